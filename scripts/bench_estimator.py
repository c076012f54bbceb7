#!/usr/bin/env python
"""Benchmark the estimator on a long simulated flight (10 signs, 1920x1080): ratios in one run.

Prints (and writes to ``--json``):

* per-frame PnP (the initial values), the batch solve (Gauss-Newton, its last
  net giving the sigmas) without and with the marginal sigmas, in ms per frame;
* the marginals two ways on the same linearised graph (its first
  ``--marginal-frames`` frames): one backward pass (``estimator.marginals``)
  against one Bayes-tree ``marginalCovariance`` per pose, their time ratio and
  largest relative difference;
* iSAM2 in its bounded window (``--window``) at N and N/2 frames and, for
  comparison, over the whole flight at ``--compare-frames``: mean, median and
  p90 ms per frame (each frame's update, write-outs included; the total with
  the final convergence and sweeps too), the final estimate against batch,
  and the peak RSS of a child process per solver (so that one solve does not
  inflate the other; VmHWM, see ``_peak_rss_mb``) with its growth per frame;
* the plot stage (``plots.write_plots`` on this flight) with its fixed layout
  against the same figures laid out by ``tight_layout``, alternating,
  ``--repeat`` times (min and median).

The machine is shared: run with OPENBLAS_NUM_THREADS=1 when it is quiet
(``uptime``); speeds are compared within one run. The flight is the
lawnmower pattern in front of the demo map, 0.4 px keypoint noise, 30 fps.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/bench_estimator.py [--frames 2000] [--json F]
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import resource
import subprocess
import sys
import tempfile
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
from signpose.estimator.camera import pinhole_camera
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.perframe import run_per_frame
from signpose.estimator.smoother import (
    LANDMARK_MODELS,
    MOTION_MODELS,
    SmootherSettings,
    _batch_graph,
    _GraphBuilder,
    batch_covariances,
    chain_ordering,
    collect_measurements,
    default_pose,
    smooth_batch,
    smooth_isam2,
)
from signpose.estimator.trajectory import Trajectory
from signpose.maps.loader import bundled_map_path, load_map

import signpose.plots as plots
from signpose.core.fileio import atomic_write
from signpose.sim.observations import SyntheticSettings, paper_like_frames


def _flight(n: int):
    sign_map = load_map(bundled_map_path())
    camera = pinhole_camera(1920, 1080, 60.0)
    frames, gt, _ = paper_like_frames(
        sign_map,
        camera,
        n,
        np.random.default_rng(0),
        SyntheticSettings(sigma_px=0.4),
        flight="lawnmower",
    )
    return sign_map, camera, frames, gt


def _marginals(meas, stamps, poses, camera, settings, m: int) -> dict:
    """One pass against per-pose Bayes-tree marginals on the first m frames' graph."""
    sub = meas.subset(meas.frame < m)
    sub = replace(sub, n_frames=m)
    b = _GraphBuilder(sub, stamps[:m], camera, settings)
    g = _batch_graph(b, poses[:m], stamps[:m])
    order = b.ordered(chain_ordering(m, len(sub.landmark_code), settings.motion))
    t, c = time.perf_counter(), time.process_time()
    fast = batch_covariances(g.graph, g.values, m, order)
    t_fast, c_fast = time.perf_counter() - t, time.process_time() - c
    t, c = time.perf_counter(), time.process_time()
    slow = batch_covariances(g.graph, g.values, m, order, per_pose=True)
    t_slow, c_slow = time.perf_counter() - t, time.process_time() - c
    rel = np.abs(fast - slow).max(axis=(1, 2)) / np.abs(slow).max(axis=(1, 2))
    return {
        "marginal_frames": m,
        "one_pass_ms_per_pose": 1e3 * t_fast / m,
        "per_pose_ms_per_pose": 1e3 * t_slow / m,
        "per_pose_over_one_pass": t_slow / t_fast,
        "per_pose_over_one_pass_cpu": c_slow / c_fast,
        "max_relative_difference": float(rel.max()),
    }


