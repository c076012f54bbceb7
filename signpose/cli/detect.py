"""``signpose detect IMAGE... [--codes ...] [--mode fast|paper]``: one JSON line per image."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2

from signpose.cli import codes_arg
from signpose.frontend.detector import SignDetector


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "detect",
        help="detect and decode the signs in images (one JSON line per image)",
        description="Run the Haar cascade detector (paper 2.2) and the decoder on each image and "
        'print {"image": path, "signs": [...]} per line. Unreadable images give a line '
        'with "error"; the exit code is 2 only when no image could be read.',
    )
    p.add_argument("images", nargs="+", type=Path, metavar="IMAGE", help="image files")
    p.add_argument(
        "--codes", type=codes_arg, default=None, help="codes that may appear, e.g. 0001,0010"
    )
    p.add_argument("--mode", choices=("fast", "paper"), default="fast", help="detection mode")
    p.add_argument("--cascade", type=Path, default=None, help="cascade XML (default: bundled)")
    p.set_defaults(func=run)


def _r(x: float) -> float:
    return round(float(x), 3)


def run(args: argparse.Namespace) -> int:
    detector = SignDetector(args.cascade)
    n_read = 0
    for path in args.images:
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
        if gray is None:
            reason = "file not found" if not path.exists() else "not a readable image"
            print(json.dumps({"image": str(path), "error": reason}), flush=True)
            continue
        n_read += 1
        result = detector.detect(gray, args.codes, mode=args.mode)
        signs = [
            {
                "code": d.code,
                "center_px": [_r(d.center_px[0]), _r(d.center_px[1])],
                "bbox_px": [_r(v) for v in d.bbox_px],
                "keypoints_px": {k: [_r(u), _r(v)] for k, (u, v) in d.keypoints_px.items()},
                "score": round(float(d.score), 4),
            }
            for d in sorted(result.detections, key=lambda d: d.code)
        ]
        print(json.dumps({"image": str(path), "signs": signs}), flush=True)
    if n_read == 0:
        print("signpose detect: error: none of the images could be read", file=sys.stderr)
        return 2
    return 0
