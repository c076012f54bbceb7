"""``signpose sign CODE --out FILE``: a printable sign as SVG or PNG."""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2

from signpose.core.errors import InputError, OutputError
from signpose.core.fileio import atomic_path, atomic_write
from signpose.frontend.sign import render_sign_png, render_sign_svg, validate_code


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "sign",
        help="write a printable sign (SVG at true size or PNG)",
        description="Write the face of sign CODE, directional rectangle up, as SVG or PNG "
        "(chosen by the --out extension).",
    )
    p.add_argument("code", help="four bits, e.g. 0101")
    p.add_argument("--out", required=True, type=Path, help="output .svg or .png")
    p.add_argument("--diameter-mm", type=float, default=800.0, help="SVG disc diameter [mm]")
    p.add_argument("--px", type=int, default=512, help="PNG side [px]")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    code = validate_code(args.code)
    suffix = args.out.suffix.lower()
    if suffix not in (".svg", ".png"):
        raise InputError(f"{args.out}: use a .svg or .png file name")
    if not args.out.parent.exists() and str(args.out.parent) not in ("", "."):
        raise OutputError(f"{args.out.parent}: folder does not exist")
    if suffix == ".svg":
        if not args.diameter_mm > 0:
            raise InputError("--diameter-mm must be > 0")
        with atomic_write(args.out) as f:
            f.write(render_sign_svg(code, args.diameter_mm))
    else:
        if not 16 <= args.px <= 16384:
            raise InputError("--px must be between 16 and 16384")
        img = render_sign_png(code, args.px)
        with atomic_path(args.out) as tmp:
            if not cv2.imwrite(str(tmp), img):
                raise OutputError(f"{args.out}: could not write PNG")
    print(f"wrote {args.out}")
    return 0