def _peak_rss_mb() -> float:
    """This process's peak resident set [MB]: VmHWM (Linux), else ru_maxrss.

    ru_maxrss of a child started with fork + exec also counts the parent's
    pages it held before the exec (measured: 1,071 MB in every child of a
    10,000-frame run, the parent's size), VmHWM only its own.
    """
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _child(path: str) -> int:
    """In a child process: one iSAM2 solve from the pickled problem; JSON on stdout."""
    with open(path, "rb") as f:
        job = pickle.load(f)
    n, settings = job["n"], job["settings"]
    meas = job["meas"].subset(job["meas"].frame < n)
    meas = replace(meas, n_frames=n)
    t = time.perf_counter()
    r = smooth_isam2(
        meas, job["stamps"][:n], job["init"][:n], job["camera"], settings, job["default"]
    )
    total = time.perf_counter() - t
    ms, cpu = r.per_frame_ms, r.per_frame_cpu_ms
    d = np.linalg.norm(r.world_T_cam[:, :3, 3] - job["batch_t"][n], axis=1) if job["compare"] else 0
    out = {
        "frames": n,
        "window": settings.isam_window_frames,
        "mean_ms": float(ms.mean()),
        "median_ms": float(np.median(ms)),
        "p90_ms": float(np.percentile(ms, 90)),
        "cpu_mean_ms": float(cpu.mean()),
        "cpu_median_ms": float(np.median(cpu)),
        "cpu_p90_ms": float(np.percentile(cpu, 90)),
        "total_ms_per_frame": 1e3 * total / n,
        "vs_batch_max_mm": float(1e3 * d.max()) if job["compare"] else None,
        "vs_batch_median_mm": float(1e3 * np.median(d)) if job["compare"] else None,
        "peak_rss_mb": _peak_rss_mb(),
        "ru_maxrss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
    }
    print(json.dumps(out))
    return 0


def _isam2_in_child(job: dict, n: int, window: int, compare: bool) -> dict:
    job = {**job, "n": n, "compare": compare}
    job["settings"] = replace(job["settings"], isam_window_frames=window)
    with tempfile.NamedTemporaryFile(suffix=".pkl", delete=False) as f:
        pickle.dump(job, f)
    try:
        out = subprocess.run(
            [sys.executable, __file__, "--child", f.name], capture_output=True, text=True
        )
    finally:
        os.unlink(f.name)
    if out.returncode != 0:
        raise RuntimeError(f"iSAM2 child ({n} frames, window {window}) failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def _plot_data(sign_map, gt, r) -> plots.PlotData:
    q = np.tile([0.0, 0.0, 0.0, 1.0], (len(gt.stamps_s), 1))
    est = Trajectory(gt.stamps_s, r.world_T_cam[:, :3, 3], q)
    return plots.PlotData(
        sign_map=sign_map,
        trajectories={"smoothed": est},
        sigmas_m={"smoothed": r.sigma_xyz},
        groundtruth=Trajectory(gt.stamps_s, gt.world_t_cam, q),
        frame_stamps_s=gt.stamps_s,
        signs_per_frame=r.signs_used,
        statuses={"smoothed": tuple("ok" if o else "bridged" for o in r.observed)},
    )


def _plot_stage(data: plots.PlotData, repeat: int) -> dict:
    """write_plots with the fixed layout against the same figures with tight_layout."""
    fixed_save = plots._save

    def tight_save(fig, path):  # as before: every figure but the 3D one laid out again
        if not any(ax.name == "3d" for ax in fig.axes):
            with plots._RENDER_LOCK, warnings.catch_warnings():
                warnings.simplefilter("ignore", UserWarning)  # as before, said every run
                fig.tight_layout()
        return fixed_save(fig, path)

    times: dict[str, list[float]] = {"fixed": [], "tight_layout": []}
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeat):
            for name, save in (("fixed", fixed_save), ("tight_layout", tight_save)):
                plots._save = save
                try:
                    folder = Path(tmp) / name
                    folder.mkdir(exist_ok=True)
                    t = time.perf_counter()
                    plots.write_plots(folder, data)
                    times[name].append(time.perf_counter() - t)
                finally:
                    plots._save = fixed_save
    ratio = [a / b for a, b in zip(times["tight_layout"], times["fixed"], strict=True)]
    return {
        "plots_fixed_s_min": min(times["fixed"]),
        "plots_fixed_s_median": float(np.median(times["fixed"])),
        "plots_tight_layout_s_min": min(times["tight_layout"]),
        "plots_tight_layout_s_median": float(np.median(times["tight_layout"])),
        "plots_tight_over_fixed_min": min(ratio),
        "plots_tight_over_fixed_median": float(np.median(ratio)),
    }


