"""Result plots as PNG (matplotlib's object API on the Agg canvas), each written atomically.

World frame: the map's, z up, metres. Trajectories are ``world_T_cam`` per
stamp; frames without an estimate carry NaN positions and leave gaps.

Thread safety: every figure is a ``matplotlib.figure.Figure`` with its own
``FigureCanvasAgg``; pyplot's global figure registry and backend switch are
never touched, so two flights in one Dask worker process (several threads)
each draw their own figures. The object API alone is not enough: matplotlib
keeps one mathtext parser per process (log-axis tick labels such as
``$\\mathdefault{10^{-2}}$`` go through it) and it fails with
``ParseException`` / ``IndexError`` when two threads lay out text at once.
So the step that lays out and renders text (``savefig``) holds
``_RENDER_LOCK``; building the artists runs in parallel. Every figure's layout
is fixed (``_LAYOUTS``), not measured by ``tight_layout``.
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

from signpose.core.fileio import atomic_path
from signpose.estimator.metrics import ground_truth_at, rotation_errors_deg
from signpose.estimator.status import PoseStatus
from signpose.estimator.trajectory import Trajectory
from signpose.maps.loader import SignMap

_COLORS = {"groundtruth": "0.2", "baseline": "#d95319", "smoothed": "#0072bd"}
_EXTRA = ("#77ac30", "#7e2f8e", "#edb120")
SIGMA_BAND = 2.0  # bands are +-2 sigma
DPI = 110  # PNG resolution [dots per inch]
# Held while matplotlib lays out or renders text (its mathtext parser is one per process).
_RENDER_LOCK = threading.Lock()
# Marker colour of each pose status (views.png) and of the status band (signs_per_frame.png);
# any other token (a per-frame method's failure: no pose) is drawn as "no pose".
STATUS_COLORS = {
    PoseStatus.OK.value: "#2ca02c",
    PoseStatus.WEAK.value: "#edb120",
    PoseStatus.BRIDGED.value: "#7f7f7f",
    PoseStatus.SUSPECT.value: "#d62728",
}
NO_POSE = "no pose"
# Marker areas [points^2]: ok poses small (the line stays visible), the others stand out.
_OK_MARKER = 2.0
_FLAGGED_MARKER = 12.0
_NO_POSE_COLOR = "0.93"  # light grey: a gap in the band


@dataclass(frozen=True)
class PlotData:
    """What the plots show.

    Attributes:
        sign_map: the signs (drawn as discs with their codes).
        trajectories: method -> estimate; rows may be NaN where a frame has none.
        sigmas_m: method -> (N, 3) standard deviation of the position per stamp
            of that method's trajectory [m], world axes; methods may be missing.
        groundtruth: the true trajectory, or None.
        frame_stamps_s: (F,) time of every processed frame [s].
        signs_per_frame: (F,) number of decoded map signs per processed frame.
        statuses: method -> (N,) pose status token per stamp of that method's
            trajectory (``ok``, ``weak``, ``bridged``, ``suspect``, or a
            failure token where it has no pose); methods may be missing.
    """

    sign_map: SignMap
    trajectories: dict[str, Trajectory]
    sigmas_m: dict[str, np.ndarray] = field(default_factory=dict)
    groundtruth: Trajectory | None = None
    frame_stamps_s: np.ndarray = field(default_factory=lambda: np.zeros(0))
    signs_per_frame: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    statuses: dict[str, tuple[str, ...]] = field(default_factory=dict)


def status_shares_text(tokens: tuple[str, ...] | list[str]) -> str:
    """``ok 90% weak 5% bridged 5% suspect 0%`` (poses without a status: ``no pose``)."""
    n = max(len(tokens), 1)
    parts = [f"{t} {100 * sum(x == t for x in tokens) / n:.0f}%" for t in STATUS_COLORS]
    missing = sum(x not in STATUS_COLORS for x in tokens)
    if missing:
        parts.append(f"{NO_POSE} {100 * missing / n:.0f}%")
    return " ".join(parts)


def _status_method(data: PlotData) -> str | None:
    """The method whose statuses the plots show: smoothed when it has them."""
    if "smoothed" in data.statuses:
        return "smoothed"
    return next(iter(data.statuses), None)


def _color(name: str, i: int) -> str:
    return _COLORS.get(name, _EXTRA[i % len(_EXTRA)])


def new_figure(figsize: tuple[float, float]) -> Figure:
    """A figure on its own Agg canvas: no pyplot, no global state."""
    fig = Figure(figsize=figsize)
    FigureCanvasAgg(fig)
    return fig


# Each figure's margins and gaps (figure fractions), fixed: matplotlib's
# tight_layout measured every label of every figure again (2.4 s of a run's
# plots); these are what it chose on typical flights, with room for wider
# tick labels.
_LAYOUTS = {
    "views": {"left": 0.065, "right": 0.985, "bottom": 0.075, "top": 0.95, "wspace": 0.16},
    "errors": {"left": 0.095, "right": 0.985, "bottom": 0.1, "top": 0.935, "hspace": 0.09},
    "signs_band": {"left": 0.075, "right": 0.985, "bottom": 0.17, "top": 0.9, "hspace": 0.37},
    "signs": {"left": 0.075, "right": 0.985, "bottom": 0.185, "top": 0.88},
    "gnss": {"left": 0.065, "right": 0.985, "bottom": 0.11, "top": 0.92, "wspace": 0.2},
}


def _save(fig: Figure, path: Path) -> Path:
    """Write ``fig`` as PNG, atomically, under the render lock (its layout is fixed)."""
    with _RENDER_LOCK, atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=DPI, format="png")
    return path


def _t0(data: PlotData) -> float:
    starts = [t.stamps_s[0] for t in data.trajectories.values() if len(t)]
    if data.groundtruth is not None and len(data.groundtruth):
        starts.append(data.groundtruth.stamps_s[0])
    if len(data.frame_stamps_s):
        starts.append(data.frame_stamps_s[0])
    return float(min(starts)) if starts else 0.0


def _disc(center: np.ndarray, world_R_sign: np.ndarray | None, diameter: float) -> np.ndarray:
    a = np.linspace(0, 2 * np.pi, 32, endpoint=False)
    if world_R_sign is None:  # centre-only sign: draw it facing +y
        world_R_sign = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]])
    local = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], 1) * diameter / 2
    return center + local @ world_R_sign.T


def plot_trajectory_3d(path: str | os.PathLike, data: PlotData, method: str | None = None) -> Path:
    """The paper's Fig. 13: the trajectory in 3D coloured by time, with the signs."""
    fig = new_figure((8, 7))
    ax = fig.add_subplot(projection="3d")
    names = list(data.trajectories)
    name = method or ("smoothed" if "smoothed" in names else (names[0] if names else None))
    t0 = _t0(data)
    pts_all = [data.sign_map.centers_m()]
    for sign in data.sign_map.signs:
        R = sign.world_R_sign() if sign.oriented else None
        disc = _disc(sign.center_m, R, sign.diameter_m)
        ax.add_collection3d(Poly3DCollection([disc], facecolor="0.85", edgecolor="k", lw=0.5))
        ax.text(*(sign.center_m + [0, 0, 0.7 * sign.diameter_m]), sign.code, fontsize=7)
    if data.groundtruth is not None:
        p = data.groundtruth.world_t_cam
        ax.plot(p[:, 0], p[:, 1], p[:, 2], color="0.5", lw=0.8, ls="--", label="ground truth")
        pts_all.append(p)
    if name is not None:
        traj = data.trajectories[name]
        p = traj.world_t_cam
        ok = np.all(np.isfinite(p), axis=1)
        segs = np.stack([p[:-1], p[1:]], axis=1)
        seg_ok = ok[:-1] & ok[1:]
        if np.any(seg_ok):
            t = traj.stamps_s[:-1][seg_ok] - t0
            lc = Line3DCollection(segs[seg_ok], cmap="viridis", lw=2.0)
            lc.set_array(t)
            ax.add_collection3d(lc)
            fig.colorbar(lc, ax=ax, shrink=0.6, label="time [s]")
            pts_all.append(p[ok])
        ax.set_title(f"{name} trajectory, coloured by time")
    pts = np.concatenate([q for q in pts_all if len(q)])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = 0.05 * max(float(np.max(hi - lo)), 1.0)
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_zlim(lo[2] - pad, hi[2] + pad)
    ax.set_box_aspect(np.maximum(hi - lo + 2 * pad, 1e-3))
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_zlabel("z [m]")
    if data.groundtruth is not None:
        ax.legend(loc="upper left")
    return _save(fig, Path(path))


