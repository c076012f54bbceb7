"""Benchmark ``signpose run`` on 1080p flights: frames/s, Table 5 split, ratio to decoding.

Simulates a flight in front of the bundled pylon (not timed; reused when the
work folder already holds one of the same size), then times the whole run:
video decoding, detection, sign decoding, tracking, estimation and outputs
(files, plots, result.mcap). Prints frames per second and the time split by
stage; ``--json`` writes the same numbers.

Throughput as a ratio (issue 14): in the same run, one after the other, each
``--repeat`` times, for every scene of ``--scenes`` and every ``--workers``
value: decode-only (read and convert every frame of the same video to gray)
and ``signpose run`` (all estimators, plots, MCAP); the ratio is the run's
frames/s over the decode-only frames/s measured just before it, and min /
median are over the repeats (a shared machine is noisy: ratios of neighbours
compare, absolute times do not). Scenes: ``sim`` (the simulator's flight) and
``independent`` (``scripts/independent_flight.py``: the same trajectory drawn
without the simulator: photographs behind, members and a conductor in front).

CPU: this process's (all threads, waited-for children) plus the chunk and
plot processes' (each writes its CPU per job under ``pipeline.PROFILE_ENV``;
they are the forkserver's children, which no rusage of this process counts).
``--budget`` splits the first run's CPU by stage: this process's main thread
per function (exclusive of the others listed; with ``--workers 1`` that is
the whole run but the video reader thread), the processes as totals.

    .venv/bin/python scripts/bench_pipeline.py --frames 1000
    .venv/bin/python scripts/bench_pipeline.py --frames 300 --workers 1 --budget
    .venv/bin/python scripts/bench_pipeline.py --frames 300 --scenes sim independent \
        --workers 1 2 --repeat 3 --json /tmp/bench_pipeline.json
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import json
import os
import platform
import resource
import statistics
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from independent_flight import drawn_once
from signpose.estimator import estimate as estimate_module
from signpose.estimator import perframe
from signpose.estimator.estimate import EstimatorSettings
from signpose.estimator.smoother import SmootherSettings
from signpose.maps.loader import bundled_map_path, load_map

from signpose import pipeline
from signpose.core.errors import InputError
from signpose.core.fileio import atomic_write, ensure_dir
from signpose.io import mcap as mcap_io
from signpose.io.camera_file import load_camera
from signpose.io.results import read_report
from signpose.io.sources import open_source
from signpose.pipeline import ObserveSettings, RunResult, RunSettings
from signpose.sim.flight import SimSettings, simulate, simulated_camera

STAGES = (
    ("decode_video", "decode video (reader thread)"),
    ("wait_video", "  of which the loop waited"),
    ("detect", "detect (cascade + merge)"),
    ("decode", "decode signs"),
    ("track", "track (per-frame PnP)"),
    ("per_frame", "per-frame methods (overlapped)"),
    ("estimate", "estimate (all methods)"),
    ("outputs", "outputs (files, plots, MCAP)"),
)


# --budget: the main process's CPU (its main thread's time, time.thread_time) per function,
# exclusive of the budgeted functions it calls, by stage. Functions looked up by name at
# call time, so wrapping the module attribute times every call.
BUDGET = (
    ("observe", pipeline, "detect_frame", "frontend: detector + decoder (detect_frame)"),
    ("observe", pipeline.FrameTracker, "plan", "tracking: predictions (FrameTracker.plan)"),
    ("observe", pipeline.FrameTracker, "finish", "tracking: PnP, consistency (finish)"),
    ("observe", pipeline, "append_observation", "observations.jsonl lines"),
    ("observe", pipeline, "_first_frame_size", "first-frame size probe"),
    ("observe", perframe.PerFrameRun, "add", "per-frame methods (PerFrameRun.add)"),
    ("estimate", estimate_module, "_noise_scaled", "pixel noise scale"),
    ("estimate", estimate_module, "collect_measurements", "smoother: measurements"),
    ("estimate", estimate_module, "smooth_batch", "smoother: batch solves + marginals"),
    ("estimate", estimate_module, "smooth_isam2", "smoother: iSAM2"),
    ("estimate", estimate_module, "_innovation_rounds", "smoother: innovation tests"),
    ("estimate", estimate_module, "tune_motion_prior", "motion-prior tuning"),
    ("estimate", estimate_module, "_smoothed_status", "smoothed statuses"),
    ("estimate", estimate_module, "_outliers", "outlier report"),
    ("estimate", estimate_module, "check_orientations", "orientation check"),
    ("estimate", pipeline, "estimate_trajectories", "estimate: the rest"),
    ("outputs", pipeline, "refine_flight", "map refinement (refine_flight)"),
    ("outputs", pipeline, "write_outputs", "TUM, CSV, report.json (write_outputs)"),
    ("outputs", pipeline, "write_run_geo", "geodetic outputs"),
    ("outputs", mcap_io, "write_result_mcap", "result.mcap"),
    ("outputs", pipeline, "_compare", "comparison with the ground truth"),
    ("outputs", pipeline, "write_run_report", "report.html"),
    ("outputs", pipeline, "_add_to_report", "report.json pipeline section"),
    ("run", pipeline, "run", "run: the rest (merge, trajectories, run.json ...)"),
)


class _Budget:
    """Exclusive main-thread CPU per budgeted function (and per plot, drawn in this process)."""

    def __init__(self) -> None:
        self.cpu: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self.each: dict[str, list[float]] = {}  # every call's exclusive CPU
        self._inner: list[float] = []

    def wrap(self, fn, label: str):
        @functools.wraps(fn)
        def timed(*args, **kwargs):
            if threading.current_thread() is not threading.main_thread():
                return fn(*args, **kwargs)
            t0 = time.thread_time()
            self._inner.append(0.0)
            try:
                return fn(*args, **kwargs)
            finally:
                inner, spent = self._inner.pop(), time.thread_time() - t0
                self.cpu[label] = self.cpu.get(label, 0.0) + spent - inner
                self.calls[label] = self.calls.get(label, 0) + 1
                self.each.setdefault(label, []).append(spent - inner)
                if self._inner:
                    self._inner[-1] += spent

        return timed


@contextlib.contextmanager
def _budgeted(budget: _Budget, plots_here: bool):
    """The BUDGET functions timed into ``budget``; ``plots_here``: the plots too (only where
    they are drawn in this process: a process is sent the plot functions themselves)."""
    saved = [(owner, name, getattr(owner, name)) for _, owner, name, _ in BUDGET]
    saved.append((pipeline, "PLOTS", pipeline.PLOTS))
    for _, owner, name, label in BUDGET:
        setattr(owner, name, budget.wrap(getattr(owner, name), label))
    if plots_here:
        pipeline.PLOTS = tuple((n, budget.wrap(draw, f"plot {n}")) for n, draw in pipeline.PLOTS)
    try:
        yield budget
    finally:
        for owner, name, value in saved:
            setattr(owner, name, value)


def _process_cpu(folder: Path, t0: float, t1: float) -> dict[str, dict[str, float]]:
    """CPU of the chunk and plot processes whose jobs ran within [t0, t1] (time.time()), from
    their pipeline.PROFILE_ENV records: kind -> {"jobs": CPU of their jobs, "starts": CPU
    before each process's first job (after the fork), "processes": how many} [s]."""
    records = [json.loads(p.read_text(encoding="utf-8")) for p in folder.glob("*.json")]
    records = [r for r in records if t0 <= r["start"] and r["end"] <= t1]
    # A process's start is counted once, with the kind of its first job (a chunk process
    # lent to another chunk writes "lent" jobs after its own "chunk" ones).
    first: dict[int, dict] = {}
    for r in records:
        if r["pid"] not in first or r["cpu_before_s"] < first[r["pid"]]["cpu_before_s"]:
            first[r["pid"]] = r
    out: dict[str, dict[str, float]] = {}
    for kind in sorted({r["kind"] for r in records}):
        mine = [r for r in records if r["kind"] == kind]
        starts = [r["cpu_before_s"] for r in first.values() if r["kind"] == kind]
        out[kind] = {
            "jobs": sum(r["cpu_s"] for r in mine),
            "starts": sum(starts),
            "processes": len({r["pid"] for r in mine}),
        }
    return out


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


def _independent(work: Path, frames: int, width: int, height: int):
    """The flight of ``scripts/independent_flight.py`` in ``work/independent`` (drawn once)."""
    out = work / "independent"
    video = drawn_once(out, frames, width, height, "bench.json")
    return video, out / "groundtruth.tum", load_camera(out / "camera.yaml")


def _cpu_s() -> float:
    """User + system CPU time of this process, its threads and its waited-for children [s]."""
    total = 0.0
    for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN):
        r = resource.getrusage(who)
        total += r.ru_utime + r.ru_stime
    return total


