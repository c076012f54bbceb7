"""signpose refine-map: the signs' centres solved jointly from several flights of one site."""

from __future__ import annotations

import argparse
from pathlib import Path

from signpose.cli import add_quiet
from signpose.estimator.estimate import check_inputs
from signpose.estimator.refine import MOVED_SIGMAS, check_flights_share_signs, refine_map
from signpose.io.camera_file import load_camera
from signpose.io.observations import read_observations
from signpose.io.results import write_refined_map
from signpose.maps.loader import load_map


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "refine-map",
        help="refine the sign map from several flights of one site",
        description="Solve several flights of one site jointly (one trajectory per flight, "
        "the signs shared as rigid bodies with the survey priors) and write the refined map "
        "(--out, in the map schema) and the same name with .json (site.yaml -> site.json) with "
        "each sign's posterior sigma, frames "
        f"seen and how far it moved; signs moved by more than {MOVED_SIGMAS:g} survey sigmas "
        "are named.",
    )
    p.add_argument("observations", type=Path, nargs="+", help="observations JSONL, one per flight")
    p.add_argument("--map", required=True, type=Path, help="sign map YAML (the survey)")
    p.add_argument("--camera", required=True, type=Path, help="camera calibration YAML")
    p.add_argument("--out", required=True, type=Path, help="refined map YAML to write")
    add_quiet(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    sign_map = load_map(args.map)
    camera = load_camera(args.camera)
    flights = [read_observations(path) for path in args.observations]
    names = [str(path) for path in args.observations]
    check_flights_share_signs(flights, names)
    for frames, name in zip(flights, names, strict=True):
        check_inputs(frames, sign_map, camera, name)
    refined = refine_map(flights, sign_map, camera)
    _, report = write_refined_map(args.out, refined, str(args.map), names)
    if not args.quiet:
        for s in refined.signs:
            print(
                f"{s.code}: moved {1e3 * s.moved_m:.1f} mm ({s.moved_sigmas:.1f} sigma), "
                f"posterior sigma {1e3 * s.sigma_m:.1f} mm, seen in {s.frames_seen} frames"
            )
        if refined.moved:
            print(
                f"moved by more than {MOVED_SIGMAS:g} sigma (re-hung?): {', '.join(refined.moved)}"
            )
        print(f"wrote {args.out}, {report}")
    return 0
