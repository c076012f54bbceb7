"""``signpose run INPUT --map MAP --out DIR``: observe + estimate + plots + MCAP (+ compare)."""

from __future__ import annotations

import argparse
import math
import sys
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import TextIO

from signpose import pipeline
from signpose.cli import (
    add_cascade,
    add_gt_offset,
    add_quiet,
    add_search,
    check_fps_input,
    codes_arg,
    observe_settings,
    out_folder_arg,
)
from signpose.core.errors import InputError
from signpose.estimator.estimate import EstimatorSettings, settings_from_options
from signpose.estimator.fusion import FusionSettings, body_T_cam_from_mounting
from signpose.estimator.refine import SUSPECT_MOVED_SIGMAS
from signpose.io.camera_file import load_camera
from signpose.io.clock import parse_start_time
from signpose.io.results import read_report
from signpose.io.telemetry import TelemetryRequest
from signpose.maps.loader import load_map
from signpose.pipeline import CONTRADICTIONS, STAGES, RefusalReason, RunResult, RunSettings

# --principal-sigma's upper bound [px]: a calibration that unsure of its principal point
# (a tenth of a 1280 px image) is no calibration; a larger value is a typo.
MAX_PRINCIPAL_SIGMA_PX = 128.0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="a flight's trajectories, plots and MCAP from its video/images/log",
        description="Detect and decode the signs (tracking with the running estimate), "
        "estimate the trajectories (the paper's per-frame method and the smoother), and write "
        "observations.jsonl, the estimator's files, PNG plots, result.mcap and report.json "
        "into DIR. With --gt also compare with the ground truth and print the table. "
        "DIR/run.json names the run DIR holds: 'complete' with its files, written last; "
        "'running' during a rerun over an earlier run's files and after one that was stopped "
        "(DIR then mixes two runs); a complete run removes the earlier files it did not rewrite.",
    )
    p.add_argument("input", type=Path, help="video file, image folder or .mcap log")
    p.add_argument("--map", type=Path, required=True, help="sign map YAML")
    p.add_argument("--camera", type=Path, help="camera file (default: the log's calibration)")
    p.add_argument("--out", type=out_folder_arg, required=True, help="output folder")
    p.add_argument("--gt", type=Path, help="ground truth TUM: compare and print the table")
    add_gt_offset(p)
    p.add_argument("--with-images", action="store_true", help="put the images into result.mcap")
    p.add_argument("--topic", help="MCAP image topic (needed when the log has several)")
    p.add_argument("--fps", type=float, help="frame rate of an image folder without frames.csv")
    p.add_argument("--codes", type=codes_arg, help="codes to look for (default: the map's)")
    add_solver(p)
    add_search(p)
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument(
        "--ros2-bag",
        action="store_true",
        help="also write DIR/result_bag, a rosbag2 folder (MCAP) that ROS 2 tools open",
    )
    p.add_argument(
        "--start-time",
        help="time of the first frame of a video or --fps folder (ISO 8601 with a zone, or "
        "epoch seconds; default: the video's creation_time, else 0)",
    )
    add_estimator_options(p)
    add_telemetry(p, log_input=True)
    add_cascade(p)
    add_quiet(p)
    p.set_defaults(func=run)


def add_solver(p: argparse.ArgumentParser) -> None:
    """--solver: the smoother's solver."""
    p.add_argument("--solver", choices=("batch", "isam2"), default="batch", help="smoother solver")


def add_estimator_options(p: argparse.ArgumentParser) -> None:
    """--no-sigmas, --map-fixed, --focal-sigma and --principal-sigma, as ``signpose run``
    has them (``estimator_settings`` reads them, with --solver)."""
    p.add_argument(
        "--no-sigmas",
        action="store_true",
        help="skip the smoother's marginal sigmas (faster on long flights; no sigma bands)",
    )
    add_map_fixed(p)
    add_focal_sigma(p)
    add_principal_sigma(p)


