"""TUM trajectory files: the one module that reads and writes them.

One pose per line, ``t x y z qx qy qz qw`` separated by single spaces: ``t`` in
seconds, position of the camera in the world frame [m], orientation
``world_R_cam`` as a unit quaternion with w last. ``#`` lines are comments.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from signpose.core.errors import InputError
from signpose.core.fileio import atomic_write
from signpose.estimator.trajectory import Trajectory

# Larger numbers are damage, not data: 1e12 s is 31,000 years, 1e12 m far past the Moon.
MAX_ABS_VALUE = 1e12


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM file; InputError names the file and line on failure."""
    p = Path(path)
    try:
        lines = p.read_bytes().decode("utf-8").splitlines()
    except FileNotFoundError:
        raise InputError(f"{p}: trajectory file not found") from None
    except IsADirectoryError:
        raise InputError(f"{p}: is a folder; pass the trajectory file") from None
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
        if not all(abs(v) <= MAX_ABS_VALUE for v in row):  # also NaN and inf
            raise InputError(f"{p}: line {lineno}: a value is not finite or beyond 1e12")
        if np.linalg.norm(row[4:]) < 1e-9:
            raise InputError(f"{p}: line {lineno}: zero quaternion")
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


def write_tum(path: str | Path, traj: Trajectory, comments: tuple[str, ...] = ()) -> None:
    """Write ``traj`` as TUM (atomically), after ``comments`` as ``#`` lines (one line each)."""
    with atomic_write(path) as f:
        for comment in comments:
            f.write("# " + " ".join(comment.split()) + "\n")
        for line in tum_lines(traj):
            f.write(line + "\n")
