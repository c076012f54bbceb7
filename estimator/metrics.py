"""Trajectory error metrics (numpy only).

Every metric compares an estimate with the ground truth at the estimate's
stamps (``ground_truth_at``): between two ground-truth poses at most
``max_gap_s`` apart (0.1 s) the ground truth is interpolated, the position
linearly and the rotation by slerp; elsewhere (before the first, after the
last, across a longer gap) the nearest ground-truth pose within ``max_dt_s``
is taken, one to one, as evo's ``associate_trajectories``. A ground truth at
the frames' own stamps (the simulator's) is therefore taken as it is, and a
denser one (a 100-200 Hz motion capture) or one on an offset clock is not
paired with a pose up to half its period away: at 5 m/s, 5 ms is 2.5 cm,
more than the smoother's error. Positions are camera centres, world frame [m].

Definitions:
    * ``mae_xyz_m``: per-axis mean absolute position error (the paper's Table 4).
    * ``ate_rmse_m``: sqrt(mean ||p_est - p_gt||^2) without alignment, and
      ``ate_rmse_aligned_m`` after the rigid SE(3) alignment (Umeyama, no scale)
      of the estimated positions onto the ground truth (evo_ape -a).
    * ``rot_rmse_deg``: RMS of the angle of ``world_R_gt^T world_R_est`` (no
      alignment), the rotation error that errors.png plots.
    * ``rpe_trans_per_m``: relative pose error, translation part, with the
      step measured in metres travelled, as ``evo_rpe tum GT EST --delta 1
      --delta_unit m --pairs_from_reference`` (consecutive pairs; note evo's
      default picks the pairs on the estimate's path, which a jittery estimate
      lengthens): walking the *ground truth* from its first associated
      pose, a checkpoint is placed each time the accumulated path length
      reaches ``delta_m`` (then the accumulator restarts); for each pair of
      consecutive checkpoints (i, j) the error is
      ``E = (gt_i^-1 gt_j)^-1 (est_i^-1 est_j)`` and its translation norm is
      taken. Reported as the RMSE over pairs divided by ``delta_m``, so it
      reads as metres of drift per metre travelled.
    * ``coverage``: estimated poses with ground truth / the reference stamps
      with ground truth: the frames (``reference_stamps_s``, e.g. every
      method's stamps together) when given, else the ground-truth poses.

``format_table`` adds, when given, each method's share of ``ok`` / ``weak`` /
``bridged`` / ``suspect`` poses over all frames (``estimator.status``): a
trajectory that covers every frame may still be mostly bridged.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass

import numpy as np
from signpose.estimator.status import PoseStatus
from signpose.estimator.trajectory import Trajectory, rotation_from_quat_xyzw


@dataclass(frozen=True)
class Metrics:
    """Errors of one estimated trajectory against ground truth.

    Attributes:
        n_matched: estimated poses with ground truth.
        coverage: n_matched / reference stamps with ground truth (see the
            module docstring).
        mae_xyz_m: (3,) per-axis mean absolute error [m].
        ate_rmse_m: ATE RMSE without alignment [m].
        ate_rmse_aligned_m: ATE RMSE after SE(3) Umeyama alignment [m].
        rpe_trans_per_m: RPE translation RMSE per metre travelled [m/m].
        rpe_pairs: number of RPE pairs.
        rot_rmse_deg: RMS rotation error without alignment [deg].
    """

    n_matched: int
    coverage: float
    mae_xyz_m: tuple[float, float, float]
    ate_rmse_m: float
    ate_rmse_aligned_m: float
    rpe_trans_per_m: float
    rpe_pairs: int
    rot_rmse_deg: float

    def to_dict(self) -> dict:
        """The metrics under their field names (the keys of report.json's ``metrics``)."""
        d = asdict(self)
        d["mae_xyz_m"] = list(self.mae_xyz_m)
        return {
            k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in d.items()
        }


def associate(stamps_est: np.ndarray, stamps_gt: np.ndarray, max_dt_s: float = 0.01):
    """Index pairs (est, gt) matched by nearest timestamp within ``max_dt_s``, one to one.

    Returns:
        ((K,) estimate indices, (K,) ground-truth indices), in estimate order.
    """
    e = np.asarray(stamps_est, dtype=float)
    g = np.asarray(stamps_gt, dtype=float)
    if len(e) == 0 or len(g) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    order = np.argsort(g)
    gs = g[order]
    pos = np.clip(np.searchsorted(gs, e), 1, len(gs) - 1) if len(gs) > 1 else np.zeros(len(e), int)
    if len(gs) > 1:
        left = gs[pos - 1]
        right = gs[pos]
        pos = np.where(np.abs(e - left) <= np.abs(e - right), pos - 1, pos)
    cand = order[pos]
    ok = np.abs(g[cand] - e) <= max_dt_s
    ie, ig = np.nonzero(ok)[0], cand[ok]
    # One to one: keep the first estimate for each ground-truth pose.
    _, first = np.unique(ig, return_index=True)
    keep = np.sort(first)
    return ie[keep], ig[keep]


def umeyama_se3(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising sum ||dst - (R src + t)||^2 (no scale).

    Args:
        src: (N, 3) points; dst: (N, 3) points.

    Returns:
        ((3, 3) R, (3,) t).
    """
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    cov = (dst - mu_d).T @ (src - mu_s) / len(src)
    U, _, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    return R, mu_d - R @ mu_s


def _rpe_pairs(gt_positions: np.ndarray, delta_m: float) -> list[tuple[int, int]]:
    ids = []
    acc = 0.0
    for i in range(len(gt_positions)):
        if i > 0:
            acc += float(np.linalg.norm(gt_positions[i] - gt_positions[i - 1]))
        if i == 0 or acc >= delta_m:
            ids.append(i)
            acc = 0.0
    return list(zip(ids[:-1], ids[1:], strict=True))


def rpe_translation(
    est_T: np.ndarray, gt_T: np.ndarray, delta_m: float = 1.0
) -> tuple[np.ndarray, int]:
    """Translation errors [m] of relative poses over ``delta_m`` of ground-truth path."""
    pairs = _rpe_pairs(gt_T[:, :3, 3], delta_m)
    errs = []
    for i, j in pairs:
        rel_gt = np.linalg.inv(gt_T[i]) @ gt_T[j]
        rel_est = np.linalg.inv(est_T[i]) @ est_T[j]
        E = np.linalg.inv(rel_gt) @ rel_est
        errs.append(float(np.linalg.norm(E[:3, 3])))
    return np.asarray(errs), len(pairs)


GT_MAX_GAP_S = 0.1  # the ground truth is interpolated across gaps up to this [s]


def _slerp_xyzw(q0: np.ndarray, q1: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(K, 4) rotations between (K, 4) unit quaternions q0 and q1 at fractions (K,) w."""
    q0 = q0 / np.linalg.norm(q0, axis=1, keepdims=True)
    q1 = q1 / np.linalg.norm(q1, axis=1, keepdims=True)
    dot = np.sum(q0 * q1, axis=1)
    q1 = np.where((dot < 0)[:, None], -q1, q1)  # the shorter way round
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    small = theta < 1e-8
    sin_t = np.where(small, 1.0, np.sin(theta))
    a = np.where(small, 1.0 - w, np.sin((1.0 - w) * theta) / sin_t)
    b = np.where(small, w, np.sin(w * theta) / sin_t)
    q = a[:, None] * q0 + b[:, None] * q1
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def ground_truth_at(
    gt: Trajectory,
    stamps_s: np.ndarray,
    max_dt_s: float = 0.01,
    max_gap_s: float = GT_MAX_GAP_S,
) -> tuple[np.ndarray, np.ndarray]:
    """The ground-truth poses at given stamps (see the module docstring).

    Args:
        gt: the ground truth.
        stamps_s: (N,) the stamps to look up [s].
        max_dt_s: nearest-pose tolerance where no interpolation applies [s].
        max_gap_s: largest ground-truth gap interpolated across [s].

    Returns:
        ((K,) indices into ``stamps_s`` that have ground truth, in order,
        (K, 4, 4) the ground truth's world_T_cam there).
    """
    e = np.asarray(stamps_s, dtype=float).reshape(-1)
    if len(e) == 0 or len(gt) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 4, 4))
    order = np.argsort(gt.stamps_s, kind="stable")
    g = gt.stamps_s[order]
    p, q = gt.world_t_cam[order], gt.quat_xyzw[order]
    j = np.searchsorted(g, e, side="right")  # g[j - 1] <= e < g[j]
    exact = (j >= 1) & (g[np.maximum(j - 1, 0)] == e)
    inner = (j >= 1) & (j < len(g)) & ~exact
    lo, hi = np.maximum(j - 1, 0), np.minimum(j, len(g) - 1)
    inner &= (g[hi] - g[lo]) <= max_gap_s * (1.0 + 1e-9)  # 0.3 - 0.2 > 0.1 in floats
    T = np.tile(np.eye(4), (len(e), 1, 1))
    have = exact | inner
    # Taken as they are: the ground truth's own poses at its own stamps.
    k = lo[exact]
    T[exact, :3, 3] = p[k]
    T[exact, :3, :3] = rotation_from_quat_xyzw(q[k])
    if inner.any():
        a, b = lo[inner], hi[inner]
        w = (e[inner] - g[a]) / (g[b] - g[a])
        T[inner, :3, 3] = p[a] + w[:, None] * (p[b] - p[a])
        T[inner, :3, :3] = rotation_from_quat_xyzw(_slerp_xyzw(q[a], q[b], w))
    rest = np.nonzero(~have)[0]
    if len(rest):
        ie, ig = associate(e[rest], gt.stamps_s, max_dt_s)
        if len(ie):
            T_gt = gt.world_T_cam()
            T[rest[ie]] = T_gt[ig]
            have[rest[ie]] = True
    idx = np.nonzero(have)[0]
    return idx, T[idx]


