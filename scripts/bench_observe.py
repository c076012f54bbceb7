"""Time ``pipeline.observe`` against decoding the video alone, and check it is deterministic.

Simulates a 1080p flight in front of the bundled pylon (kept in the work
folder for reruns), then, in one process and one after the other:

* ``decode_only``: read and decode every frame to grey (the floor no frontend
  can beat; on a shared machine the ratios to it are what compare runs);
* ``observe_wN``: ``pipeline.observe`` with tracking and ``--workers N`` for
  each N in ``--workers``.

Prints seconds, ms per frame and the ratio to ``decode_only``, and whether
the ``observations.jsonl`` of every worker count are byte-identical.

    .venv/bin/python scripts/bench_observe.py --frames 120 --workers 1 2 --repeat 2 [--json PATH]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

from signpose.maps.loader import bundled_map_path, load_map

from signpose.core.fileio import atomic_write, ensure_dir
from signpose.io.sources import open_source
from signpose.pipeline import ObserveSettings, observe
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
    args = p.parse_args(argv)
    work = ensure_dir(args.work)
    video = _flight(work, args.frames, args.width, args.height)
    sign_map = load_map(bundled_map_path())
    camera = simulated_camera(SimSettings(width=args.width, height=args.height))
    # The machine is shared: every configuration runs --repeat times, interleaved,
    # and the fastest run of each counts.
    times: dict[str, float] = {}
    digests: set[str] = set()
    for _ in range(args.repeat):
        times["decode_only"] = min(times.get("decode_only", math.inf), _decode_only(video))
        for n in args.workers:
            out = work / f"observations_w{n}.jsonl"
            t0 = time.perf_counter()
            observe(
                open_source(video),
                sign_map,
                camera,
                ObserveSettings(workers=n),
                progress=False,
                out_path=out,
            )
            key = f"observe_w{n}"
            times[key] = min(times.get(key, math.inf), time.perf_counter() - t0)
            digests.add(hashlib.sha256(out.read_bytes()).hexdigest())
    base = times["decode_only"]
    print(f"{args.frames} frames {args.width}x{args.height} on {os.cpu_count()} cores")
    print(f"{'run':14s} {'total [s]':>10s} {'ms/frame':>9s} {'/ decode_only':>14s}")
    for k, v in times.items():
        print(f"{k:14s} {v:10.2f} {1000 * v / args.frames:9.1f} {v / base:14.2f}")
    identical = len(digests) == 1
    print(f"observations.jsonl identical over {args.repeat} x workers {args.workers}: {identical}")
    if args.json:
        data = {
            "frames": args.frames,
            "size": [args.width, args.height],
            "times_s": {k: round(v, 3) for k, v in times.items()},
            "ratio_to_decode_only": {k: round(v / base, 3) for k, v in times.items()},
            "identical": identical,
            "sha256": sorted(digests),
            "cpu_count": os.cpu_count(),
        }
        with atomic_write(args.json) as f:
            f.write(json.dumps(data, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
