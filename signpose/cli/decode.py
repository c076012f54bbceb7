"""``signpose decode IMAGE... [--codes ...]``: decode one sign crop per image.

Prints one JSON line per image, in the order given::

    {"image": "a.png", "code": "0101", "reason": "ok",
     "keypoints_px": {"center": [u, v], ...}, "sigma_px": 0.12}

An unreadable image gets a line with ``"reason": "unreadable"`` and the batch
goes on; the exit code is 2 only when no image could be read.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import cv2

from signpose.cli import EXIT_INPUT, EXIT_OK, codes_arg
from signpose.frontend.decoder import decode_roi


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "decode",
        help="decode the sign in each image crop (paper §1.2)",
        description="Decode the one sign filling each image (a crop around a sign, as a "
        "detector's region of interest) and print one JSON line per image.",
    )
    p.add_argument("images", nargs="+", metavar="IMAGE", help="image files (PNG, JPEG, ...)")
    p.add_argument(
        "--codes",
        type=codes_arg,
        default=None,
        help="comma-separated codes the map holds (e.g. 0001,0010); others are dropped",
    )
    p.set_defaults(func=run)


def _num(x: float) -> float | None:
    return round(float(x), 4) if math.isfinite(x) else None


def run(args: argparse.Namespace) -> int:
    n_read = 0
    for path in args.images:
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if Path(path).is_file() else None
        if gray is None or gray.size == 0:
            line = {
                "image": str(path),
                "code": None,
                "reason": "unreadable",
                "keypoints_px": {},
                "sigma_px": None,
            }
        else:
            n_read += 1
            res = decode_roi(gray, args.codes)
            line = {
                "image": str(path),
                "code": res.code,
                "reason": res.reason,
                "keypoints_px": {k: [_num(u), _num(v)] for k, (u, v) in res.keypoints_px.items()},
                "sigma_px": _num(res.sigma_px) if res.code is not None else None,
            }
        print(json.dumps(line), flush=True)
    if n_read == 0:
        print("signpose decode: error: no image could be read", file=sys.stderr)
        return EXIT_INPUT
    return EXIT_OK