def _decode_only(video: Path) -> tuple[float, float]:
    """Frames per second of reading and converting every frame to gray, nothing else, and
    the CPU it took [s] (this process, every thread)."""
    cpu0, t0 = _cpu_s(), time.perf_counter()
    n = 0
    for frame in open_source(video):
        frame.gray()
        n += 1
    return n / (time.perf_counter() - t0), _cpu_s() - cpu0


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
    p.add_argument(
        "--no-overlap",
        action="store_true",
        help="one stage after another (RunSettings.overlap=False; the same files)",
    )
    p.add_argument(
        "--scenes",
        nargs="+",
        choices=("sim", "independent"),
        default=["sim"],
        help="flights to time (default: sim); independent = scripts/independent_flight.py",
    )
    p.add_argument(
        "--workers",
        type=int,
        nargs="+",
        default=[0],
        help="--workers of each run (default 0: the run's default, 2 on 2 cores)",
    )
    p.add_argument("--repeat", type=int, default=1, help="rounds of every configuration")
    p.add_argument(
        "--count-pnp",
        action="store_true",
        help="count the first run's solve_frame_pnp calls (tracker, estimator) in this "
        "process: with --workers 1 that is every call; chunk processes are not counted",
    )
    p.add_argument(
        "--budget",
        action="store_true",
        help="the first run's CPU by stage: this process's main thread per function (with "
        "--workers 1 all but the video reader thread; else chunk 0 and the rest of the run), "
        "the chunk and plot processes as totals",
    )
    p.add_argument("--quiet", action="store_true")
    return p.parse_args(argv)


