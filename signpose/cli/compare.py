"""``signpose compare DIR --gt groundtruth.tum``: metrics of every method in an estimate folder."""

from __future__ import annotations

import argparse
from pathlib import Path

from signpose.cli import add_gt_offset
from signpose.io.results import compare_dir, metrics_table


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "compare",
        help="trajectory errors of an estimate folder against ground truth",
        description="Print per-axis mean absolute error, ATE (raw and SE(3)-aligned), RPE per "
        "metre and coverage for every <method>.tum in DIR; store them in DIR/report.json.",
    )
    p.add_argument("dir", type=Path, help="output folder of 'signpose estimate'")
    p.add_argument("--gt", required=True, type=Path, help="ground-truth TUM file")
    add_gt_offset(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    compare_dir(args.dir, args.gt, args.gt_offset)
    print(metrics_table(args.dir))
    return 0
