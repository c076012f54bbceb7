"""Ground truth for comparisons: the TUM file shifted by ``--gt-offset`` and its time check.

Stamps are seconds on the ground truth's own clock; ``offset_s`` is added to
them so that they read on the trajectory's clock (e.g. a video stamped from its
epoch ``creation_time`` against a motion-capture file starting at 0).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from signpose.core.errors import InputError
from signpose.estimator.metrics import ground_truth_at
from signpose.estimator.trajectory import Trajectory
from signpose.io.tum import read_tum

# Share of the trajectory's time span the ground truth must cover (issue 13 item 6):
# below it the metrics describe a few poses or none (a table of '-', RMSE nan).
GT_MIN_TIME_OVERLAP = 0.5


def read_ground_truth(path: str | Path, offset_s: float = 0.0) -> Trajectory:
    """The ground truth TUM file with ``offset_s`` [s] added to its stamps (``--gt-offset``).

    Two poses at one time are refused (InputError): the comparison would take
    either one for the frame at that time.
    """
    gt = read_tum(path)
    order = np.argsort(gt.stamps_s, kind="stable")
    same = np.flatnonzero(np.diff(gt.stamps_s[order]) == 0.0)
    if len(same):
        t = gt.stamps_s[order[same[0]]]
        raise InputError(
            f"{path}: {len(same)} time(s) given twice (first: {t:.9f} s); "
            "each ground-truth pose needs its own time: remove the repeated lines"
        )
    if offset_s == 0.0:
        return gt
    return Trajectory(gt.stamps_s + float(offset_s), gt.world_t_cam, gt.quat_xyzw)


def check_time_overlap(
    stamps_s: np.ndarray, source: str | Path, gt: Trajectory, gt_path: str | Path
) -> None:
    """Raise InputError when ``gt`` shares no stamps with, or covers under half of, a trajectory.

    Args:
        stamps_s: (N,) the trajectory's (or the frames') times [s].
        source: the file those times come from (named in the message).
        gt: the ground truth, offset already applied.
        gt_path: its file (named in the message).
    """
    e = np.asarray(stamps_s, dtype=float)
    g = np.asarray(gt.stamps_s, dtype=float)
    if len(e) == 0 or len(g) == 0:
        return
    e0, e1, g0, g1 = float(e.min()), float(e.max()), float(g.min()), float(g.max())
    shared = len(ground_truth_at(gt, e)[0])
    covered = max(0.0, min(e1, g1) - max(e0, g0))
    share = covered / (e1 - e0) if e1 > e0 else float(g0 <= e0 <= g1)
    if shared > 0 and share >= GT_MIN_TIME_OVERLAP:
        return
    raise InputError(
        f"{gt_path}: ground truth spans {g0:.3f} to {g1:.3f} s but {source} spans "
        f"{e0:.3f} to {e1:.3f} s ({share:.0%} of it covered, {shared} shared stamps); "
        f"pass the ground truth of this flight, or --gt-offset SECONDS for a known clock "
        f"shift (start to start: {e0 - g0:.3f})"
    )