def _print_timing(args: argparse.Namespace, timed: _Timed) -> None:
    """frames/s, CPU time and the per-stage split, as a table on stdout."""
    result, wall, cpu = timed.result, timed.wall, timed.cpu
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
    split = [f"main process {timed.cpu_main:.2f}"] + [
        f"{kind} processes ({p['processes']}) {p['jobs']:.2f} + their starts {p['starts']:.2f}"
        for kind, p in timed.processes.items()
    ]
    print("CPU [s]: " + "; ".join(split) + " (the forkserver's start is not counted)")
    print(f"{'stage':32s} {'total [s]':>10s} {'ms/frame':>9s} {'share':>7s}")
    for key, label in STAGES:
        v = t.get(key, 0.0)
        print(f"{label:32s} {v:10.2f} {1000 * v / max(n, 1):9.2f} {100 * v / wall:6.1f}%")
    print(f"{'total (wall)':32s} {wall:10.2f} {1000 * wall / max(n, 1):9.2f} {100.0:6.1f}%")
    print(
        "(video decoding runs in a reader thread, overlapping detection; the per-frame methods "
        "run in the main process as frames come, overlapping the chunk processes; shares of "
        "wall time)"
    )
    print("coverage: " + ", ".join(f"{k} {100 * v:.1f}%" for k, v in result.coverage.items()))
    print(
        "position RMSE: " + ", ".join(f"{k} {v:.3f} m" for k, v in result.position_rmse_m.items())
    )


