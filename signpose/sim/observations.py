"""Synthetic sign observations projected from a map (for tests, evaluation and reproduction).

The image frontend is bypassed: every map keypoint is projected into the
camera along a ground-truth flight, Gaussian pixel noise is added (as a
decoder measures it), points outside the image are dropped, and optional
faults are injected: observations given another sign's code (mis-decoding)
and false observations at random pixels (false detections).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from signpose.estimator.camera import CameraModel, pixel_from_world_point
from signpose.estimator.trajectory import Trajectory
from signpose.frontend.observations import FrameObservations, SignObservation
from signpose.maps.loader import MapSign, SignMap
from signpose.sim.trajectories import make_trajectory


@dataclass(frozen=True)
class SyntheticSettings:
    """How observations are synthesised.

    Attributes:
        sigma_px: standard deviation of the Gaussian noise on each keypoint
            coordinate [px]; also written as each observation's ``sigma_px``.
        keypoints: ``"all"`` (every keypoint the map gives) or ``"center"``.
        wrong_code_rate: share of observations given another map sign's code.
        false_rate: expected false observations per true observation (each a
            random map code with only a centre at a uniformly random pixel).
        margin_px: keypoints closer than this to the image border are dropped.
        min_depth_m: points nearer than this along the optical axis are dropped.
    """

    sigma_px: float = 0.4
    keypoints: str = "all"
    wrong_code_rate: float = 0.0
    false_rate: float = 0.0
    margin_px: float = 2.0
    min_depth_m: float = 0.5


@dataclass(frozen=True)
class SyntheticTruth:
    """What really happened in the synthesised observations (for tests and reports).

    Attributes:
        wrong_code: (frame, given code, true code) for each mis-decoded observation.
        false_obs: (frame, code) for each false observation.
    """

    wrong_code: tuple[tuple[int, str, str], ...]
    false_obs: tuple[tuple[int, str], ...]


def _sign_keypoints(sign: MapSign, which: str) -> dict[str, np.ndarray]:
    kps = sign.keypoints_world()
    if which == "center":
        return {"center": kps["center"]}
    return kps


def synthesize_observations(
    sign_map: SignMap,
    camera: CameraModel,
    trajectory: Trajectory,
    rng: np.random.Generator,
    settings: SyntheticSettings | None = None,
) -> tuple[list[FrameObservations], SyntheticTruth]:
    """Project the map along ``trajectory`` into noisy per-frame observations.

    Args:
        sign_map: the surveyed signs (their true positions).
        camera: the camera, including its distortion (pixels are raw).
        trajectory: ground-truth ``world_T_cam`` per frame.
        rng: the random generator (seeded by the caller).
        settings: noise and fault rates.

    Returns:
        (one FrameObservations per trajectory pose, the injected faults).
    """
    s = settings or SyntheticSettings()
    codes = sign_map.codes
    poses = trajectory.world_T_cam()
    stamps_ns = np.round(np.asarray(trajectory.stamps_s) * 1e9).astype(np.int64)
    names_points = [_sign_keypoints(sign, s.keypoints) for sign in sign_map.signs]
    w, h = camera.width, camera.height
    # The sigma written into each observation must be > 0 even for noise-free data.
    reported_sigma = s.sigma_px if s.sigma_px > 0 else 0.1
    frames: list[FrameObservations] = []
    wrong: list[tuple[int, str, str]] = []
    false: list[tuple[int, str]] = []
    for i, world_T_cam in enumerate(poses):
        signs: list[SignObservation] = []
        for sign, named in zip(sign_map.signs, names_points, strict=True):
            names = list(named)
            px, depth = pixel_from_world_point(camera, world_T_cam, np.array(list(named.values())))
            px = px + rng.normal(0.0, s.sigma_px, size=px.shape)
            inside = (
                (depth > s.min_depth_m)
                & (px[:, 0] >= s.margin_px)
                & (px[:, 0] <= w - 1 - s.margin_px)
                & (px[:, 1] >= s.margin_px)
                & (px[:, 1] <= h - 1 - s.margin_px)
            )
            if not inside[names.index("center")]:
                continue
            kps = {
                n: (float(p[0]), float(p[1]))
                for n, p, ok in zip(names, px, inside, strict=True)
                if ok
            }
            code = sign.code
            if s.wrong_code_rate > 0 and len(codes) > 1 and rng.random() < s.wrong_code_rate:
                others = [c for c in codes if c != sign.code]
                code = others[int(rng.integers(len(others)))]
                wrong.append((i, code, sign.code))
            radius = 4.0
            us = [p[0] for p in kps.values()]
            vs = [p[1] for p in kps.values()]
            bbox = (
                min(us) - radius,
                min(vs) - radius,
                max(us) - min(us) + 2 * radius,
                max(vs) - min(vs) + 2 * radius,
            )
            signs.append(SignObservation(code, kps, bbox, reported_sigma, 1.0))
        n_false = int(rng.binomial(len(signs), s.false_rate)) if s.false_rate > 0 else 0
        for _ in range(n_false):
            code = codes[int(rng.integers(len(codes)))]
            c = (float(rng.uniform(0, w - 1)), float(rng.uniform(0, h - 1)))
            signs.append(SignObservation(code, {"center": c}, None, reported_sigma, 0.5))
            false.append((i, code))
        frames.append(FrameObservations(i, int(stamps_ns[i]), (w, h), tuple(signs)))
    return frames, SyntheticTruth(tuple(wrong), tuple(false))


def flatten_map(sign_map: SignMap, offset_m: float = 0.0, rng: np.random.Generator | None = None):
    """A copy of ``sign_map`` with every sign moved onto the best-fit plane of the centres.

    With ``offset_m`` > 0 each sign is then pushed off that plane along its
    normal by a uniform random amount in [-offset_m, offset_m] (alternating
    signs when no ``rng`` is given), for the planarity sweep.

    Returns:
        A new SignMap.
    """
    centers = sign_map.centers_m()
    mean = centers.mean(axis=0)
    _, _, vt = np.linalg.svd(centers - mean)
    n = vt[2]
    out = []
    for k, sign in enumerate(sign_map.signs):
        c = sign.center_m - ((sign.center_m - mean) @ n) * n
        if offset_m > 0:
            d = rng.uniform(-offset_m, offset_m) if rng is not None else offset_m * (-1) ** k
            c = c + d * n
        out.append(replace(sign, center_m=c))
    return replace(sign_map, signs=tuple(out))


def paper_like_frames(
    sign_map: SignMap,
    camera: CameraModel,
    n_frames: int,
    rng: np.random.Generator,
    settings: SyntheticSettings | None = None,
    flight: str = "climb-hover-depart",
    fps: float = 30.0,
    distance_m: float = 27.0,
    seed: int = 0,
) -> tuple[list[FrameObservations], Trajectory, SyntheticTruth]:
    """A simulated flight and its observations (paper-like geometry by default).

    Returns:
        (observations per frame, ground-truth trajectory, injected faults).
    """
    gt = make_trajectory(
        flight, sign_map, n_frames=n_frames, fps=fps, distance_m=distance_m, seed=seed
    )
    frames, truth = synthesize_observations(sign_map, camera, gt, rng, settings)
    return frames, gt, truth


def drop_signs(
    frames: Sequence[FrameObservations], keep: dict[int, int], rng: np.random.Generator
) -> list[FrameObservations]:
    """Copies of ``frames`` where frame ``i`` in ``keep`` keeps only ``keep[i]`` random signs."""
    out = []
    for f in frames:
        if f.frame in keep and len(f.signs) > keep[f.frame]:
            idx = sorted(rng.choice(len(f.signs), size=keep[f.frame], replace=False).tolist())
            f = replace(f, signs=tuple(f.signs[j] for j in idx))
        out.append(f)
    return out