def plot_views(path: str | os.PathLike, data: PlotData) -> Path:
    """Top (x-y) and side (y-z) views of every method, and x, y, z over time with sigma bands.

    The views are zoomed on the flight; the signs are in the 3D plot.
    """
    fig = new_figure((13, 8))
    grid = fig.add_gridspec(3, 2, width_ratios=[1.0, 1.3], hspace=0.44)
    fig.subplots_adjust(**_LAYOUTS["views"])
    top = fig.add_subplot(grid[0:2, 0])
    side = fig.add_subplot(grid[2, 0])
    axes_t = [fig.add_subplot(grid[k, 1]) for k in range(3)]
    t0 = _t0(data)
    if data.groundtruth is not None:
        g = data.groundtruth.world_t_cam
        top.plot(g[:, 0], g[:, 1], color="0.5", ls="--", lw=1, label="ground truth")
        side.plot(g[:, 1], g[:, 2], color="0.5", ls="--", lw=1)
        for k in range(3):
            axes_t[k].plot(data.groundtruth.stamps_s - t0, g[:, k], color="0.5", ls="--", lw=1)
    for i, (name, traj) in enumerate(data.trajectories.items()):
        c = _color(name, i)
        p = traj.world_t_cam
        t = traj.stamps_s - t0
        top.plot(p[:, 0], p[:, 1], color=c, lw=1.2, label=name)
        side.plot(p[:, 1], p[:, 2], color=c, lw=1.2)
        sigma = data.sigmas_m.get(name)
        if sigma is not None and len(sigma) == len(p):
            step = max(1, len(p) // 25)
            sel = slice(None, None, step)
            for ax, (a, b) in ((top, (0, 1)), (side, (1, 2))):
                ax.errorbar(
                    p[sel, a],
                    p[sel, b],
                    xerr=SIGMA_BAND * sigma[sel, a],
                    yerr=SIGMA_BAND * sigma[sel, b],
                    fmt="none",
                    ecolor=c,
                    alpha=0.5,
                    lw=0.8,
                )
        for k in range(3):
            axes_t[k].plot(t, p[:, k], color=c, lw=1.0, label=name)
            if sigma is not None and len(sigma) == len(p):
                axes_t[k].fill_between(
                    t,
                    p[:, k] - SIGMA_BAND * sigma[:, k],
                    p[:, k] + SIGMA_BAND * sigma[:, k],
                    color=c,
                    alpha=0.2,
                    lw=0,
                )
    top.set_title("top view")
    top.set_xlabel("x [m]")
    top.set_ylabel("y [m]")
    top.set_aspect("equal", adjustable="datalim")
    top.legend(fontsize=8)
    side.set_title("side view")
    side.set_xlabel("y [m]")
    side.set_ylabel("z [m]")
    side.set_aspect("equal", adjustable="datalim")
    for k, axis in enumerate("xyz"):
        axes_t[k].set_ylabel(f"{axis} [m]")
        axes_t[k].grid(alpha=0.3)
    axes_t[0].set_title(f"position over time (bands: +-{SIGMA_BAND:g} sigma)")
    axes_t[0].legend(fontsize=8)
    axes_t[2].set_xlabel("time [s]")
    _mark_statuses(data, top, side, axes_t)
    return _save(fig, Path(path))


def _mark_statuses(data: PlotData, top, side, axes_t) -> None:
    """Dots on one method's poses coloured by status, the shares in the top view's legend."""
    name = _status_method(data)
    if name is None or name not in data.trajectories:
        return
    traj = data.trajectories[name]
    tokens = np.asarray(data.statuses[name], dtype=object)
    if len(tokens) != len(traj):
        return
    p, t = traj.world_t_cam, traj.stamps_s - _t0(data)
    n = len(tokens)
    for token, c in STATUS_COLORS.items():
        sel = tokens == token
        if not np.any(sel):
            continue
        label = f"{name} {token} {100 * sel.sum() / n:.0f}%"
        size = _OK_MARKER if token == PoseStatus.OK.value else _FLAGGED_MARKER
        top.scatter(p[sel, 0], p[sel, 1], s=size, color=c, zorder=3, label=label)
        side.scatter(p[sel, 1], p[sel, 2], s=size, color=c, zorder=3)
        for k in range(3):
            axes_t[k].scatter(t[sel], p[sel, k], s=size, color=c, zorder=3)
    top.legend(fontsize=8)
    side.set_title(f"side view; {name} poses by status")


def pose_errors(traj: Trajectory, gt: Trajectory) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(stamps [s], position error [m], rotation error [deg]) where the ground truth is known.

    The ground truth at the trajectory's stamps as the metrics take it
    (``estimator.metrics.ground_truth_at``: interpolated across short gaps).
    """
    i, gt_T = ground_truth_at(gt, traj.stamps_s)
    dp = np.linalg.norm(traj.world_t_cam[i] - gt_T[:, :3, 3], axis=1)
    dr = rotation_errors_deg(traj.world_R_cam()[i], gt_T[:, :3, :3])
    return traj.stamps_s[i], dp, dr


def plot_errors(path: str | os.PathLike, data: PlotData) -> Path | None:
    """Position and rotation error over time against the ground truth (None without it)."""
    if data.groundtruth is None:
        return None
    fig = new_figure((10, 6))
    fig.subplots_adjust(**_LAYOUTS["errors"])
    ax_p, ax_r = fig.subplots(2, 1, sharex=True)
    t0 = _t0(data)
    for i, (name, traj) in enumerate(data.trajectories.items()):
        t, dp, dr = pose_errors(traj, data.groundtruth)
        c = _color(name, i)
        ok = np.isfinite(dp)
        med = float(np.median(dp[ok])) if np.any(ok) else float("nan")
        ax_p.plot(t - t0, dp, color=c, lw=1.0, label=f"{name} (median {med:.3f} m)")
        ax_r.plot(t - t0, dr, color=c, lw=1.0, label=name)
    ax_p.set_ylabel("position error [m]")
    ax_r.set_ylabel("rotation error [deg]")
    ax_r.set_xlabel("time [s]")
    ax_p.set_yscale("log")
    ax_p.set_title("error against ground truth")
    for ax in (ax_p, ax_r):
        ax.grid(alpha=0.3)
    ax_p.legend(fontsize=8)
    return _save(fig, Path(path))


def plot_signs_per_frame(path: str | os.PathLike, data: PlotData) -> Path:
    """Number of decoded map signs in every frame, with a band of the poses' statuses."""
    name = _status_method(data)
    tokens = data.statuses.get(name, ()) if name is not None else ()
    band = len(tokens) == len(data.frame_stamps_s) and len(tokens) > 0
    fig = new_figure((10, 3.8 if band else 3.2))
    fig.subplots_adjust(**_LAYOUTS["signs_band" if band else "signs"])
    if band:
        ax, ax_band = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [5, 1]})
    else:
        ax, ax_band = fig.subplots(), None
    t = data.frame_stamps_s - _t0(data)
    n = np.asarray(data.signs_per_frame)
    ax.step(t, n, where="mid", color="#0072bd", lw=1.0)
    ax.fill_between(t, 0, n, step="mid", color="#0072bd", alpha=0.25)
    lost = n == 0
    if np.any(lost):
        ax.plot(t[lost], np.zeros(int(lost.sum())), "|", color="#d95319", label="no sign")
        ax.legend(fontsize=8)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("signs seen")
    top = int(n.max()) if len(n) else 1
    ax.set_ylim(0, max(top, 1) + 0.5)
    ax.set_title(f"signs seen per frame (mean {float(n.mean()) if len(n) else 0.0:.1f})")
    ax.grid(alpha=0.3)
    if ax_band is not None and name is not None:
        ax.set_xlabel("")
        _status_band(ax_band, t, tuple(tokens), name)
    return _save(fig, Path(path))