def _print_budget(budget: _Budget, timed: _Timed) -> None:
    """The first run's CPU budget (``--budget``) as a table."""
    n = max(timed.result.n_frames, 1)
    print("\nCPU budget of the first run (main thread: exclusive time per function)")
    print(
        f"{'stage':10s} {'what':52s} {'CPU [s]':>8s} {'ms/frame':>9s} {'calls':>6s} "
        f"{'median ms/call':>14s}"
    )
    rows = [(stage, label) for stage, _, _, label in BUDGET]
    rows += [("outputs", k) for k in budget.cpu if k.startswith("plot ")]
    for stage, label in rows:
        if label in budget.cpu:
            c, calls = budget.cpu[label], budget.calls[label]
            med = 1000 * statistics.median(budget.each[label])
            print(f"{stage:10s} {label:52s} {c:8.2f} {1000 * c / n:9.2f} {calls:6d} {med:14.2f}")
    main_thread = sum(budget.cpu.values())
    other = timed.cpu_main - main_thread
    print(
        f"{'':10s} {'main process, other threads (video reader, OpenCV, BLAS)':52s} "
        f"{other:8.2f} {1000 * other / n:9.2f}"
    )
    for kind, p in timed.processes.items():
        for what, v in (("jobs", p["jobs"]), ("starts", p["starts"])):
            label = f"{kind} processes ({p['processes']}): {what}"
            print(f"{'':10s} {label:52s} {v:8.2f} {1000 * v / n:9.2f}")
    print(f"{'':10s} {'total':52s} {timed.cpu:8.2f} {1000 * timed.cpu / n:9.2f}")


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
        "overlap": not args.no_overlap,
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
    }


@contextlib.contextmanager
def _counting_pnp(calls: dict[str, int]):
    """solve_frame_pnp counted by caller: the tracker's (pipeline) and the estimator's."""
    real = perframe.solve_frame_pnp

    def counter(who: str):
        def counted(*a, **kw):
            calls[who] += 1
            return real(*a, **kw)

        return counted

    pipeline.solve_frame_pnp = counter("tracker")
    perframe.solve_frame_pnp = counter("estimator")
    try:
        yield calls
    finally:
        pipeline.solve_frame_pnp = perframe.solve_frame_pnp = real


@dataclass(frozen=True)
class _Timed:
    """One timed run: its result, wall time and CPU [s].

    ``cpu_main``: this process (all its threads, and children it waited for);
    ``processes``: the chunk and plot processes' (``_process_cpu``), which are the
    forkserver's children (no rusage of this process counts them). The forkserver's own
    start (importing the pipeline, once per bench process) is in neither.
    """

    result: RunResult
    wall: float
    cpu_main: float
    processes: dict

    @property
    def cpu(self) -> float:
        return self.cpu_main + sum(p["jobs"] + p["starts"] for p in self.processes.values())


def _timed_run(args, scene: str, workers: int, flight) -> _Timed:
    """One ``signpose run`` of a scene's flight."""
    video, gt, camera = flight
    settings = RunSettings(
        observe=ObserveSettings(tracking=not args.no_tracking, workers=workers),
        estimator=EstimatorSettings(smoother=SmootherSettings(compute_sigmas=not args.no_sigmas)),
        plots=not args.no_plots,
        overlap=not args.no_overlap,
    )
    cpu0, since = _cpu_s(), time.time()
    t0 = time.perf_counter()
    result = pipeline.run(  # looked up here: --budget wraps it
        video,
        load_map(bundled_map_path()),
        args.work / f"run_{scene}_w{workers}",
        camera=camera,
        gt_path=gt,
        settings=settings,
        progress=not args.quiet,
    )
    wall, cpu = time.perf_counter() - t0, _cpu_s() - cpu0
    return _Timed(result, wall, cpu, _process_cpu(args.cpu_records, since, time.time()))


def _summary(values: list[float]) -> dict:
    return {
        "min": round(min(values), 4),
        "median": round(statistics.median(values), 4),
        "all": [round(v, 4) for v in values],
    }


def _ratio_table(ratios: dict) -> None:
    """Per scene and worker count: run frames/s, decode-only frames/s, their ratio."""
    print(
        f"\n{'scene':12s} {'workers':>7s} {'run f/s':>14s} {'decode f/s':>14s} "
        f"{'run / decode-only (min / median)':>34s}"
    )
    for scene, rows in ratios.items():
        for key, row in rows.items():
            if key == "decode_only_fps":
                continue
            run_fps, dec, ratio = row["run_fps"], rows["decode_only_fps"], row["ratio"]
            print(
                f"{scene:12s} {key[1:]:>7s} {run_fps['median']:14.1f} {dec['median']:14.1f} "
                f"{ratio['min']:16.3f} / {ratio['median']:.3f}"
            )
    print("(ratio of each run to the decode-only pass just before it; min / median over repeats)")


