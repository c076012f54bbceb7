"""Benchmark the flight simulator: frames/s and total seconds on one core.

Usage:
    OMP_NUM_THREADS=1 .venv/bin/python scripts/bench_simulate.py [--frames 210] [--json FILE]

Target (issue 2): 210 frames at 1920x1080 in under 60 s on one core, with
everything on (background, blur, noise, JPEG round trip, mp4 output).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import cv2  # noqa: E402
from signpose.maps.loader import bundled_map_path, load_map  # noqa: E402

from signpose.core.fileio import atomic_write  # noqa: E402
from signpose.sim.flight import FORMATS, SimSettings, simulate  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=210)
    parser.add_argument("--width", type=int, default=1920)
    parser.add_argument("--height", type=int, default=1080)
    parser.add_argument("--format", choices=FORMATS, default="mp4")
    parser.add_argument("--dirt", action="store_true")
    parser.add_argument("--occlusion", action="store_true")
    parser.add_argument(
        "--hard", action="store_true", help="every real-pylon condition on (SimSettings.hard)"
    )
    parser.add_argument("--json", help="also write the numbers to this JSON file")
    args = parser.parse_args(argv)
    cv2.setNumThreads(1)
    sign_map = load_map(bundled_map_path())
    settings = SimSettings(
        frames=args.frames,
        width=args.width,
        height=args.height,
        format=args.format,
        dirt=args.dirt,
        occlusion=args.occlusion,
    )
    if args.hard:
        settings = settings.hard()
    with tempfile.TemporaryDirectory(prefix="bench_simulate_") as tmp:
        t0, c0 = time.perf_counter(), time.process_time()
        result = simulate(sign_map, tmp, settings, progress=False)
        total, cpu = time.perf_counter() - t0, time.process_time() - c0
        size_mb = sum(f.stat().st_size for f in result.out_dir.rglob("*") if f.is_file()) / (
            1024 * 1024
        )
    print(
        f"simulate{' --hard' if args.hard else ''}: {result.n_frames} frames "
        f"{args.width}x{args.height} {args.format} "
        f"(cv2 threads {cv2.getNumThreads()}, OMP_NUM_THREADS={os.environ['OMP_NUM_THREADS']})"
    )
    print(f"total {total:.1f} s, {result.n_frames / total:.2f} frames/s, output {size_mb:.1f} MB")
    # Wall time depends on what else the machine runs; CPU time of this process does not.
    print(f"cpu {cpu:.1f} s ({result.n_frames / cpu:.2f} frames per cpu-second)")
    if args.json:
        out = {
            "frames": result.n_frames,
            "width": args.width,
            "height": args.height,
            "format": args.format,
            "dirt": args.dirt,
            "occlusion": args.occlusion,
            "hard": args.hard,
            "wall_s": round(total, 3),
            "cpu_s": round(cpu, 3),
            "frames_per_s": round(result.n_frames / total, 3),
            "frames_per_cpu_s": round(result.n_frames / cpu, 3),
            "output_mb": round(size_mb, 2),
            "cv2_threads": cv2.getNumThreads(),
        }
        with atomic_write(args.json, encoding="utf-8") as f:
            json.dump(out, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