def _status_band(ax, t: np.ndarray, tokens: tuple[str, ...], name: str) -> None:
    """One coloured cell per frame: the status of ``name``'s pose, shares in the title.

    Neighbouring cells of one status are one bar (a bar per frame was 300 patches on a
    300-frame flight, half the plot's time; the same band without the seams between cells).
    """
    edges = _cell_edges(t)
    shown = [x if x in STATUS_COLORS else NO_POSE for x in tokens]
    starts = [k for k in range(len(shown)) if k == 0 or shown[k] != shown[k - 1]]
    ends = [*starts[1:], len(shown)]
    run_token = np.array([shown[k] for k in starts], dtype=object)
    left, right = edges[starts], edges[ends]
    for token, c in (*STATUS_COLORS.items(), (NO_POSE, _NO_POSE_COLOR)):
        sel = run_token == token
        if np.any(sel):
            ax.bar(
                left[sel],
                1.0,
                width=(right - left)[sel],
                align="edge",
                color=c,
                edgecolor="none",
                label=token,
            )
    ax.set_yticks([])
    ax.set_ylim(0, 1)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(name, fontsize=8)
    ax.set_title(f"{name} pose status: {status_shares_text(tokens)}", fontsize=9)
    ax.legend(fontsize=7, ncol=5, loc="upper right", bbox_to_anchor=(1.0, -0.6))