def _parse(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--isam-frames", type=int, default=None, help="frames for iSAM2 (default all)")
    ap.add_argument("--motion", choices=MOTION_MODELS, default=SmootherSettings().motion)
    ap.add_argument("--landmarks", choices=LANDMARK_MODELS, default=SmootherSettings().landmarks)
    ap.add_argument(
        "--window",
        type=int,
        default=SmootherSettings().isam_window_frames or 300,
        help="iSAM2 window [frames] (isam_window_frames)",
    )
    ap.add_argument(
        "--marginal-frames",
        type=int,
        default=300,
        help="frames of the one-pass vs per-pose marginals comparison",
    )
    ap.add_argument(
        "--compare-frames",
        type=int,
        default=500,
        help="frames of the whole-flight iSAM2 (no window) compared with the window",
    )
    ap.add_argument("--repeat", type=int, default=3, help="plot stage repetitions")
    ap.add_argument("--no-isam", action="store_true")
    ap.add_argument(
        "--pipeline",
        action="store_true",
        help="also time estimate_trajectories (PnP, Huber solve, innovation rounds, motion "
        "prior from the flight, final Tukey solve) as 'signpose estimate --no-sigmas' runs it",
    )
    ap.add_argument("--json", help="also write the numbers to this JSON file")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    return ap.parse_args(argv)


def _batch(out: dict, meas, gt, init, camera, settings, default, n: int):
    c = time.process_time()
    r = smooth_batch(meas, gt.stamps_s, init, camera, settings, default)
    c_batch = time.process_time() - c
    err = np.abs(r.world_T_cam[:, :3, 3] - gt.world_t_cam).mean(axis=0)
    with_s = replace(settings, compute_sigmas=True, max_sigma_frames=n)
    c = time.process_time()
    rs = smooth_batch(meas, gt.stamps_s, init, camera, with_s, default)
    c_with = time.process_time() - c
    out.update(
        batch_s=r.seconds,
        batch_with_pnp_s=r.seconds + 1e-3 * out["pnp_ms_per_frame"] * n,
        batch_ms_per_frame=1e3 * r.seconds / n,
        batch_cpu_ms_per_frame=1e3 * c_batch / n,
        batch_build_ms_per_frame=1e3 * r.build_seconds / n,
        batch_iterations=r.iterations,
        batch_mae_xyz=err.tolist(),
        batch_with_sigmas_ms_per_frame=1e3 * (rs.seconds + rs.sigma_seconds) / n,
        batch_with_sigmas_cpu_ms_per_frame=1e3 * c_with / n,
        batch_sigmas_ms_per_frame=1e3 * rs.sigma_seconds / n,
    )
    print(
        f"batch: {out['batch_ms_per_frame']:.3f} ms/frame (CPU "
        f"{out['batch_cpu_ms_per_frame']:.3f}; build {out['batch_build_ms_per_frame']:.3f}, "
        f"{r.iterations} iterations); with sigmas {out['batch_with_sigmas_ms_per_frame']:.3f} "
        f"ms/frame (CPU {out['batch_with_sigmas_cpu_ms_per_frame']:.3f}; marginals "
        f"{out['batch_sigmas_ms_per_frame']:.3f}); MAE xyz {np.round(err, 4)}"
    )
    return rs


def _isam2(out: dict, job: dict, n: int, window: int, compare_n: int) -> None:
    half = _isam2_in_child(job, max(n // 2, 1), window, False)
    full = _isam2_in_child(job, n, window, True)
    growth = (full["peak_rss_mb"] - half["peak_rss_mb"]) / max(n - n // 2, 1)
    out["isam2_window"] = {"half": half, "full": full, "rss_growth_kb_per_frame": 1e3 * growth}
    out.update(  # the keys scripts/reproduce_paper.py reads
        isam2_frames=n,
        isam2_median_ms=full["median_ms"],
        isam2_p90_ms=full["p90_ms"],
        isam2_cpu_median_ms=full["cpu_median_ms"],
        isam2_vs_batch_mm=full["vs_batch_max_mm"],
    )
    print(
        f"iSAM2, window {window}, {n} frames: mean {full['mean_ms']:.2f} ms/frame (CPU "
        f"{full['cpu_mean_ms']:.2f}), median {full['median_ms']:.2f}, p90 {full['p90_ms']:.2f} "
        f"(CPU {full['cpu_p90_ms']:.2f}), with the final convergence "
        f"{full['total_ms_per_frame']:.2f}; final vs batch max {full['vs_batch_max_mm']:.3f} mm "
        f"(median {full['vs_batch_median_mm']:.3f}); peak RSS {full['peak_rss_mb']:.0f} MB at "
        f"{n}, {half['peak_rss_mb']:.0f} MB at {n // 2}: {1e3 * growth:.1f} KB per frame"
    )
    m = min(compare_n, n)
    if m <= 0:
        return
    whole = _isam2_in_child(job, m, 0, True)
    win = _isam2_in_child(job, m, window, True)
    out["isam2_compare"] = {
        "frames": m,
        "whole": whole,
        "window": win,
        "rss_whole_over_window": whole["peak_rss_mb"] / win["peak_rss_mb"],
        "mean_ms_whole_over_window": whole["mean_ms"] / win["mean_ms"],
    }
    print(
        f"iSAM2 over {m} frames, whole flight vs window {window}: peak RSS "
        f"{whole['peak_rss_mb']:.0f} vs {win['peak_rss_mb']:.0f} MB, mean "
        f"{whole['mean_ms']:.2f} vs {win['mean_ms']:.2f} ms/frame (CPU {whole['cpu_mean_ms']:.2f}"
        f" vs {win['cpu_mean_ms']:.2f}), p90 {whole['p90_ms']:.2f} vs {win['p90_ms']:.2f}; final "
        f"vs batch max {whole['vs_batch_max_mm']:.3f} vs {win['vs_batch_max_mm']:.3f} mm"
    )


def main(argv=None) -> int:
    args = _parse(argv)
    if args.child:
        return _child(args.child)
    n = args.frames
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    t = time.perf_counter()
    sign_map, camera, frames, gt = _flight(n)
    t_syn = time.perf_counter() - t
    meas = collect_measurements(frames, sign_map, camera)
    print(
        f"# {n} frames, {len(sign_map.signs)} signs, {len(meas.landmark_code)} landmarks, "
        f"{len(meas.frame)} projection factors, motion {args.motion}; load average {load:.1f} on "
        f"{os.cpu_count()} cores (synthesis {t_syn:.1f} s)"
    )
    out: dict = {
        "frames": n,
        "motion": args.motion,
        "landmarks": args.landmarks,
        "load_average": load,
    }
    t = time.perf_counter()
    pnp = run_per_frame(frames, sign_map, camera, "pnp")
    out["pnp_ms_per_frame"] = 1e3 * (time.perf_counter() - t) / n
    print(f"per-frame PnP (initial values): {out['pnp_ms_per_frame']:.3f} ms/frame")
    init = [p.world_T_cam for p in pnp]
    settings = SmootherSettings(motion=args.motion, landmarks=args.landmarks, compute_sigmas=False)
    default = default_pose(sign_map)
    rs = _batch(out, meas, gt, init, camera, settings, default, n)
    out["marginals"] = mg = _marginals(
        meas, gt.stamps_s, rs.world_T_cam, camera, settings, min(args.marginal_frames, n)
    )
    print(
        f"marginals of {mg['marginal_frames']} poses: one pass {mg['one_pass_ms_per_pose']:.3f} "
        f"ms/pose, per-pose Bayes tree {mg['per_pose_ms_per_pose']:.3f} ms/pose: "
        f"{mg['per_pose_over_one_pass']:.1f}x (CPU {mg['per_pose_over_one_pass_cpu']:.1f}x); "
        f"largest relative difference "
        f"{mg['max_relative_difference']:.1e}"
    )
    if args.pipeline:
        es = EstimatorSettings(methods=("pnp", "smoothed"), smoother=settings)
        t = time.perf_counter()
        res = estimate_trajectories(frames, sign_map, camera, es, progress=False)
        out["pipeline_s"] = time.perf_counter() - t
        print(
            f"estimate_trajectories (pnp + smoothed, no sigmas): {out['pipeline_s']:.2f} s; "
            f"stages {', '.join(f'{k} {v:.1f} s' for k, v in res.timing_s.items())}"
        )
    if not args.no_isam:
        # iSAM2 keeps keypoint landmarks (the rigid model is batch only): its batch reference too.
        kp = replace(settings, landmarks="keypoints")
        n_isam = min(args.isam_frames or n, n)
        refs = {}
        for m in {n_isam, min(args.compare_frames, n_isam)} - {0}:
            sub = replace(meas.subset(meas.frame < m), n_frames=m)
            refs[m] = smooth_batch(sub, gt.stamps_s[:m], init[:m], camera, kp, default)
        job = {
            "meas": meas,
            "stamps": gt.stamps_s,
            "init": init,
            "camera": camera,
            "settings": kp,
            "default": default,
            "batch_t": {m: r.world_T_cam[:, :3, 3] for m, r in refs.items()},
        }
        _isam2(out, job, n_isam, args.window, args.compare_frames)
    out.update(_plot_stage(_plot_data(sign_map, gt, rs), args.repeat))
    print(
        f"plots: fixed layout {out['plots_fixed_s_min']:.2f} s (median "
        f"{out['plots_fixed_s_median']:.2f}), tight_layout {out['plots_tight_layout_s_min']:.2f} "
        f"s (median {out['plots_tight_layout_s_median']:.2f}): tight/fixed "
        f"{out['plots_tight_over_fixed_min']:.2f}x min, {out['plots_tight_over_fixed_median']:.2f}x"
        f" median"
    )
    if args.json:
        with atomic_write(args.json, encoding="utf-8") as f:
            json.dump(out, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