def estimator_settings(args: argparse.Namespace) -> EstimatorSettings:
    """The estimator's settings from --solver and ``add_estimator_options``' options."""
    return settings_from_options(
        args.solver,
        args.map_fixed,
        not args.no_sigmas,
        focal_sigma(args),
        principal_sigma(args),
    )


def add_map_fixed(p: argparse.ArgumentParser) -> None:
    """--map-fixed: the survey taken as exact."""
    p.add_argument(
        "--map-fixed",
        action="store_true",
        help="treat the survey as exact (default: each keypoint with its sign's sigma_m)",
    )


def add_principal_sigma(p: argparse.ArgumentParser) -> None:
    """--principal-sigma: the calibration's principal point uncertainty, into the pose sigmas."""
    p.add_argument(
        "--principal-sigma",
        type=float,
        default=0.0,
        metavar="PX",
        help="the camera calibration's principal point sigma on each image axis [px], added "
        "to the position sigmas: a principal point c px off shifts the camera across the view "
        "by up to c / f times the range and the video cannot show it (default 0: exact)",
    )


def principal_sigma(args: argparse.Namespace) -> float:
    """--principal-sigma checked (InputError outside [0, MAX_PRINCIPAL_SIGMA_PX])."""
    px = args.principal_sigma
    if not (math.isfinite(px) and 0.0 <= px <= MAX_PRINCIPAL_SIGMA_PX):
        raise InputError(
            f"--principal-sigma {px}: give the principal point's sigma in pixels, in "
            f"[0, {MAX_PRINCIPAL_SIGMA_PX:g}], e.g. 5"
        )
    return px


def add_focal_sigma(p: argparse.ArgumentParser) -> None:
    """--focal-sigma: the calibration's focal length uncertainty, into the pose sigmas."""
    p.add_argument(
        "--focal-sigma",
        type=float,
        default=0.0,
        metavar="REL",
        help="the camera calibration's focal length sigma as a fraction (0.005: 0.5 %%), added "
        "to the position sigmas: from one pylon face a focal length error moves every pose by "
        "that fraction of its range and the video cannot show it (default 0: exact)",
    )


def focal_sigma(args: argparse.Namespace) -> float:
    """--focal-sigma checked (InputError outside [0, 0.5))."""
    rel = args.focal_sigma
    if not (math.isfinite(rel) and 0.0 <= rel < 0.5):
        raise InputError(
            f"--focal-sigma {rel}: give the focal length's sigma as a fraction in [0, 0.5), "
            "e.g. 0.005 for 0.5 %"
        )
    return rel


def add_telemetry(p: argparse.ArgumentParser, log_input: bool) -> None:
    """--telemetry, --telemetry-topic, --telemetry-offset and --geo (issue 17)."""
    p.add_argument(
        "--telemetry",
        type=Path,
        metavar="FILE",
        help="the drone's own GNSS/IMU log, fused with the signs (method 'fused'): a DJI .SRT "
        "sidecar, a PX4 .ulg, a telemetry CSV (docs/telemetry.md), or an MCAP / rosbag2 log "
        "with sensor_msgs/NavSatFix and Imu topics",
    )
    same_log = " (without --telemetry: from the input log itself)" if log_input else ""
    p.add_argument(
        "--telemetry-topic",
        metavar="T",
        help=f"NavSatFix / Imu topic(s) of an MCAP / rosbag2 telemetry log, comma-separated"
        f"{same_log}; needed when the log has several",
    )
    p.add_argument(
        "--telemetry-offset",
        type=float,
        metavar="S",
        help="telemetry time minus video time [s] (default: estimated from the flight)",
    )
    p.add_argument(
        "--antenna-offset",
        metavar="X,Y,Z",
        help="the GNSS antenna in the camera frame [m] (x right, y down, z along the optical "
        "axis; default 0,0,0: at the camera)",
    )
    p.add_argument(
        "--imu-to-camera",
        metavar="R,P,Y",
        help="the camera's mounting in the IMU body frame (FLU), roll,pitch,yaw [deg] about the "
        "body's x, y, z from looking forward (pitch +45: 45 deg down; default 0,0,0)",
    )
    p.add_argument(
        "--geo",
        action="store_true",
        help="require the WGS84 outputs (trajectory_wgs84.csv, trajectory.geojson, "
        "trajectory.kml, LocationFix in result.mcap): exit 2 when the map has no origin "
        "(default: written when the map has one, skipped with a note otherwise)",
    )


