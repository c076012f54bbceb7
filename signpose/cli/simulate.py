"""``signpose simulate --map MAP --out DIR``: render a flight with ground truth."""

from __future__ import annotations

import argparse
from pathlib import Path

from signpose.cli import add_quiet
from signpose.maps.loader import bundled_map_path, load_map
from signpose.sim.flight import FORMATS, SimSettings, simulate
from signpose.sim.trajectories import TRAJECTORIES


def register(sub: argparse._SubParsersAction) -> None:
    d = SimSettings()
    p = sub.add_parser(
        "simulate",
        help="render a simulated flight (frames + ground truth)",
        description="Render a UAV flight in front of the signs of MAP: frames (video.mp4 or "
        "frames/NNNNNN.png), camera.yaml, groundtruth.tum, boxes.jsonl and map.yaml in DIR. "
        "Same seed, same outputs.",
    )
    p.add_argument(
        "--map", type=Path, default=None, help="sign map YAML (default: the bundled demo pylon)"
    )
    p.add_argument("--out", type=Path, required=True, help="output folder")
    p.add_argument("--frames", type=int, default=d.frames, help=f"frames (default {d.frames})")
    p.add_argument("--fps", type=float, default=d.fps, help=f"frame rate (default {d.fps:g})")
    p.add_argument(
        "--trajectory",
        choices=TRAJECTORIES,
        default=d.trajectory,
        help=f"flight (default {d.trajectory})",
    )
    p.add_argument("--seed", type=int, default=d.seed, help="random seed (default 0)")
    p.add_argument("--format", choices=FORMATS, default=d.format, help="frame output format")
    p.add_argument(
        "--distance", type=float, default=d.distance_m, help="distance from the signs [m]"
    )
    p.add_argument("--width", type=int, default=d.width, help="image width [px]")
    p.add_argument("--height", type=int, default=d.height, help="image height [px]")
    p.add_argument("--dirt", action="store_true", help="stains on some sign faces")
    p.add_argument("--occlusion", action="store_true", help="bars in front of some sign faces")
    p.add_argument("--no-blur", action="store_true", help="no motion blur")
    p.add_argument("--no-noise", action="store_true", help="no sensor noise, no JPEG round trip")
    add_quiet(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    map_path = args.map if args.map is not None else bundled_map_path()
    sign_map = load_map(map_path)
    settings = SimSettings(
        frames=args.frames,
        fps=args.fps,
        trajectory=args.trajectory,
        seed=args.seed,
        distance_m=args.distance,
        width=args.width,
        height=args.height,
        format=args.format,
        dirt=args.dirt,
        occlusion=args.occlusion,
        blur=not args.no_blur,
        noise_sigma=0.0 if args.no_noise else SimSettings.noise_sigma,
        jpeg_quality=None if args.no_noise else SimSettings.jpeg_quality,
    ).validate()
    result = simulate(sign_map, args.out, settings, progress=not args.quiet)
    print(
        f"simulated {result.n_frames} frames ({settings.trajectory}, seed {settings.seed}) "
        f"of {map_path} into {result.out_dir}:"
    )
    for path in result.paths():
        print(f"  {path}")
    return 0
