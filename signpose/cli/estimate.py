"""``signpose estimate OBSERVATIONS --map MAP --camera CAM --out DIR``: trajectories."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from signpose.cli import add_quiet, out_folder_arg
from signpose.cli.run import (
    add_focal_sigma,
    add_map_fixed,
    add_principal_sigma,
    add_telemetry,
    focal_sigma,
    fusion_settings,
    principal_sigma,
    telemetry_request,
    trust_warnings,
)
from signpose.core.errors import InputError
from signpose.estimator.estimate import EstimatorSettings, check_inputs, estimate_trajectories
from signpose.estimator.refine import refine_flight, survey_checked
from signpose.io.camera_file import load_camera
from signpose.io.geo_out import (
    check_anchor,
    check_geo_request,
    fused_clock_and_outliers,
    fusion_summary,
    run_geo,
    write_run_geo,
)
from signpose.io.observations import read_observations
from signpose.io.results import status_line, write_outputs
from signpose.io.telemetry import check_overlap, describe, read_requested
from signpose.maps.loader import load_map


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "estimate",
        help="camera trajectory from per-frame sign observations",
        description="Estimate the camera trajectory with the paper's per-frame method "
        "(baseline), per-frame PnP and the gtsam smoother; write <method>.tum, "
        "trajectory.csv, report.json and (with the smoother) map_refined.yaml, the map "
        "refined from the flight, with map_refined.json (posterior sigmas, frames seen) "
        "into --out.",
    )
    p.add_argument("observations", type=Path, help="observations JSONL")
    p.add_argument("--map", required=True, type=Path, help="sign map YAML")
    p.add_argument("--camera", required=True, type=Path, help="camera calibration YAML")
    p.add_argument("--out", required=True, type=out_folder_arg, help="output folder")
    p.add_argument(
        "--method",
        choices=("baseline", "pnp", "smoothed", "all"),
        default=None,
        help="method to run (default: baseline and smoothed)",
    )
    p.add_argument("--solver", choices=("batch", "isam2"), default="batch", help="smoother solver")
    p.add_argument("--huber", type=float, default=None, help="Huber threshold [sigmas]")
    p.add_argument(
        "--motion",
        choices=("random-walk", "constant-velocity"),
        default=None,
        help="motion prior of the smoother",
    )
    p.add_argument("--max-speed", type=float, default=None, help="baseline speed gate [m/s]")
    p.add_argument("--no-sigmas", action="store_true", help="skip marginal covariances")
    add_map_fixed(p)
    p.add_argument(
        "--fixed-motion-prior",
        action="store_true",
        help="keep the motion prior's default strength (default: chosen from the flight)",
    )
    add_focal_sigma(p)
    add_principal_sigma(p)
    add_telemetry(p, log_input=False)
    add_quiet(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    frames = read_observations(args.observations)
    sign_map = load_map(args.map)
    camera = load_camera(args.camera)
    check_inputs(frames, sign_map, camera, str(args.observations))
    request = telemetry_request(args, log_input=False)
    fusion = fusion_settings(args, request)  # the geometry options checked before any work
    check_geo_request(sign_map, args.geo)
    telemetry, notes = None, []
    if request is not None:
        stamps = np.array([f.stamp_ns for f in frames], float) * 1e-9
        telemetry = read_requested(request, args.observations, float(stamps[0]))
        check_anchor(sign_map, telemetry)
        check_overlap(telemetry, stamps, request.clock_offset_s)
        notes.append(describe(telemetry))
    settings = EstimatorSettings()
    if args.method == "all":
        methods = ("baseline", "pnp", "smoothed")
    elif args.method is None:
        methods = ("baseline", "smoothed")
    else:
        methods = (args.method,)
    smoother = settings.smoother
    if args.huber is not None:
        if not args.huber > 0:
            raise InputError("--huber must be > 0")
        smoother = replace(smoother, huber_k=args.huber)
    if args.motion is not None:
        smoother = replace(smoother, motion=args.motion)
    if args.no_sigmas:
        smoother = replace(smoother, compute_sigmas=False)
    if args.map_fixed:
        smoother = replace(smoother, landmarks="fixed")
    per_frame = settings.per_frame
    if args.max_speed is not None:
        per_frame = replace(per_frame, max_speed_mps=args.max_speed)
    settings = replace(
        settings,
        methods=methods,
        solver=args.solver,
        smoother=smoother,
        per_frame=per_frame,
        focal_sigma_rel=focal_sigma(args),
        principal_sigma_px=principal_sigma(args),
    )
    if args.fixed_motion_prior:
        settings = replace(settings, tune_motion=False)
    result = estimate_trajectories(
        frames,
        sign_map,
        camera,
        settings,
        args.progress,
        telemetry=telemetry,
        fusion=fusion if request else None,
    )
    refined = refine_flight(frames, sign_map, camera, result)
    result = survey_checked(result, refined, frames)  # signs far from the map: suspect
    written = write_outputs(args.out, result, refined)
    written += _geo_files(args, sign_map, result, telemetry, request, notes)
    for line in notes:
        print(line)
    for line in result.warnings:  # e.g. a camera file that does not fit the video
        print(f"signpose estimate: warning: {args.camera}: {line}", file=sys.stderr)
    for line in trust_warnings(written):
        print(f"signpose estimate: {line}", file=sys.stderr)
    if args.quiet:  # the result and errors only
        print(status_line(result))
        print(f"wrote {len(written)} files into {args.out}")
        return 0
    for name, m in result.methods.items():
        print(f"{name}: {int(m.valid.sum())}/{len(m.valid)} frames posed")
    print(status_line(result))
    print(f"wrote {', '.join(str(p) for p in written)}")
    return 0


def _geo_files(args, sign_map, result, telemetry, request, notes: list[str]) -> list:
    """The WGS84 files (map with an origin); the note why not when there is telemetry."""
    gnss = telemetry.gnss if telemetry is not None else None
    offset, outlier = 0.0, None
    if gnss is not None:
        offset, outlier = fused_clock_and_outliers(result.fusion, gnss, request.clock_offset_s)
    if (f := result.fusion) is not None:  # a refused fusion: its note only
        notes.extend(f.notes if f.refused else (fusion_summary(f), *f.notes))
    geo = run_geo(sign_map, result.methods, gnss, offset, outlier, required=args.geo)
    if geo.note and telemetry is not None:
        notes.append(f"note: {geo.note}")
    return write_run_geo(args.out, geo)