def compute_metrics(
    est: Trajectory,
    gt: Trajectory,
    max_dt_s: float = 0.01,
    delta_m: float = 1.0,
    reference_stamps_s: np.ndarray | None = None,
) -> Metrics:
    """All metrics of ``est`` against ``gt`` (see the module docstring).

    Args:
        reference_stamps_s: (F,) the frames' stamps [s], coverage's
            denominator (those with ground truth); None: the ground-truth poses.
    """
    ie, gt_T = ground_truth_at(gt, est.stamps_s, max_dt_s)
    n = len(ie)
    if reference_stamps_s is None:
        n_ref = len(gt)
    else:
        ref = np.unique(np.asarray(reference_stamps_s, dtype=float))
        n_ref = len(ground_truth_at(gt, ref, max_dt_s)[0])
    nan = float("nan")
    if n == 0:
        return Metrics(
            n_matched=0,
            coverage=0.0,
            mae_xyz_m=(nan, nan, nan),
            ate_rmse_m=nan,
            ate_rmse_aligned_m=nan,
            rpe_trans_per_m=nan,
            rpe_pairs=0,
            rot_rmse_deg=nan,
        )
    pe, pg = est.world_t_cam[ie], gt_T[:, :3, 3]
    d = pe - pg
    mae = tuple(float(x) for x in np.mean(np.abs(d), axis=0))
    ate = float(np.sqrt(np.mean(np.sum(d * d, axis=1))))
    if n >= 3:
        R, t = umeyama_se3(pe, pg)
        da = pe @ R.T + t - pg
        ate_al = float(np.sqrt(np.mean(np.sum(da * da, axis=1))))
    else:
        ate_al = nan
    errs, n_pairs = rpe_translation(est.world_T_cam()[ie], gt_T, delta_m)
    rpe = float(np.sqrt(np.mean(errs**2)) / delta_m) if n_pairs else nan
    rot = rotation_errors_deg(est.world_R_cam()[ie], gt_T[:, :3, :3])
    return Metrics(
        n_matched=n,
        coverage=n / max(n_ref, n),
        mae_xyz_m=mae,
        ate_rmse_m=ate,
        ate_rmse_aligned_m=ate_al,
        rpe_trans_per_m=rpe,
        rpe_pairs=n_pairs,
        rot_rmse_deg=float(np.sqrt(np.mean(rot**2))),
    )


