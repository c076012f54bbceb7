#!/usr/bin/env python
"""Benchmark the smoother on a long simulated flight (10 signs, 1920x1080).

Reports: batch Levenberg-Marquardt seconds (graph building + optimisation),
the marginal covariances' seconds separately, and iSAM2's median update time
per frame (including building that frame's factors and reading its estimate).
Initial values come from per-frame PnP (timed too, and added to the batch time
in the "what a user waits for" line). Every figure is wall time with the
process's CPU time beside it (the machine is shared; run with
OPENBLAS_NUM_THREADS=1). The flight is the
lawnmower pattern in front of the demo map, 0.4 px keypoint noise, 30 fps.

    .venv/bin/python scripts/bench_estimator.py [--frames 10000] [--motion ...]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np
from signpose.estimator.camera import pinhole_camera
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.perframe import run_per_frame
from signpose.estimator.smoother import (
    LANDMARK_MODELS,
    MOTION_MODELS,
    SmootherSettings,
    collect_measurements,
    default_pose,
    smooth_batch,
    smooth_isam2,
)
from signpose.maps.loader import bundled_map_path, load_map

from signpose.core.fileio import atomic_write
from signpose.sim.observations import SyntheticSettings, paper_like_frames


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10000)
    ap.add_argument("--isam-frames", type=int, default=None, help="frames for iSAM2 (default all)")
    ap.add_argument("--motion", choices=MOTION_MODELS, default=SmootherSettings().motion)
    ap.add_argument("--landmarks", choices=LANDMARK_MODELS, default=SmootherSettings().landmarks)
    ap.add_argument("--sigmas", action="store_true", help="also time the marginals")
    ap.add_argument("--no-isam", action="store_true")
    ap.add_argument(
        "--pipeline",
        action="store_true",
        help="also time estimate_trajectories (PnP, Huber solve, innovation rounds, motion "
        "prior from the flight, final Tukey solve) as 'signpose estimate --no-sigmas' runs it",
    )
    ap.add_argument("--json", help="also write the numbers to this JSON file")
    args = ap.parse_args(argv)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    sign_map = load_map(bundled_map_path())
    camera = pinhole_camera(1920, 1080, 60.0)
    rng = np.random.default_rng(0)
    t = time.perf_counter()
    frames, gt, _ = paper_like_frames(
        sign_map, camera, args.frames, rng, SyntheticSettings(sigma_px=0.4), flight="lawnmower"
    )
    t_syn = time.perf_counter() - t
    meas = collect_measurements(frames, sign_map, camera)
    print(
        f"# {args.frames} frames, {len(sign_map.signs)} signs, {len(meas.landmark_code)} "
        f"landmarks, {len(meas.frame)} projection factors, motion {args.motion}; "
        f"load average {load:.1f} on {os.cpu_count()} cores (synthesis {t_syn:.1f} s)"
    )
    out: dict = {"frames": args.frames, "motion": args.motion, "load_average": load}
    t, c = time.perf_counter(), time.process_time()
    pnp = run_per_frame(frames, sign_map, camera, "pnp")
    t_pnp, c_pnp = time.perf_counter() - t, time.process_time() - c
    print(
        f"per-frame PnP (initial values): {t_pnp:.2f} s, CPU {c_pnp:.2f} s "
        f"({1e3 * t_pnp / args.frames:.2f} ms/frame, CPU {1e3 * c_pnp / args.frames:.2f})"
    )
    init = [p.world_T_cam for p in pnp]
    settings = SmootherSettings(motion=args.motion, landmarks=args.landmarks, compute_sigmas=False)
    default = default_pose(sign_map)
    c = time.process_time()
    r = smooth_batch(meas, gt.stamps_s, init, camera, settings, default)
    c_batch = time.process_time() - c
    err = np.abs(r.world_T_cam[:, :3, 3] - gt.world_t_cam).mean(axis=0)
    out.update(
        pnp_ms_per_frame=1e3 * t_pnp / args.frames,
        pnp_cpu_ms_per_frame=1e3 * c_pnp / args.frames,
        batch_s=r.seconds,
        batch_cpu_s=c_batch,
        batch_with_pnp_s=r.seconds + t_pnp,
        batch_build_s=r.build_seconds,
        batch_optimize_s=(r.seconds - r.build_seconds),
        batch_iterations=r.iterations,
        batch_mae_xyz=err.tolist(),
    )
    print(
        f"batch LM: {r.seconds:.2f} s, CPU {c_batch:.2f} s (build {r.build_seconds:.2f} s, "
        f"optimise {(r.seconds - r.build_seconds):.2f} s, {r.iterations} iterations); "
        f"MAE xyz {np.round(err, 4)}"
    )
    if args.pipeline:
        es = EstimatorSettings(methods=("pnp", "smoothed"), smoother=settings)
        t, c = time.perf_counter(), time.process_time()
        res = estimate_trajectories(frames, sign_map, camera, es, progress=False)
        t_pipe, c_pipe = time.perf_counter() - t, time.process_time() - c
        err_p = np.abs(res.methods["smoothed"].world_T_cam[:, :3, 3] - gt.world_t_cam).mean(0)
        out.update(pipeline_s=t_pipe, pipeline_cpu_s=c_pipe, pipeline_mae_xyz=err_p.tolist())
        print(
            f"estimate_trajectories (pnp + smoothed, no sigmas): {t_pipe:.2f} s, CPU "
            f"{c_pipe:.2f} s; stages {', '.join(f'{k} {v:.1f} s' for k, v in res.timing_s.items())}"
            f"; {len(res.outliers.rejected)} rejected; MAE xyz {np.round(err_p, 4)}"
        )
    print(
        f"batch LM + per-frame PnP initialisation (what a user waits for): "
        f"{r.seconds + t_pnp:.2f} s, CPU {c_batch + c_pnp:.2f} s"
    )
    if args.sigmas:
        graph_s = SmootherSettings(
            motion=args.motion, compute_sigmas=True, max_sigma_frames=args.frames
        )
        t = time.perf_counter()
        r2 = smooth_batch(meas, gt.stamps_s, init, camera, graph_s, default)
        print(
            f"marginals (chain-ordered Bayes tree, all {args.frames} poses): "
            f"{r2.sigma_seconds:.2f} s "
            f"(whole run {time.perf_counter() - t:.2f} s)"
        )
        out["marginals_s"] = r2.sigma_seconds
    if not args.no_isam:
        n = args.isam_frames or args.frames
        sub = collect_measurements(frames[:n], sign_map, camera)
        ri = smooth_isam2(sub, gt.stamps_s[:n], init[:n], camera, settings, default)
        ms = ri.per_frame_ms
        cpu = ri.per_frame_cpu_ms
        q = np.percentile(ms, [50, 90, 99])
        last = np.median(ms[-min(500, n) :])
        print(
            f"iSAM2 over {n} frames: median {q[0]:.2f} ms/frame (p90 {q[1]:.2f}, p99 {q[2]:.2f}, "
            f"median of the last 500 {last:.2f}); total {ri.seconds:.1f} s incl. final convergence"
        )
        if cpu is not None:
            qc = np.percentile(cpu, [50, 90])
            print(
                f"iSAM2 CPU: median {qc[0]:.2f} ms/frame (p90 {qc[1]:.2f}, "
                f"median of the last 500 {np.median(cpu[-min(500, n) :]):.2f})"
            )
            out["isam2_cpu_median_ms"] = float(qc[0])
        d = (
            np.abs(ri.world_T_cam[:, :3, 3] - r.world_T_cam[:n, :3, 3]).max()
            if n == args.frames
            else None
        )
        out.update(isam2_frames=n, isam2_median_ms=float(q[0]), isam2_p90_ms=float(q[1]))
        if d is not None:
            print(f"iSAM2 final vs batch: max position difference {d * 1e3:.3f} mm")
            out["isam2_vs_batch_mm"] = float(d * 1e3)
    if args.json:
        with atomic_write(args.json, encoding="utf-8") as f:
            json.dump(out, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
