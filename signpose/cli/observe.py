"""``signpose observe INPUT --out observations.jsonl``: the frontend alone."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from signpose import pipeline
from signpose.cli import (
    add_cascade,
    add_quiet,
    add_search,
    check_fps_input,
    codes_arg,
    observe_settings,
)
from signpose.core.errors import OutputError
from signpose.io.camera_file import load_camera
from signpose.io.sources import open_source
from signpose.maps.loader import load_map


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "observe",
        help="detect and decode the signs of a flight into observations.jsonl",
        description="Run the frontend (detector + decoder) over a video, an image folder or "
        "an MCAP log and write one JSON line per frame. With --map and --camera the search "
        "follows the running pose estimate (tracking).",
    )
    p.add_argument("input", type=Path, help="video file, image folder or .mcap log")
    p.add_argument("--out", type=Path, required=True, help="observations .jsonl to write")
    p.add_argument("--map", type=Path, help="sign map YAML (codes to look for; tracking)")
    p.add_argument("--camera", type=Path, help="camera file (default: the log's calibration)")
    p.add_argument("--topic", help="MCAP image topic (needed when the log has several)")
    p.add_argument("--fps", type=float, help="frame rate of an image folder without frames.csv")
    p.add_argument("--codes", type=codes_arg, help="codes to look for, e.g. 0001,0101")
    add_search(p)
    add_cascade(p)
    add_quiet(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    check_fps_input(args.input, args.fps)
    sign_map = load_map(args.map) if args.map else None
    camera = load_camera(args.camera) if args.camera else None
    parent = args.out.parent if str(args.out.parent) else Path(".")
    if not parent.is_dir():
        raise OutputError(f"{parent}: folder does not exist; create it or choose another --out")
    source = open_source(args.input, topic=args.topic, fps=args.fps)
    if camera is None:
        camera = source.camera
    settings = observe_settings(args)
    # Through the module, so that a test's stand-in for pipeline.observe is seen.
    result = pipeline.observe(source, sign_map, camera, settings, args.progress, out_path=args.out)
    n = len(result.frames)
    signs = sum(len(f.signs) for f in result.frames)
    print(f"wrote {args.out}: {n} frames, {signs} sign observations")
    if result.problems:
        print(
            f"signpose observe: error: {'; '.join(result.problems)} "
            f"(the {n} readable frames are in {args.out})",
            file=sys.stderr,
        )
        return 2
    return 0