def telemetry_request(args: argparse.Namespace, log_input: bool) -> TelemetryRequest | None:
    """The telemetry the options ask for, or None; InputError for options that do not fit."""
    offset = args.telemetry_offset
    if offset is not None and not math.isfinite(offset):
        raise InputError(f"--telemetry-offset {offset}: give a finite number of seconds")
    if args.telemetry is None and not (log_input and args.telemetry_topic):
        if offset is not None:
            raise InputError("--telemetry-offset needs --telemetry FILE")
        if args.telemetry_topic:
            raise InputError("--telemetry-topic needs --telemetry FILE")
        return None
    return TelemetryRequest(args.telemetry, args.telemetry_topic, offset)


def _three(args: argparse.Namespace, name: str, what: str) -> tuple[float, float, float] | None:
    text = getattr(args, name.lstrip("-").replace("-", "_"))
    if text is None:
        return None
    try:
        v = tuple(float(x) for x in text.split(","))
    except ValueError:
        v = ()
    if len(v) != 3 or not all(math.isfinite(x) for x in v):
        raise InputError(f"{name} {text}: give {what}, three numbers separated by commas")
    return v


def fusion_settings(args: argparse.Namespace, request: TelemetryRequest | None) -> FusionSettings:
    """The fusion's geometry and clock from the options (InputError for values that do not fit)."""
    arm = _three(args, "--antenna-offset", "X,Y,Z in metres")
    mount = _three(args, "--imu-to-camera", "roll,pitch,yaw in degrees")
    if request is None and (arm is not None or mount is not None):
        name = "--antenna-offset" if arm is not None else "--imu-to-camera"
        raise InputError(f"{name} needs --telemetry FILE")
    s = FusionSettings(clock_offset_s=None if request is None else request.clock_offset_s)
    if arm is not None:
        s = replace(s, cam_t_antenna_m=arm)
    if mount is not None:
        s = replace(s, body_T_cam=body_T_cam_from_mounting(*mount))
    return s


def print_result(result: RunResult, out: TextIO | None = None, quiet: bool = False) -> None:
    """The user's summary of a run: table, coverage, timing, files (to stdout by default).

    ``quiet``: the result only: no timing, one line for the files.
    """
    out = out if out is not None else sys.stdout
    if result.comparison_table:
        print(result.comparison_table, file=out)
    for line in result.notes:  # telemetry read, clock offset found, geodetic outputs skipped
        print(line, file=out)
    cov = ", ".join(f"{k} {100 * v:.1f}%" for k, v in result.coverage.items())
    print(f"{result.n_frames} frames; poses for {cov}", file=out)
    if result.status:
        shares = "; ".join(
            f"{k} " + " ".join(f"{t} {100 * v:.1f}%" for t, v in st.items())
            for k, st in result.status.items()
        )
        print(f"pose status: {shares}", file=out)
    if result.position_rmse_m:
        err = ", ".join(f"{k} {v:.3f} m" for k, v in result.position_rmse_m.items())
        print(f"position RMSE vs ground truth: {err}", file=out)
    contradicting = {k: n for k, n in result.refused.items() if k in CONTRADICTIONS and n}
    if contradicting:
        why = ", ".join(f"{k} {n}" for k, n in contradicting.items())
        print(
            f"refused {sum(contradicting.values())} decoded readings that contradict the frame "
            f"or the track ({why}); listed in report.json",
            file=out,
        )
    if n_unknown := result.refused.get(RefusalReason.CODE_NOT_IN_MAP.value, 0):
        print(
            f"left out {n_unknown} readings of codes the map does not have; listed in report.json",
            file=out,
        )
    if quiet:
        print(f"wrote {len(result.files)} files into {result.out_dir}", file=out)
        return
    t = result.timing_s
    split = ", ".join(f"{k} {1000 * t.get(k, 0.0) / max(result.n_frames, 1):.1f}" for k in STAGES)
    print(f"{result.fps:.1f} frames/s; ms per frame: {split}", file=out)
    print(f"wrote {len(result.files)} files into {result.out_dir}:", file=out)
    for path in result.files:
        print(f"  {path}", file=out)


