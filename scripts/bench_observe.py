"""Time ``pipeline.observe`` against decoding the video alone, and check it is deterministic.

Simulates a 1080p flight in front of the bundled pylon (kept in the work
folder for reruns), then, in one process and one after the other:

* ``decode_only``: read and decode every frame to grey (the floor no frontend
  can beat; on a shared machine the ratios to it are what compare runs);
* ``observe_wN``: ``pipeline.observe`` with tracking and ``--workers N`` for
  each N in ``--workers``.

Prints seconds, ms per frame and the ratio to ``decode_only``, and whether
the ``observations.jsonl`` of every worker count are byte-identical.

``--against REV`` also runs ``signpose/pipeline.py`` and ``frontend/detector.py``
as they were at git revision REV (``git show``; the rest of the package is
today's, so the decoder is the same), interleaved with today's, for a
before/after in one run on a shared machine. It works for revisions whose
``observe`` takes (source, map, camera, settings, progress, out_path).

    .venv/bin/python scripts/bench_observe.py --frames 120 --workers 1 2 --repeat 2 [--json PATH]
    .venv/bin/python scripts/bench_observe.py --workers 1 2 --repeat 3 --against ae0faeb
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import importlib.util
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType

from signpose.frontend import detector
from signpose.maps.loader import bundled_map_path, load_map

from signpose import pipeline
from signpose.core.fileio import atomic_write, ensure_dir
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


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--width", type=int, default=1920)
    p.add_argument("--height", type=int, default=1080)
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    p.add_argument("--repeat", type=int, default=2, help="runs per configuration (fastest counts)")
    p.add_argument(
        "--work", type=Path, default=Path(tempfile.gettempdir()) / "signpose-bench-observe"
    )
    p.add_argument("--json", type=Path, help="write the numbers here")
    p.add_argument("--against", metavar="REV", help="also time the pipeline+detector of REV")
    args = p.parse_args(argv)
    work = ensure_dir(args.work)
    versions = {"observe": (pipeline, None)}
    if args.against:
        old_detector = _module_at(args.against, "frontend/detector.py", "_against_detector", work)
        with _detector_is(old_detector):
            old = _module_at(args.against, "signpose/pipeline.py", "_against_pipeline", work)
        versions[args.against] = (old, old_detector)
    video = _flight(work, args.frames, args.width, args.height)
    sign_map = load_map(bundled_map_path())
    camera = simulated_camera(SimSettings(width=args.width, height=args.height))
    # The machine is shared: every configuration runs --repeat times, interleaved,
    # and the fastest run of each counts.
    times: dict[str, float] = {}
    digests: dict[str, set[str]] = {name: set() for name in versions}
    for _ in range(args.repeat):
        times["decode_only"] = min(times.get("decode_only", math.inf), _decode_only(video))
        for n in args.workers:
            for name, (module, its_detector) in versions.items():
                out = work / f"{name}_w{n}.jsonl"
                t0 = time.perf_counter()
                with _detector_is(its_detector):
                    module.observe(
                        open_source(video),
                        sign_map,
                        camera,
                        module.ObserveSettings(workers=n),
                        False,
                        out,
                    )
                key = f"{name}_w{n}"
                times[key] = min(times.get(key, math.inf), time.perf_counter() - t0)
                digests[name].add(hashlib.sha256(out.read_bytes()).hexdigest())
    base = times["decode_only"]
    print(f"{args.frames} frames {args.width}x{args.height} on {os.cpu_count()} cores")
    print(f"{'run':18s} {'total [s]':>10s} {'ms/frame':>9s} {'/ decode_only':>14s}")
    for k, v in times.items():
        print(f"{k:18s} {v:10.2f} {1000 * v / args.frames:9.1f} {v / base:14.2f}")
    for name, found in digests.items():
        print(
            f"{name}: observations.jsonl identical over {args.repeat} x workers "
            f"{args.workers}: {len(found) == 1}"
        )
    identical = len(digests["observe"]) == 1
    if args.json:
        data = {
            "frames": args.frames,
            "size": [args.width, args.height],
            "times_s": {k: round(v, 3) for k, v in times.items()},
            "ratio_to_decode_only": {k: round(v / base, 3) for k, v in times.items()},
            "identical": identical,
            "sha256": sorted(digests["observe"]),
            "against": {
                "rev": args.against,
                "identical": len(digests[args.against]) == 1,
            }
            if args.against
            else None,
            "cpu_count": os.cpu_count(),
        }
        with atomic_write(args.json) as f:
            f.write(json.dumps(data, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
