"""``signpose demo``: simulate the bundled pylon flight, run both methods, compare, plot."""

from __future__ import annotations

import argparse
from pathlib import Path

from signpose import pipeline
from signpose.cli import add_cascade, add_quiet, out_folder_arg
from signpose.cli.run import print_result


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="simulate the bundled pylon flight and run the whole pipeline on it",
        description="Simulate a flight in front of the bundled demo pylon, run the paper's "
        "per-frame method and the smoother on it, compare both with the ground truth and "
        "write plots and result.mcap (open it in Foxglove) into --out.",
    )
    p.add_argument("--out", type=out_folder_arg, default=Path("demo-out"), help="output folder")
    p.add_argument("--frames", type=int, default=210, help="frames to simulate (default 210)")
    p.add_argument("--width", type=int, default=1920, help="image width [px]")
    p.add_argument("--height", type=int, default=1080, help="image height [px]")
    p.add_argument("--with-images", action="store_true", help="put the images into result.mcap")
    add_cascade(p)
    add_quiet(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    result = pipeline.run_demo(
        args.out,
        frames=args.frames,
        width=args.width,
        height=args.height,
        with_images=args.with_images,
        progress=args.progress,
        cascade_path=str(args.cascade or ""),
    )
    print_result(result.run, quiet=args.quiet)
    print(f"simulated flight in {result.flight_dir}; results in {result.run.out_dir}")
    print(f"open {result.run.out_dir / 'result.mcap'} in Foxglove; plots: *.png there")
    return 0
