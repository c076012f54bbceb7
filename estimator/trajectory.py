"""Camera trajectories: timed poses ``world_T_cam`` and quaternion conversions.

A pose is ``world_T_cam``: the camera centre in the world frame [m] and the
rotation from camera to world, stored as a unit quaternion ``quat_xyzw`` (w
last). The TUM file format lives in ``signpose.io.tum``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Trajectory:
    """A timed sequence of camera poses in the world frame.

    Attributes:
        stamps_s: (N,) times [s].
        world_t_cam: (N, 3) camera centres in the world frame [m].
        quat_xyzw: (N, 4) rotation world_R_cam as unit quaternions, w last.
    """

    stamps_s: np.ndarray
    world_t_cam: np.ndarray
    quat_xyzw: np.ndarray

    def __len__(self) -> int:
        return len(self.stamps_s)

    def world_R_cam(self) -> np.ndarray:
        """(N, 3, 3) rotation matrices."""
        return rotation_from_quat_xyzw(self.quat_xyzw)

    def world_T_cam(self) -> np.ndarray:
        """(N, 4, 4) poses."""
        T = np.tile(np.eye(4), (len(self), 1, 1))
        T[:, :3, :3] = self.world_R_cam()
        T[:, :3, 3] = self.world_t_cam
        return T

    @staticmethod
    def from_matrices(stamps_s: np.ndarray, world_T_cam: np.ndarray) -> Trajectory:
        T = np.asarray(world_T_cam, dtype=float).reshape(-1, 4, 4)
        return Trajectory(
            np.asarray(stamps_s, dtype=float).reshape(-1),
            T[:, :3, 3].copy(),
            quat_xyzw_from_rotation(T[:, :3, :3]),
        )


def rotation_from_quat_xyzw(q: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (x, y, z, w) to (N, 3, 3) rotation matrices."""
    q = np.asarray(q, dtype=float).reshape(-1, 4)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    x, y, z, w = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def quat_xyzw_from_rotation(R: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations to (N, 4) unit quaternions (x, y, z, w) with w >= 0."""
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    out = np.empty((len(R), 4))
    for i, m in enumerate(R):
        tr = m[0, 0] + m[1, 1] + m[2, 2]
        if tr > 0:
            s = 2.0 * np.sqrt(tr + 1.0)
            q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, s / 4]
        elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
            q = [s / 4, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
        elif m[1, 1] > m[2, 2]:
            s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
            q = [(m[0, 1] + m[1, 0]) / s, s / 4, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
            q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, s / 4, (m[1, 0] - m[0, 1]) / s]
        q = np.asarray(q)
        q /= np.linalg.norm(q)
        out[i] = -q if q[3] < 0 else q
    return out