def trust_warnings(files: tuple[Path, ...] | list[Path]) -> list[str]:
    """What a run's own report.json and map_refined.json say the user must check, one line each.

    Frames where signs were in view but a method rejected every observation
    and bridged them with its motion prior (more ``bridged`` frames than frames
    without signs: one sign surveyed 0.5 m off made the smoother do that on 45
    of 60 frames, exit 0, nothing said), readings of one code where the map has
    another (``misdecoded``: codes swapped in the survey), and signs the flight
    moved by more than the refinement's threshold against the survey
    (``moved``). Only the files this run wrote (``files``) are read; an older
    run's are not. Warnings, not errors: the outputs stand and the exit code is 0.
    """
    by_name = {Path(p).name: Path(p) for p in files}
    lines = []
    if "report.json" in by_name:
        report = read_report(by_name["report.json"])
        without_signs = report.get("frames", 0) - report.get("frames_with_signs", 0)
        for method, cov in report.get("coverage", {}).items():
            seen = cov.get("bridged", 0) - without_signs
            if seen > 0:
                lines.append(
                    f"warning: {method}: at least {seen} frames with signs in view had every "
                    "observation rejected and are only bridged by the motion prior; the map and "
                    "the images disagree there: check the survey (report.json 'outliers')"
                )
        pairs = Counter(
            f"{m.get('code')} where the map has {m.get('likely_code')}"
            for m in report.get("outliers", {}).get("misdecoded", [])
        )
        if pairs:
            lines.append(
                f"warning: {sum(pairs.values())} readings sit where the map has another code ("
                + ", ".join(f"{k}: {n}" for k, n in pairs.most_common(3))
                + "): two codes swapped in the survey, or misread signs; set aside as outliers"
            )
    if "map_refined.json" in by_name:
        refined = read_report(by_name["map_refined.json"])
        # The signs beyond the survey check's threshold are named by its own warning.
        named = {
            s.get("code")
            for s in refined.get("signs", [])
            if s.get("moved_sigmas", 0.0) > SUSPECT_MOVED_SIGMAS
        }
        if moved := [c for c in refined.get("moved", []) if c not in named]:
            lines.append(
                f"warning: the flight puts sign(s) {', '.join(moved)} more than "
                f"{refined.get('moved_sigmas', 3):g} survey sigmas from the map: check the survey "
                "(map_refined.json)"
            )
    return lines


def run(args: argparse.Namespace) -> int:
    check_fps_input(args.input, args.fps)
    sign_map = load_map(args.map)
    camera = load_camera(args.camera) if args.camera else None
    settings = RunSettings(
        observe=observe_settings(args),
        estimator=estimator_settings(args),
        with_images=args.with_images,
        plots=not args.no_plots,
        ros2_bag=args.ros2_bag,
        start_ns=parse_start_time(args.start_time) if args.start_time is not None else None,
        gt_offset_s=args.gt_offset,
        telemetry=(request := telemetry_request(args, log_input=True)),
        geo=args.geo,
        fusion=fusion_settings(args, request),
    )
    # Through the module, so that a test's stand-in for pipeline.run is seen.
    result = pipeline.run(
        args.input,
        sign_map,
        args.out,
        camera=camera,
        gt_path=args.gt,
        topic=args.topic,
        fps=args.fps,
        settings=settings,
        progress=args.progress,
    )
    print_result(result, quiet=args.quiet)
    for line in trust_warnings(result.files):
        print(f"signpose run: {line}", file=sys.stderr)
    if result.problems:
        print(
            f"signpose run: error: {'; '.join(result.problems)} "
            f"(the {result.n_frames} readable frames were processed; outputs in {result.out_dir})",
            file=sys.stderr,
        )
        return 2
    return 0
