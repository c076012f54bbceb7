"""Simulated UAV flights in front of a sign map (ground truth for the simulator and evaluations).

Every trajectory looks at the map's signs from the side their normals face,
25 to 30 m away by default (the paper's simulated set), with the small yaw,
pitch and roll wobble of a real multirotor. Poses are ``world_T_cam`` with
the OpenCV camera axes (x right, y down, z forward).

Timing: each trajectory is a path (one *pass*) with its own speed profile
(smooth starts and stops, the hover of climb-hover-depart). Given a cruise
speed (``speed_mps``: the mean path speed, path length / pass time) a flight
of N frames covers the first N / fps seconds of the flight; a flight longer
than one pass keeps flying: the orbit repeats (its path is closed and
periodic), climb-hover-depart and the lawnmower fly their path back and forth
(they stop at both ends, so the turn is smooth: depart, come back, descend;
sweep up the pylon, sweep back down). Without a speed the whole path is
squeezed into the frames once (the library's old behaviour, which the
evaluations keep).
"""

from __future__ import annotations

import math

import numpy as np

from signpose.estimator.trajectory import Trajectory
from signpose.maps.loader import SignMap

TRAJECTORIES = ("climb-hover-depart", "orbit", "lawnmower")

# Each trajectory's default cruise speed, the mean path speed [m/s]. climb-hover-depart
# keeps the speed its default flight (210 frames at 30 fps over the bundled map) has
# always flown (peak 3.1 m/s; it hovers for a fifth of the pass); orbit and lawnmower
# fly at inspection speeds (peaks about 6 m/s).
DEFAULT_SPEED_MPS = {"climb-hover-depart": 1.55, "orbit": 4.0, "lawnmower": 3.0}
MAX_SPEED_MPS = 30.0
# How a flight longer than one pass goes on: "repeat" (closed paths) or "back and forth".
CONTINUATION = {
    "climb-hover-depart": "back and forth",
    "orbit": "repeat",
    "lawnmower": "back and forth",
}
# Samples of one pass for its length.
_LENGTH_SAMPLES = 4001


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def site_frame(sign_map: SignMap) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The site's axes: what flights look at and the pylon is built around.

    Returns:
        (mean sign centre (3,) [m], horizontal unit facing direction of the
        signs, horizontal unit 'right' of a viewer facing them, world up),
        all in the world frame.
    """
    centers = sign_map.centers_m()
    center = centers.mean(axis=0)
    normals = [s.normal for s in sign_map.signs if s.normal is not None]
    if normals:
        facing = np.mean(normals, axis=0)
    else:
        # Centre-only map: the direction of least spread of the centres.
        _, _, vt = np.linalg.svd(centers - center)
        facing = vt[-1].copy()
    facing[2] = 0.0
    if np.linalg.norm(facing) < 1e-6:
        facing = np.array([0.0, 1.0, 0.0])
    facing /= np.linalg.norm(facing)
    z_up = np.array([0.0, 0.0, 1.0])
    right = np.cross(z_up, facing)  # horizontal: the right of a viewer facing the signs
    right /= np.linalg.norm(right)
    return center, facing, right, z_up


def look_at(cam_pos: np.ndarray, target: np.ndarray, world_up: np.ndarray) -> np.ndarray:
    """(3, 3) world_R_cam for a camera at ``cam_pos`` looking at ``target``, image up ~ world up."""
    z = target - cam_pos
    z = z / np.linalg.norm(z)
    x = np.cross(z, world_up)
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def _path(
    name: str, s: np.ndarray, sign_map: SignMap, distance_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Positions (N, 3) and look-at targets (N, 3) [m] at path parameters ``s`` in [0, 1]."""
    center, facing, right, up = site_frame(sign_map)
    span_z = float(np.ptp(sign_map.centers_m()[:, 2])) if len(sign_map.signs) > 1 else 4.0
    d = distance_m
    n = len(s)
    if name == "climb-hover-depart":
        # Paper Fig. 13: climb in front of the pylon, hover, back away while descending.
        climb = _smoothstep(s / 0.4)
        depart = _smoothstep((s - 0.6) / 0.4)
        height = -0.45 * span_z + 0.55 * span_z * climb - 0.35 * span_z * depart
        back = d - 1.5 + 1.5 * climb + 3.5 * depart
        lateral = 1.0 - 1.0 * climb - 1.5 * depart
        pos = center + np.outer(back, facing) + np.outer(lateral, right) + np.outer(height, up)
        target = np.tile(center, (n, 1))
    elif name == "orbit":
        angle = np.radians(35.0) * np.sin(2 * np.pi * s)
        radius = d + 1.5 * np.sin(4 * np.pi * s)
        height = 0.15 * span_z * np.sin(2 * np.pi * s + 0.7)
        horiz = np.outer(np.cos(angle), facing) + np.outer(np.sin(angle), right)
        pos = center + horiz * radius[:, None] + np.outer(height, up)
        target = np.tile(center, (n, 1))
    else:  # lawnmower: horizontal passes at four heights, facing the pylon
        rows = 4
        row = np.minimum((s * rows).astype(int), rows - 1)
        within = s * rows - row
        sweep = np.where(row % 2 == 0, within, 1 - within)
        lateral = -4.0 + 8.0 * _smoothstep(sweep)
        height = (
            -0.4 + 0.8 * (row + _smoothstep(np.clip((within - 0.85) / 0.15, 0, 1))) / rows
        ) * span_z
        pos = center + d * facing + np.outer(lateral, right) + np.outer(height, up)
        target = center + np.outer(0.6 * lateral, right) + np.outer(0.6 * height, up)
    return pos, target