def main(argv: list[str] | None = None) -> int:
    args = _parse_args(argv)
    ensure_dir(args.work)
    # Every chunk and plot process writes its CPU here (read back per run by _process_cpu);
    # set before the first process starts: the forkserver passes its environment on.
    args.cpu_records = Path(tempfile.mkdtemp(prefix="cpu-", dir=args.work))
    os.environ[pipeline.PROFILE_ENV] = str(args.cpu_records)
    flights, sim_s = {}, 0.0
    for scene in args.scenes:
        if scene == "sim":
            video, gt, camera, sim_s = _flight(
                args.work, args.frames, args.width, args.height, args.quiet
            )
            flights[scene] = (video, gt, camera)
        else:
            flights[scene] = _independent(args.work, args.frames, args.width, args.height)
    samples: dict[str, dict[str, list[float]]] = {}
    first, est = None, {}
    pnp_calls = {"tracker": 0, "estimator": 0}
    budget = _Budget()
    for _ in range(args.repeat):
        for scene, flight in flights.items():
            for workers in args.workers:
                decode_fps, decode_cpu = _decode_only(flight[0])
                counting = _counting_pnp(pnp_calls) if args.count_pnp and first is None else None
                budgeting = (
                    _budgeted(budget, workers == 1) if args.budget and first is None else None
                )
                with counting or contextlib.nullcontext(), budgeting or contextlib.nullcontext():
                    timed = _timed_run(args, scene, workers, flight)
                if first is None:  # its folder is run again by the later rounds
                    first = (scene, workers, timed, decode_fps, decode_cpu)
                    est = result_estimator_timing(args.work / f"run_{scene}_w{workers}")
                row = samples.setdefault(f"{scene}/w{workers}", {"decode": [], "run": []})
                row["decode"].append(decode_fps)
                row["run"].append(timed.result.n_frames / timed.wall)
    scene, workers, timed, decode_fps, decode_cpu = first
    result, wall, cpu = timed.result, timed.wall, timed.cpu
    if args.count_pnp:
        where = "every call" if workers == 1 else "chunk processes not counted"
        print(f"solve_frame_pnp calls of the first run in this process ({where}): {pnp_calls}")
    print(f"first run: scene {scene}, --workers {workers}")
    _print_timing(args, timed)
    allowed = result.n_frames / (0.5 * decode_fps)
    print(
        f"issue 14's budget (0.5x the decode-only {decode_fps:.1f} frames/s of its round, "
        f"{decode_cpu:.2f} s CPU): {allowed:.2f} s wall for the whole run, "
        f"{100 * allowed / wall:.0f}% of this one's"
    )
    if est:
        print("estimator split [s]: " + ", ".join(f"{k} {v:.1f}" for k, v in est.items()))
    if args.budget:
        _print_budget(budget, timed)
    if sim_s:
        print(f"(simulation, not timed above: {sim_s:.1f} s)")
    ratios: dict[str, dict] = {}
    for key, row in samples.items():
        scene, w = key.split("/")
        per_run = [r / d for r, d in zip(row["run"], row["decode"], strict=True)]
        ratios.setdefault(scene, {})[w] = {
            "run_fps": _summary(row["run"]),
            "decode_only_fps": _summary(row["decode"]),
            "ratio": _summary(per_run),
        }
        ratios[scene]["decode_only_fps"] = _summary(
            [d for k, r in samples.items() if k.startswith(scene + "/") for d in r["decode"]]
        )
    _ratio_table(ratios)
    if args.json:
        data = _json_data(args, result, wall, cpu, est) | {
            "first_run": {"scene": scene, "workers": workers},
            "repeat": args.repeat,
            "load_average_1min": round(os.getloadavg()[0], 2),
            "ratio_to_decode_only": ratios,
            "decode_only_cpu_s": round(decode_cpu, 3),
            "cpu_main_s": round(timed.cpu_main, 3),
            "cpu_processes_s": timed.processes,
        }
        if args.budget:
            data["budget_cpu_s"] = {k: round(v, 4) for k, v in budget.cpu.items()}
        with atomic_write(args.json) as f:
            f.write(json.dumps(data, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