def rotation_errors_deg(world_R_est: np.ndarray, world_R_gt: np.ndarray) -> np.ndarray:
    """(N,) angle of ``world_R_gt^T world_R_est`` [deg] for (N, 3, 3) rotations."""
    # trace(A^T B) = sum of the elementwise product; angle = arccos((trace - 1) / 2).
    cos = (np.einsum("nij,nij->n", world_R_est, world_R_gt) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


STATUS_COLUMNS = tuple(s.value for s in PoseStatus)  # ok, weak, bridged, suspect


def format_table(
    rows: Mapping[str, Metrics], status: Mapping[str, Mapping[str, float]] | None = None
) -> str:
    """A plain-text table, one row per method (the paper's Table 4 errors and more).

    Args:
        rows: method -> its metrics.
        status: method -> share of frames with each pose status token
            (``signpose.io.results.status_shares``); None leaves the status
            columns out, a method missing from it shows ``-``.
    """
    head = (
        f"{'method':<10} {'MAE x':>8} {'MAE y':>8} {'MAE z':>8} {'ATE':>8} "
        f"{'ATE(al)':>8} {'RPE/m':>8} {'rot deg':>8} {'cover':>7}"
    )
    if status is not None:
        head += "".join(f" {t:>7}" for t in STATUS_COLUMNS)
    lines = [head, "-" * len(head)]

    def f(x: float) -> str:
        return f"{x:8.4f}" if np.isfinite(x) else f"{'-':>8}"

    for name, m in rows.items():
        line = (
            f"{name:<10} {f(m.mae_xyz_m[0])} {f(m.mae_xyz_m[1])} {f(m.mae_xyz_m[2])} "
            f"{f(m.ate_rmse_m)} {f(m.ate_rmse_aligned_m)} {f(m.rpe_trans_per_m)} "
            f"{f(m.rot_rmse_deg)} {m.coverage:7.1%}"
        )
        if status is not None:
            shares = status.get(name)
            line += "".join(
                f" {shares.get(t, 0.0):7.1%}" if shares is not None else f" {'-':>7}"
                for t in STATUS_COLUMNS
            )
        lines.append(line)
    return "\n".join(lines)
