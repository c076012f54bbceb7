"""Units, time stamps and frame conventions that every layer shares.

Frames (written down here once; modules name them in variables, ``world_T_cam``):
    world   the map's frame: right-handed, z up, metres (``maps/SCHEMA.md``).
    sign    a sign's own frame: origin at the disc centre, x right, y up toward the
            directional rectangle, z out of the face (``signpose.frontend.sign``).
    cam     OpenCV's and gtsam's camera frame: x right, y down, z forward.
    pixel   u right, v down, pixel centres at integer coordinates.

Time: a frame's stamp is an integer ``stamp_ns`` [ns]; trajectories carry float
seconds ``stamps_s``. Durations measured for reports are milliseconds ``*_ms``.
Quaternions are named by their layout, ``quat_xyzw`` or ``quat_wxyz``.
"""

from __future__ import annotations

import numpy as np

NS_PER_S = 1_000_000_000
MS_PER_S = 1_000.0


def stamp_ns_from_s(stamp_s: float) -> int:
    """Seconds -> integer nanoseconds, rounded to the nearest."""
    return int(round(float(stamp_s) * NS_PER_S))


def stamps_ns_from_s(stamps_s: np.ndarray) -> np.ndarray:
    """(N,) seconds -> (N,) int64 nanoseconds, rounded to the nearest."""
    return np.round(np.asarray(stamps_s, dtype=np.float64) * NS_PER_S).astype(np.int64)


def s_from_stamp_ns(stamp_ns: int) -> float:
    """Integer nanoseconds -> seconds."""
    return int(stamp_ns) / NS_PER_S


def s_from_stamps_ns(stamps_ns: np.ndarray) -> np.ndarray:
    """(N,) integer nanoseconds -> (N,) float64 seconds."""
    return np.asarray(stamps_ns, dtype=np.int64) / NS_PER_S


def ms_from_s(duration_s: float) -> float:
    """A duration in seconds -> milliseconds."""
    return float(duration_s) * MS_PER_S
