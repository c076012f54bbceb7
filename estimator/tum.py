"""Trajectories and the TUM file format (the one module that reads and writes TUM).

TUM: one pose per line, ``t x y z qx qy qz qw``, single spaces, t in seconds,
the pose being ``world_T_cam`` (position of the camera centre in the world,
rotation from camera to world, quaternion w last). ``#`` lines are comments.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from signpose.core.errors import InputError
from signpose.core.fileio import atomic_write


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


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM file; InputError names the file and line on failure."""
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        raise InputError(f"{p}: trajectory file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read trajectory file ({exc})") from None
    rows = []
    for lineno, line in enumerate(lines, start=1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        parts = s.replace(",", " ").split()
        if len(parts) != 8:
            raise InputError(f"{p}: line {lineno}: expected 't x y z qx qy qz qw' (8 numbers)")
        try:
            row = [float(x) for x in parts]
        except ValueError:
            raise InputError(f"{p}: line {lineno}: not a number") from None
        if not np.all(np.isfinite(row)) or np.linalg.norm(row[4:]) < 1e-9:
            raise InputError(f"{p}: line {lineno}: non-finite value or zero quaternion")
        rows.append(row)
    if not rows:
        raise InputError(f"{p}: trajectory file has no poses")
    a = np.array(rows)
    q = a[:, 4:8] / np.linalg.norm(a[:, 4:8], axis=1, keepdims=True)
    return Trajectory(a[:, 0], a[:, 1:4], q)


def tum_lines(traj: Trajectory) -> list[str]:
    out = []
    for t, p, q in zip(traj.stamps_s, traj.world_t_cam, traj.quat_xyzw, strict=True):
        vals = [f"{t:.9f}"] + [f"{v:.6f}" for v in p] + [f"{v:.9f}" for v in q]
        out.append(" ".join(vals))
    return out


def write_tum(path: str | Path, traj: Trajectory) -> None:
    """Write ``traj`` as TUM (atomically)."""
    with atomic_write(path) as f:
        for line in tum_lines(traj):
            f.write(line + "\n")