def _cell_edges(t: np.ndarray) -> np.ndarray:
    """(F+1,) edges of one cell per stamp, halfway between neighbouring stamps [s]."""
    if len(t) == 1:
        return np.array([t[0] - 0.5, t[0] + 0.5])
    mid = (t[:-1] + t[1:]) / 2
    return np.concatenate([[2 * t[0] - mid[0]], mid, [2 * t[-1] - mid[-1]]])


# The plots of a run, in order: (file name, function(path, data) -> path, or None when
# it has nothing to show: errors.png without a ground truth).
PLOTS = (
    ("trajectory_3d.png", plot_trajectory_3d),
    ("views.png", plot_views),
    ("signs_per_frame.png", plot_signs_per_frame),
    ("errors.png", plot_errors),
)


def write_plots(out_dir: str | os.PathLike, data: PlotData) -> list[Path]:
    """All plots into ``out_dir``: trajectory_3d, views, signs_per_frame, errors (with GT)."""
    out = Path(out_dir)
    written = [draw(out / name, data) for name, draw in PLOTS]
    return [p for p in written if p is not None]


def plot_gnss_track(
    path: str | os.PathLike,
    track: Trajectory,
    name: str,
    gnss_world_m: np.ndarray,
    gnss_stamps_s: np.ndarray,
    outlier: np.ndarray | None = None,
) -> Path:
    """The GNSS fixes beside an estimated track (issue 17): top view and distance over time.

    Args:
        track: the estimate (``fused``, else ``smoothed``); NaN rows leave gaps.
        name: its method name (legend and colour).
        gnss_world_m: (G, 3) the fixes in the world frame (ENU at the map's origin) [m].
        gnss_stamps_s: (G,) their times on the video's clock [s].
        outlier: (G,) True for the fixes the fusion rejected, or None.
    """
    g = np.asarray(gnss_world_m, float).reshape(-1, 3)
    tg = np.asarray(gnss_stamps_s, float).reshape(-1)
    bad = np.zeros(len(g), bool) if outlier is None else np.asarray(outlier, bool).reshape(-1)
    fig = new_figure((12, 5))
    fig.subplots_adjust(**_LAYOUTS["gnss"])
    top, dist = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    p = track.world_t_cam
    c = _color(name, 0)
    top.plot(p[:, 0], p[:, 1], color=c, lw=1.2, label=name)
    top.scatter(g[~bad, 0], g[~bad, 1], s=6, color="#f09c3c", label="GNSS fix")
    if bad.any():
        top.scatter(g[bad, 0], g[bad, 1], s=14, color="#d62728", marker="x", label="rejected fix")
    top.set_title("top view: GNSS fixes and the estimate")
    top.set_xlabel("east [m]")
    top.set_ylabel("north [m]")
    top.set_aspect("equal", adjustable="datalim")
    top.legend(fontsize=8)
    ok = np.all(np.isfinite(p), axis=1)
    t0 = float(min(tg[0] if len(tg) else np.inf, track.stamps_s[0] if len(track) else np.inf))
    if ok.sum() >= 2 and len(g):
        t = track.stamps_s[ok]
        at = np.stack([np.interp(tg, t, p[ok, k], left=np.nan, right=np.nan) for k in range(3)], 1)
        d = np.linalg.norm((g - at)[:, :2], axis=1)
        dist.plot(tg[~bad] - t0, d[~bad], ".", ms=3, color="#f09c3c", label="GNSS fix")
        if bad.any():
            dist.plot(tg[bad] - t0, d[bad], "x", ms=4, color="#d62728", label="rejected fix")
        dist.legend(fontsize=8)
    dist.set_title(f"horizontal distance of each fix from {name}")
    dist.set_xlabel("time [s]")
    dist.set_ylabel("distance [m]")
    dist.grid(alpha=0.3)
    return _save(fig, Path(path))
