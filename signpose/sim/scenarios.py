"""The estimator's fault scenario: a figure-eight pass with a two-sign stretch and wrong codes.

Issue 12's test flight, rebuilt: a figure-eight 22-32 m in front of the
pylon, nine signs of the demo map reduced to their centres (an un-oriented,
centre-only map), 0.3 px keypoint noise, a stretch of frames in which only
two signs are seen with a wrong code on the 4th frame of it, and, with
``faults``, 5 % of all observations given another sign's code and 2 % false
observations at random pixels.

World frame: the map's (z up); poses ``world_T_cam`` with OpenCV camera axes.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from signpose.estimator.camera import CameraModel, pinhole_camera
from signpose.estimator.trajectory import Trajectory
from signpose.frontend.observations import FrameObservations, SignObservation
from signpose.maps.loader import SignMap, bundled_map_path, load_map
from signpose.sim.observations import SyntheticSettings, synthesize_observations
from signpose.sim.trajectories import look_at, site_frame


@dataclass(frozen=True)
class ScenarioSettings:
    """The fault scenario's knobs (defaults: issue 12's numbers).

    Attributes:
        n_frames: frames at ``fps``.
        fps: frame rate [Hz].
        n_signs: the first this many signs of the demo map.
        near_m / far_m: closest and farthest distance from the map centre [m].
        lateral_m: half width of the figure-eight across the face [m].
        sigma_px: keypoint noise [px].
        stretch_start / stretch_frames: the frames that see only ``stretch_codes``.
        stretch_codes: the two signs seen in the stretch.
        stretch_wrong_frame: offset in the stretch of the frame whose first
            sign is given ``stretch_wrong_code`` (-1: none).
        wrong_code_rate: share of the other observations given another sign's code.
        false_rate: false observations per true observation.
    """

    n_frames: int = 300
    fps: float = 30.0
    n_signs: int = 9
    near_m: float = 22.0
    far_m: float = 32.0
    lateral_m: float = 6.0
    sigma_px: float = 0.3
    stretch_start: int = 150
    stretch_frames: int = 20
    stretch_codes: tuple[str, str] = ("0001", "1010")
    stretch_wrong_frame: int = 3
    stretch_wrong_code: str = "1100"
    wrong_code_rate: float = 0.05
    false_rate: float = 0.02


@dataclass(frozen=True)
class Scenario:
    """A built scenario.

    Attributes:
        sign_map: the centre-only map (survey = truth).
        camera: 1920x1080, 60 deg horizontal field of view, no distortion.
        frames: the observations (raw pixels).
        truth: ground-truth poses.
        wrong_code: (frame, given code, true code) of every wrong code.
        false_obs: (frame, code) of every false observation.
        stretch: (first, last + 1) frames of the two-sign stretch.
    """

    sign_map: SignMap
    camera: CameraModel
    frames: list[FrameObservations]
    truth: Trajectory
    wrong_code: tuple[tuple[int, str, str], ...]
    false_obs: tuple[tuple[int, str], ...]
    stretch: tuple[int, int]


def centre_only_map(n_signs: int) -> SignMap:
    """The first ``n_signs`` signs of the demo map without their orientation."""
    demo = load_map(bundled_map_path())
    signs = tuple(replace(s, normal=None, up=None) for s in demo.signs[:n_signs])
    return replace(demo, signs=signs)


def figure_eight(sign_map: SignMap, s: ScenarioSettings) -> Trajectory:
    """A figure-eight in front of the map, looking at its centre, between near_m and far_m."""
    center, facing, right, up = site_frame(sign_map)
    t = np.arange(s.n_frames) / s.fps
    phase = 2 * np.pi * t / (s.n_frames / s.fps)
    mid, half = 0.5 * (s.near_m + s.far_m), 0.5 * (s.far_m - s.near_m)
    distance = mid + half * np.sin(2 * phase)
    lateral = s.lateral_m * np.sin(phase)
    height = 1.5 * np.sin(phase + 0.5)
    pos = center + np.outer(distance, facing) + np.outer(lateral, right) + np.outer(height, up)
    poses = np.tile(np.eye(4), (s.n_frames, 1, 1))
    for i in range(s.n_frames):
        poses[i, :3, :3] = look_at(pos[i], center, up)
        poses[i, :3, 3] = pos[i]
    return Trajectory.from_matrices(t, poses)


def _restrict(
    frames: Sequence[FrameObservations], s: ScenarioSettings
) -> tuple[list[FrameObservations], tuple[int, str, str] | None]:
    """Only the stretch codes inside the stretch; the planted wrong code."""
    out = list(frames)
    planted = None
    for k in range(s.stretch_frames):
        i = s.stretch_start + k
        signs = [o for o in out[i].signs if o.code in s.stretch_codes]
        if k == s.stretch_wrong_frame and signs:
            planted = (i, s.stretch_wrong_code, signs[0].code)
            signs[0] = replace(signs[0], code=s.stretch_wrong_code)
        out[i] = replace(out[i], signs=tuple(signs))
    return out, planted


def _inject(
    frames: list[FrameObservations],
    sign_map: SignMap,
    camera: CameraModel,
    s: ScenarioSettings,
    rng: np.random.Generator,
) -> tuple[list[FrameObservations], list[tuple[int, str, str]], list[tuple[int, str]]]:
    """Wrong codes and false observations at the scenario's rates."""
    codes = sign_map.codes
    wrong, false = [], []
    out = []
    for f in frames:
        signs = []
        for o in f.signs:
            if rng.random() < s.wrong_code_rate:
                others = [c for c in codes if c != o.code]
                given = others[int(rng.integers(len(others)))]
                wrong.append((f.frame, given, o.code))
                o = replace(o, code=given)
            signs.append(o)
        for _ in range(int(rng.binomial(len(f.signs), s.false_rate))):
            code = codes[int(rng.integers(len(codes)))]
            uv = (float(rng.uniform(0, camera.width - 1)), float(rng.uniform(0, camera.height - 1)))
            signs.append(SignObservation(code, {"center": uv}, None, s.sigma_px, 0.5))
            false.append((f.frame, code))
        out.append(replace(f, signs=tuple(signs)))
    return out, wrong, false


def build_scenario(
    rng: np.random.Generator, faults: bool = True, settings: ScenarioSettings | None = None
) -> Scenario:
    """The scenario's flight; without ``faults`` the stretch stays but no code is wrong."""
    s = settings or ScenarioSettings()
    if not faults:
        s = replace(s, stretch_wrong_frame=-1, wrong_code_rate=0.0, false_rate=0.0)
    sign_map = centre_only_map(s.n_signs)
    camera = pinhole_camera(1920, 1080, 60.0)
    truth = figure_eight(sign_map, s)
    syn = SyntheticSettings(sigma_px=s.sigma_px, keypoints="center")
    frames, _ = synthesize_observations(sign_map, camera, truth, rng, syn)
    frames, planted = _restrict(frames, s)
    frames, wrong, false = _inject(frames, sign_map, camera, s, rng)
    if planted is not None:
        wrong.append(planted)
    return Scenario(
        sign_map=sign_map,
        camera=camera,
        frames=frames,
        truth=truth,
        wrong_code=tuple(sorted(wrong)),
        false_obs=tuple(false),
        stretch=(s.stretch_start, s.stretch_start + s.stretch_frames),
    )