def path_length_m(name: str, sign_map: SignMap, distance_m: float = 27.0) -> float:
    """Length of one pass of trajectory ``name`` over ``sign_map`` [m]."""
    _check_name(name)
    pos, _ = _path(name, np.linspace(0.0, 1.0, _LENGTH_SAMPLES), sign_map, distance_m)
    return float(np.linalg.norm(np.diff(pos, axis=0), axis=1).sum())


def pass_parameter(name: str, t_s: np.ndarray, pass_s: float) -> np.ndarray:
    """Path parameter in [0, 1] at flight times ``t_s`` [s], one pass taking ``pass_s``.

    Past the first pass: repeated for the orbit, back and forth for the others
    (``CONTINUATION``).
    """
    u = np.asarray(t_s, dtype=float) / pass_s
    if CONTINUATION[name] == "repeat":
        return u - np.floor(u)
    # Triangle wave: 0 -> 1 -> 0 -> ...
    return 1.0 - np.abs(np.mod(u, 2.0) - 1.0)


def speed_stats(traj: Trajectory) -> tuple[float, float]:
    """(mean, peak) speed of a trajectory's camera [m/s] from its poses.

    Mean: distance flown / time flown; peak: the fastest frame-to-frame step.
    Both 0 for a single pose.
    """
    if len(traj) < 2:
        return 0.0, 0.0
    steps = np.linalg.norm(np.diff(traj.world_t_cam, axis=0), axis=1)
    dt = np.diff(traj.stamps_s)
    return float(steps.sum() / (traj.stamps_s[-1] - traj.stamps_s[0])), float(np.max(steps / dt))


def _check_name(name: str) -> None:
    if name not in TRAJECTORIES:
        raise ValueError(f"unknown trajectory {name!r}; choose from {', '.join(TRAJECTORIES)}")


def make_trajectory(
    name: str,
    sign_map: SignMap,
    n_frames: int = 210,
    fps: float = 30.0,
    distance_m: float = 27.0,
    seed: int = 0,
    wobble_deg: float = 1.5,
    speed_mps: float | None = None,
) -> Trajectory:
    """A simulated flight.

    Args:
        name: one of ``TRAJECTORIES``.
        sign_map: the signs the flight looks at.
        n_frames: number of poses.
        fps: frame rate [Hz]; stamps are frame / fps [s].
        distance_m: nominal distance from the signs [m].
        seed: seeds the wobble phases.
        wobble_deg: amplitude of the yaw/pitch/roll wobble [deg].
        speed_mps: cruise speed, the mean path speed [m/s]: the frames cover the
            first n_frames / fps seconds of the flight at that speed (passes
            continue as ``CONTINUATION`` says). None: the whole path once over
            the n_frames, whatever speed that takes.

    Returns:
        The ground-truth trajectory (world_T_cam per frame).
    """
    _check_name(name)
    rng = np.random.default_rng(seed)
    up = site_frame(sign_map)[3]
    if speed_mps is None:
        s = np.linspace(0.0, 1.0, n_frames)
        t = s * n_frames / fps  # the wobble's clock, as it always was
    else:
        t = np.arange(n_frames) / fps
        s = pass_parameter(name, t, path_length_m(name, sign_map, distance_m) / speed_mps)
    pos, target = _path(name, s, sign_map, distance_m)
    # Multirotor wobble: a few incommensurate sinusoids per axis.
    freqs = rng.uniform(0.2, 1.5, size=(3, 3))
    phases = rng.uniform(0, 2 * np.pi, size=(3, 3))
    amps = np.radians(wobble_deg) * np.array([1.0, 0.6, 0.4])
    poses = np.tile(np.eye(4), (n_frames, 1, 1))
    for i in range(n_frames):
        R = look_at(pos[i], target[i], up)
        ang = amps[:, None] * np.sin(2 * np.pi * freqs * t[i] + phases)
        yaw, pitch, roll = ang.sum(axis=1) / 3.0
        # Yaw about world up, pitch about the camera x axis, roll about the optical axis.
        R = (
            _rot(up, yaw)
            @ R
            @ _rot(np.array([1.0, 0, 0]), pitch)
            @ _rot(np.array([0, 0, 1.0]), roll)
        )
        poses[i, :3, :3] = R
        poses[i, :3, 3] = pos[i]
    return Trajectory.from_matrices(np.arange(n_frames) / fps, poses)
