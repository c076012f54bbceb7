"""Time ``pipeline.observe`` against decoding the video alone, and check it is deterministic.

Simulates a 1080p flight in front of the bundled pylon (kept in the work
folder for reruns), then, in one process and one after the other:

* ``decode_only``: read and decode every frame to grey (the floor no frontend
  can beat; on a shared machine the ratios to it are what compare runs);
* ``observe_wN``: ``pipeline.observe`` with tracking and ``--workers N`` for
  each N in ``--workers`` (``observe_wN_cL`` for each chunk length L of
  ``--chunks``: tracking starts again with a full-frame search every L frames).

Prints seconds, ms per frame and the ratio to ``decode_only`` (min and median
over ``--repeat`` rounds, each configuration's ratio taken to the decode-only
pass of its own round), what the chunk length costs the tracking (share of
frames searched only around predictions, decoded signs per frame, frames the
per-frame PnP poses), and whether the ``observations.jsonl`` of every worker
count are byte-identical. ``--scene independent`` times the flight of
``scripts/independent_flight.py`` (photographs, members in front) instead of
the simulator's.

``--against REV`` also runs ``signpose/pipeline.py`` and ``frontend/detector.py``
as they were at git revision REV (``git show``; the rest of the package is
today's, so the decoder is the same), interleaved with today's, for a
before/after in one run on a shared machine. It works for revisions whose
``observe`` takes (source, map, camera, settings, progress, out_path).

    .venv/bin/python scripts/bench_observe.py --frames 120 --workers 1 2 --repeat 2 [--json PATH]
    .venv/bin/python scripts/bench_observe.py --frames 400 --workers 2 --chunks 50 100 200
    .venv/bin/python scripts/bench_observe.py --workers 1 2 --repeat 3 --against ae0faeb
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import importlib.util
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

from independent_flight import drawn_once
from signpose.estimator.perframe import solve_frame_pnp
from signpose.frontend import detector
from signpose.maps.loader import bundled_map_path, load_map

from signpose import pipeline
from signpose.core.fileio import atomic_write, ensure_dir
from signpose.io.camera_file import load_camera
from signpose.io.sources import open_source
from signpose.sim.flight import SimSettings, simulate, simulated_camera

BENCH_SEED = 7


def _flight(work: Path, frames: int, width: int, height: int) -> Path:
    """The simulated flight's video in ``work/flight`` (simulated once per size)."""
    stamp = work / "flight" / "bench_observe.json"
    key = {"frames": frames, "width": width, "height": height, "seed": BENCH_SEED}
    video = work / "flight" / "video.mp4"
    if stamp.is_file() and video.is_file() and json.loads(stamp.read_text()) == key:
        return video
    settings = SimSettings(frames=frames, width=width, height=height, seed=BENCH_SEED)
    sim = simulate(load_map(bundled_map_path()), work / "flight", settings, progress=False)
    with atomic_write(stamp) as f:
        json.dump(key, f)
    return Path(sim.frames_path)


def _independent(work: Path, frames: int, width: int, height: int) -> Path:
    """The flight of ``scripts/independent_flight.py`` in ``work/independent`` (drawn once)."""
    return drawn_once(work / "independent", frames, width, height, "bench_observe.json")


def _quality(result, sign_map, camera) -> dict:
    """What tracking gave: tracked share, decoded signs per frame, frames the PnP poses."""
    n = max(len(result.frames), 1)
    posed = sum(solve_frame_pnp(f, sign_map, camera).world_T_cam is not None for f in result.frames)
    return {
        "tracked_share": round(result.tracked_frames / n, 4),
        "signs_per_frame": round(sum(len(f.signs) for f in result.frames) / n, 3),
        "pnp_coverage": round(posed / n, 4),
    }


def _module_at(rev: str, path: str, name: str, work: Path) -> ModuleType:
    """The file ``path`` of git revision ``rev`` loaded as module ``name``."""
    root = Path(__file__).resolve().parent.parent
    text = subprocess.run(
        ["git", "show", f"{rev}:{path}"], cwd=root, check=True, capture_output=True, text=True
    ).stdout
    file = work / f"{name}.py"
    file.write_text(text, encoding="utf-8")
    spec = importlib.util.spec_from_file_location(name, file)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up while it loads
    with _detector_is(module if name.endswith("detector") else None):
        spec.loader.exec_module(module)
    return module


@contextlib.contextmanager
def _detector_is(module: ModuleType | None) -> Iterator[None]:
    """``signpose.frontend.detector`` resolves to ``module`` meanwhile (None: today's)."""
    if module is None:
        yield
        return
    sys.modules["signpose.frontend.detector"] = module
    try:
        yield
    finally:
        sys.modules["signpose.frontend.detector"] = detector


