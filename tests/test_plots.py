"""Plots drawn from several threads at once (two flights in one Dask worker process)."""

from __future__ import annotations

import subprocess
import sys
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
from matplotlib.image import imread
from signpose.estimator.trajectory import Trajectory
from signpose.maps.loader import bundled_map_path, load_map

from signpose import plots
from signpose.plots import PlotData, plot_errors, write_plots

PLOT_NAMES = ["errors.png", "signs_per_frame.png", "trajectory_3d.png", "views.png"]


def _plot_data(rng: np.random.Generator, error_exponent: float, n: int = 30) -> PlotData:
    """A flight in front of the bundled pylon with ground truth, so errors.png (log axis) is drawn.

    Position errors are about ``10**error_exponent`` m: threads given other
    exponents get other log-axis tick labels, which matplotlib must parse
    afresh (its mathtext parser caches what it has seen).
    """
    stamps_s = np.arange(n) * 0.1
    gt_t = np.stack([np.linspace(-5, 5, n), np.full(n, -12.0), np.full(n, 8.0)], axis=1)
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
    gt = Trajectory(stamps_s, gt_t, quat)
    scale_m = 10.0 ** (error_exponent + rng.uniform(-1.5, 1.5, size=(n, 1)))
    est = Trajectory(stamps_s, gt_t + scale_m * rng.standard_normal((n, 3)), quat)
    return PlotData(
        sign_map=load_map(bundled_map_path()),
        trajectories={"baseline": est, "smoothed": est},
        sigmas_m={"smoothed": np.full((n, 3), 0.02)},
        groundtruth=gt,
        frame_stamps_s=stamps_s,
        signs_per_frame=rng.integers(0, 4, size=n),
    )


def test_plots_from_several_threads_at_once(tmp_path):
    n_threads, rounds = 3, 3
    rng = np.random.default_rng(7)
    data = [
        [_plot_data(rng, error_exponent=-1.0 - (k * rounds + r)) for r in range(rounds)]
        for k in range(n_threads)
    ]
    start = threading.Barrier(n_threads)
    errors: list[str] = []

    def draw(k: int) -> None:
        folder = tmp_path / f"thread{k}"
        (folder / "again").mkdir(parents=True)
        start.wait()
        try:  # the log-axis plot, again and again, then the rest
            for r in range(rounds):
                plot_errors(folder / "again" / f"errors{r}.png", data[k][r])
            write_plots(folder, data[k][0])
        except Exception as exc:  # noqa: BLE001 - collected and asserted below
            errors.append(f"thread {k}: {type(exc).__name__}: {exc}")

    threads = [threading.Thread(target=draw, args=(k,)) for k in range(n_threads)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert errors == []
    for k in range(n_threads):
        folder = tmp_path / f"thread{k}"
        assert sorted(p.name for p in folder.glob("*.png")) == PLOT_NAMES
        alone = plot_errors(tmp_path / f"alone{k}.png", data[k][0])
        assert (folder / "errors.png").read_bytes() == alone.read_bytes()  # same pixels
        assert (folder / "again" / "errors0.png").read_bytes() == alone.read_bytes()


def test_plots_do_not_load_pyplot():
    code = "import sys, signpose.plots; print('matplotlib.pyplot' in sys.modules)"
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=Path.cwd()
    )
    assert out.stdout.strip() == "False"


def _band_per_frame(ax, t: np.ndarray, tokens: tuple[str, ...], name: str) -> None:
    """The status band as it was drawn before: one bar per frame (the reference)."""
    edges = plots._cell_edges(t)
    for token, c in (*plots.STATUS_COLORS.items(), (plots.NO_POSE, plots._NO_POSE_COLOR)):
        if token == plots.NO_POSE:
            sel = np.array([x not in plots.STATUS_COLORS for x in tokens])
        else:
            sel = np.array([x == token for x in tokens])
        if np.any(sel):
            ax.bar(
                edges[:-1][sel],
                1.0,
                width=np.diff(edges)[sel],
                align="edge",
                color=c,
                edgecolor="none",
                label=token,
            )
    ax.set_yticks([])
    ax.set_ylim(0, 1)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(name, fontsize=8)
    ax.set_title(f"{name} pose status: {plots.status_shares_text(tokens)}", fontsize=9)
    ax.legend(fontsize=7, ncol=5, loc="upper right", bbox_to_anchor=(1.0, -0.6))


def test_status_band_of_runs_draws_the_pixels_of_one_bar_per_frame(tmp_path, monkeypatch):
    """signs_per_frame.png's band: a bar per run of one status, the same image as a bar per
    frame (runs of every length, a failure token, uneven frame times)."""
    rng = np.random.default_rng(11)
    n = 120
    choices = ["ok", "weak", "bridged", "suspect", "no_signs"]
    tokens = tuple(choices[k] for k in np.repeat(rng.integers(0, 5, 40), rng.integers(1, 6, 40)))
    n = len(tokens)
    stamps_s = np.cumsum(rng.uniform(0.05, 0.15, n))
    data = replace(_plot_data(rng, -2.0, n), frame_stamps_s=stamps_s, statuses={"smoothed": tokens})
    runs = 1 + sum(a != b for a, b in zip(tokens, tokens[1:], strict=False))
    assert runs < n  # some runs are longer than a frame
    merged = plots.plot_signs_per_frame(tmp_path / "runs.png", data)
    monkeypatch.setattr(plots, "_status_band", _band_per_frame)
    per_frame = plots.plot_signs_per_frame(tmp_path / "frames.png", data)
    a, b = imread(merged), imread(per_frame)
    assert a.shape == b.shape
    assert np.abs(a - b).max() <= 1 / 255
