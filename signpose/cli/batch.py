"""``signpose batch INPUT... --map MAP --out DIR``: many flights, one summary.csv."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from signpose.batch import SUMMARY_NAME, FlightOutcome, FlightStatus, run_batch
from signpose.cli import (
    EXIT_INPUT,
    EXIT_INTERNAL,
    EXIT_OK,
    add_cascade,
    add_quiet,
    out_folder_arg,
)
from signpose.cli.run import add_estimator_options, add_solver, focal_sigma, principal_sigma
from signpose.core.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "batch",
        help="run many flights in parallel (locally or on a Dask cluster)",
        description="Run every flight like `signpose run`, each into DIR/<flight>/, and write "
        "DIR/summary.csv. A failed flight is recorded and the rest go on; a rerun skips a "
        "finished flight only when its input, map, camera, ground truth, --topic/--fps, the "
        "estimator's options and the signpose version are unchanged (--force redoes all), and "
        "keeps the summary rows of flights not passed this time. The camera defaults to "
        "camera.yaml beside each input (else the log's calibration) and groundtruth.tum beside "
        "an input is compared with. "
        "Ctrl-C or SIGTERM stops the batch at once (exit 130 or 143): summary.csv lists the "
        "running flights as interrupted and the queued ones as not_started, and a rerun runs them.",
    )
    p.add_argument("inputs", type=Path, nargs="+", metavar="INPUT", help="flights")
    p.add_argument("--map", type=Path, required=True, help="sign map YAML")
    p.add_argument("--out", type=out_folder_arg, required=True, help="output folder")
    p.add_argument("--camera", type=Path, help="camera file for every flight")
    p.add_argument("--topic", help="MCAP image topic")
    p.add_argument("--fps", type=float, help="frame rate of image folders without frames.csv")
    p.add_argument("--with-images", action="store_true", help="put the images into result.mcap")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--jobs", type=int, default=1, help="parallel flights (default 1)")
    p.add_argument(
        "--scheduler",
        metavar="tcp://HOST:PORT",
        help="run on this Dask distributed scheduler (pip install signpose[dask])",
    )
    p.add_argument("--force", action="store_true", help="run every flight again, finished or not")
    p.add_argument(
        "--root",
        type=Path,
        help="name each flight by its input's path below ROOT (ROOT/f1/video.mp4 -> f1_video), "
        "the same whichever flights are passed; default: the input's name",
    )
    p.add_argument(
        "--telemetry",
        metavar="NAME",
        help="fuse each flight's GNSS/IMU from the file NAME beside its input; {stem} is the "
        "input's name without its suffix (DJI: '{stem}.SRT'; simulated: telemetry.csv); "
        "a flight without it fails (docs/telemetry.md)",
    )
    p.add_argument(
        "--telemetry-offset",
        type=float,
        metavar="S",
        help="telemetry time minus video time [s] for every flight (default: estimated)",
    )
    add_solver(p)
    add_estimator_options(p)
    add_cascade(p)
    add_quiet(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.jobs < 1:
        raise InputError(f"--jobs must be >= 1, got {args.jobs}")
    outcomes = run_batch(
        args.inputs,
        args.map,
        args.out,
        camera_path=args.camera,
        topic=args.topic,
        fps=args.fps,
        with_images=args.with_images,
        plots=not args.no_plots,
        jobs=args.jobs,
        scheduler=args.scheduler,
        progress=args.progress,
        force=args.force,
        root=args.root,
        cascade_path=args.cascade,
        telemetry=args.telemetry,
        telemetry_offset_s=args.telemetry_offset,
        solver=args.solver,
        map_fixed=args.map_fixed,
        sigmas=not args.no_sigmas,
        focal_sigma_rel=focal_sigma(args),
        principal_sigma_px=principal_sigma(args),
    )
    failed = [o for o in outcomes if o.status is FlightStatus.FAILED]
    skipped = sum(o.skipped for o in outcomes)
    print(
        f"{len(outcomes)} flights: {len(outcomes) - len(failed)} done "
        f"({skipped} from an earlier run), {len(failed)} failed; "
        f"summary in {Path(args.out) / SUMMARY_NAME}"
    )
    if failed:
        names = ", ".join(f"{o.flight} ({o.message})" for o in failed)
        print(f"signpose batch: error: failed flights: {names}", file=sys.stderr)
    partial = [o for o in outcomes if o.status is FlightStatus.PARTIAL]
    if partial:
        names = ", ".join(f"{o.flight} ({o.message})" for o in partial)
        print(f"signpose batch: error: flights read only in part: {names}", file=sys.stderr)
    return exit_code(outcomes)


def exit_code(outcomes: list[FlightOutcome]) -> int:
    """The worst flight decides: 1 if one failed on a bug, else 2 if one failed on bad input or
    was read only in part (as ``signpose run`` exits for it), else 0."""
    if any(o.status is FlightStatus.FAILED and o.internal for o in outcomes):
        return EXIT_INTERNAL
    if any(o.status is not FlightStatus.OK for o in outcomes):
        return EXIT_INPUT
    return EXIT_OK