def _decode_only(video: Path) -> float:
    t0 = time.perf_counter()
    for frame in open_source(video):
        frame.gray()
    return time.perf_counter() - t0


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    p.add_argument(
        "--chunks", type=int, nargs="+", help="chunk lengths to compare (default: the default)"
    )
    p.add_argument("--scene", choices=("sim", "independent"), default="sim")
    p.add_argument("--repeat", type=int, default=2, help="rounds of every configuration")
    p.add_argument(
        "--work", type=Path, default=Path(tempfile.gettempdir()) / "signpose-bench-observe"
    )
    p.add_argument("--json", type=Path, help="write the numbers here")
    p.add_argument("--against", metavar="REV", help="also time the pipeline+detector of REV")
    return p.parse_args(argv)


def _configurations(args, versions) -> list[tuple[str, str, ModuleType, ModuleType | None, dict]]:
    """(key, group, module, its detector, ObserveSettings keywords) of every configuration;
    a group's outputs must be the same bytes for every worker count."""
    out = []
    for chunk in args.chunks or [None]:
        for n in args.workers:
            for name, (module, its_detector) in versions.items():
                kw = {"workers": n} | ({} if chunk is None else {"chunk_frames": chunk})
                group = name + ("" if chunk is None else f"_c{chunk}")
                out.append((f"{name}_w{n}" + group[len(name) :], group, module, its_detector, kw))
    return out


def _summary(values: list[float]) -> dict:
    return {
        "min": round(min(values), 3),
        "median": round(statistics.median(values), 3),
        "all": [round(v, 3) for v in values],
    }


def main(argv: list[str] | None = None) -> int:
    args = _parse_args(argv)
    work = ensure_dir(args.work)
    versions = {"observe": (pipeline, None)}
    if args.against:
        old_detector = _module_at(args.against, "frontend/detector.py", "_against_detector", work)
        with _detector_is(old_detector):
            old = _module_at(args.against, "signpose/pipeline.py", "_against_pipeline", work)
        versions[args.against] = (old, old_detector)
    sign_map = load_map(bundled_map_path())
    if args.scene == "sim":
        video = _flight(work, args.frames, args.width, args.height)
        camera = simulated_camera(SimSettings(width=args.width, height=args.height))
    else:
        video = _independent(work, args.frames, args.width, args.height)
        camera = load_camera(video.parent / "camera.yaml")
    # The machine is shared: every configuration runs --repeat times, interleaved with
    # a decode-only pass per round; each run's ratio is to its round's decode-only time.
    times: dict[str, list[float]] = {"decode_only": []}
    ratios: dict[str, list[float]] = {}
    quality: dict[str, dict] = {}
    digests: dict[str, set[str]] = {}
    for _ in range(args.repeat):
        base = _decode_only(video)
        times["decode_only"].append(base)
        for key, group, module, its_detector, kw in _configurations(args, versions):
            out = work / f"{key}.jsonl"
            t0 = time.perf_counter()
            with _detector_is(its_detector):
                result = module.observe(
                    open_source(video), sign_map, camera, module.ObserveSettings(**kw), False, out
                )
            spent = time.perf_counter() - t0
            times.setdefault(key, []).append(spent)
            ratios.setdefault(key, []).append(spent / base)
            if key not in quality:  # the first round's only
                quality[key] = _quality(result, sign_map, camera)
            digests.setdefault(group, set()).add(hashlib.sha256(out.read_bytes()).hexdigest())
    _print(args, times, ratios, quality, digests)
    if args.json:
        data = {
            "frames": args.frames,
            "size": [args.width, args.height],
            "scene": args.scene,
            "repeat": args.repeat,
            "times_s": {k: _summary(v) for k, v in times.items()},
            "ratio_to_decode_only": {k: _summary(v) for k, v in ratios.items()},
            "quality": quality,
            "identical": {g: len(d) == 1 for g, d in digests.items()},
            "sha256": {g: sorted(d) for g, d in digests.items()},
            "load_average_1min": round(os.getloadavg()[0], 2),
            "cpu_count": os.cpu_count(),
        }
        with atomic_write(args.json) as f:
            f.write(json.dumps(data, indent=2) + "\n")
    return 0


def _print(args, times, ratios, quality, digests) -> None:
    print(
        f"{args.frames} frames {args.width}x{args.height} ({args.scene}) on {os.cpu_count()} "
        f"cores, {args.repeat} rounds; load average {os.getloadavg()[0]:.1f}"
    )
    print(
        f"{'run':22s} {'min [s]':>8s} {'ms/frame':>9s} {'/ decode_only min':>18s} {'median':>7s}"
        f" {'tracked':>8s} {'signs/fr':>9s} {'PnP posed':>10s}"
    )
    for k, v in times.items():
        r = ratios.get(k, [1.0])
        q = quality.get(k)
        extra = (
            f" {100 * q['tracked_share']:7.1f}% {q['signs_per_frame']:9.2f} "
            f"{100 * q['pnp_coverage']:9.1f}%"
            if q
            else ""
        )
        print(
            f"{k:22s} {min(v):8.2f} {1000 * min(v) / args.frames:9.1f} {min(r):18.2f} "
            f"{statistics.median(r):7.2f}{extra}"
        )
    for group, found in digests.items():
        print(
            f"{group}: observations.jsonl identical over {args.repeat} x workers "
            f"{args.workers}: {len(found) == 1}"
        )


if __name__ == "__main__":
    sys.exit(main())
