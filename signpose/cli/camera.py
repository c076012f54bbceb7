"""``signpose camera FILE``: what a calibration file says, and conversion between formats."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from signpose.core.errors import InputError
from signpose.io.camera_file import (
    camera_summary,
    read_camera_file,
    write_camera_info,
    write_kalibr,
    write_opencv,
)

WRITERS = {"camera_info": write_camera_info, "opencv": write_opencv, "kalibr": write_kalibr}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "camera",
        help="check a camera calibration file, or convert it",
        description="Read FILE (ROS camera_info / ost.yaml, OpenCV FileStorage YAML or XML, "
        "Kalibr camchain) and print what signpose reads as one JSON object: model, width, "
        "height, fx, fy, cx, cy, skew, distortion, source_format. With --to and --out, "
        "write it in another format.",
    )
    p.add_argument("file", type=Path, help="camera calibration file")
    p.add_argument("--to", choices=sorted(WRITERS), help="format to convert to (needs --out)")
    p.add_argument("--out", type=Path, help="file to write with --to")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if (args.to is None) != (args.out is None):
        raise InputError("--to and --out go together: give both to convert, neither to check")
    if args.out is not None and args.out.is_dir():
        raise InputError(f"{args.out}: is a folder; --out names the file to write")
    found = read_camera_file(args.file)
    if args.to is not None:
        WRITERS[args.to](args.out, found.camera)
    print(json.dumps(camera_summary(found.camera, found.source_format)))
    return 0
