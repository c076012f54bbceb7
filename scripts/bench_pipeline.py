"""Benchmark ``signpose run`` on a simulated 1080p flight (the paper's Table 5 split).

Simulates a flight in front of the bundled pylon (not timed; reused when the
work folder already holds one of the same size), then times the whole run:
video decoding, detection, sign decoding, tracking, estimation and outputs
(files, plots, result.mcap). Prints frames per second and the time split by
stage; ``--json`` writes the same numbers.

    .venv/bin/python scripts/bench_pipeline.py --frames 1000
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import sys
import tempfile
import time
from pathlib import Path

from signpose.estimator.estimate import EstimatorSettings
from signpose.estimator.smoother import SmootherSettings
from signpose.maps.loader import bundled_map_path, load_map

from signpose.core.errors import InputError
from signpose.core.fileio import atomic_write, ensure_dir
from signpose.io.results import read_report
from signpose.pipeline import ObserveSettings, RunResult, RunSettings, run
from signpose.sim.flight import SimSettings, simulate, simulated_camera

STAGES = (
    ("decode_video", "decode video (reader thread)"),
    ("wait_video", "  of which the loop waited"),
    ("detect", "detect (cascade + merge)"),
    ("decode", "decode signs"),
    ("track", "track (per-frame PnP)"),
    ("estimate", "estimate (all methods)"),
    ("outputs", "outputs (files, plots, MCAP)"),
)


def _flight(work: Path, frames: int, width: int, height: int, quiet: bool):
    """The simulated flight in ``work/flight`` (simulated once per size)."""
    stamp = work / "flight" / "bench.json"
    settings = SimSettings(frames=frames, width=width, height=height)
    key = {"frames": frames, "width": width, "height": height}
    video = work / "flight" / "video.mp4"
    if stamp.is_file() and video.is_file() and json.loads(stamp.read_text()) == key:
        return video, work / "flight" / "groundtruth.tum", simulated_camera(settings), 0.0
    t0 = time.perf_counter()
    sim = simulate(load_map(bundled_map_path()), work / "flight", settings, progress=not quiet)
    elapsed = time.perf_counter() - t0
    with atomic_write(stamp) as f:
        json.dump(key, f)
    return sim.frames_path, sim.groundtruth_path, sim.camera, elapsed


def _cpu_s() -> float:
    """User + system CPU time of this process and its threads [s]."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def result_estimator_timing(run_dir: Path) -> dict:
    """The estimator's own split (baseline, pnp, smoothed, sigmas) from report.json."""
    try:
        return read_report(run_dir / "report.json").get("timing_s", {})
    except InputError:
        return {}


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--frames", type=int, default=1000, help="frames (default 1000)")
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--height", type=int, default=1080)
    p.add_argument(
        "--work",
        type=Path,
        default=Path(tempfile.gettempdir()) / "signpose-bench",
        help="work folder (the simulated flight is kept there for reruns)",
    )
    p.add_argument("--json", type=Path, help="write the numbers here")
    p.add_argument("--no-plots", action="store_true", help="time the run without PNG plots")
    p.add_argument("--no-tracking", action="store_true", help="full-frame detection every frame")
    p.add_argument("--no-sigmas", action="store_true", help="skip the smoother's marginal sigmas")
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def _print_timing(args: argparse.Namespace, result: RunResult, wall: float, cpu: float) -> None:
    """frames/s, CPU time and the per-stage split, as a table on stdout."""
    n = result.n_frames
    t = result.timing_s
    print(
        f"signpose run: {n} frames {args.width}x{args.height}, {wall:.1f} s wall, "
        f"{n / wall:.1f} frames/s (target >= 15; paper 6.5) on {os.cpu_count()} cores"
    )
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(
        f"CPU time {cpu:.1f} s ({1000 * cpu / max(n, 1):.0f} ms/frame, {cpu / wall:.2f} cores busy "
        f"on average); 1-min load average at the end {load:.1f}"
    )
    print(f"{'stage':32s} {'total [s]':>10s} {'ms/frame':>9s} {'share':>7s}")
    for key, label in STAGES:
        v = t.get(key, 0.0)
        print(f"{label:32s} {v:10.2f} {1000 * v / max(n, 1):9.2f} {100 * v / wall:6.1f}%")
    print(f"{'total (wall)':32s} {wall:10.2f} {1000 * wall / max(n, 1):9.2f} {100.0:6.1f}%")
    print("(video decoding runs in a reader thread, overlapping detection; shares of wall time)")
    print("coverage: " + ", ".join(f"{k} {100 * v:.1f}%" for k, v in result.coverage.items()))
    print(
        "position RMSE: " + ", ".join(f"{k} {v:.3f} m" for k, v in result.position_rmse_m.items())
    )


def _json_data(
    args: argparse.Namespace, result: RunResult, wall: float, cpu: float, est: dict
) -> dict:
    """What ``--json`` writes (reproduce_paper.py's Table 5 reads it)."""
    n = result.n_frames
    t = result.timing_s
    return {
        "frames": n,
        "size": [args.width, args.height],
        "wall_s": round(wall, 3),
        "cpu_s": round(cpu, 3),
        "frames_per_second": round(n / wall, 3),
        "stages_s": {k: round(t.get(k, 0.0), 4) for k, _ in STAGES},
        "stages_ms_per_frame": {k: round(1000 * t.get(k, 0.0) / max(n, 1), 3) for k, _ in STAGES},
        "coverage": result.coverage,
        "position_rmse_m": result.position_rmse_m,
        "tracking": not args.no_tracking,
        "sigmas": not args.no_sigmas,
        "estimator_timing_s": est,
        "plots": not args.no_plots,
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
    }


def main(argv: list[str] | None = None) -> int:
    args = _parse_args(argv)
    ensure_dir(args.work)
    video, gt, camera, sim_s = _flight(args.work, args.frames, args.width, args.height, args.quiet)
    settings = RunSettings(
        observe=ObserveSettings(tracking=not args.no_tracking),
        estimator=EstimatorSettings(smoother=SmootherSettings(compute_sigmas=not args.no_sigmas)),
        plots=not args.no_plots,
    )
    cpu0 = _cpu_s()
    t0 = time.perf_counter()
    result = run(
        video,
        load_map(bundled_map_path()),
        args.work / "run",
        camera=camera,
        gt_path=gt,
        settings=settings,
        progress=not args.quiet,
    )
    wall = time.perf_counter() - t0
    cpu = _cpu_s() - cpu0
    _print_timing(args, result, wall, cpu)
    est = result_estimator_timing(args.work / "run")
    if est:
        print("estimator split [s]: " + ", ".join(f"{k} {v:.1f}" for k, v in est.items()))
    if sim_s:
        print(f"(simulation, not timed above: {sim_s:.1f} s)")
    if args.json:
        with atomic_write(args.json) as f:
            f.write(json.dumps(_json_data(args, result, wall, cpu, est), indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
