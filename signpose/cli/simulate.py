"""``signpose simulate --map MAP --out DIR``: render a flight with ground truth."""

from __future__ import annotations

import argparse
import math
from dataclasses import replace
from pathlib import Path

from signpose.cli import add_quiet, count_arg, out_folder_arg
from signpose.core.errors import InputError
from signpose.maps.loader import bundled_map_path, load_map
from signpose.sim.flight import FORMATS, HARD, SimSettings, frames_for_duration, simulate
from signpose.sim.telemetry import SIM_ORIGIN, TelemetrySimSettings
from signpose.sim.trajectories import DEFAULT_SPEED_MPS, TRAJECTORIES


def register(sub: argparse._SubParsersAction) -> None:
    d = SimSettings()
    p = sub.add_parser(
        "simulate",
        help="render a simulated flight (frames + ground truth)",
        description="Render a UAV flight in front of the signs of MAP: frames (video.mp4 or "
        "frames/NNNNNN.png), camera.yaml, groundtruth.tum, boxes.jsonl and map.yaml in DIR. "
        "Same seed, same outputs. The flight lasts --frames / --fps seconds (or --duration) "
        "at the trajectory's cruise speed (--speed): a shorter flight is the start of a longer "
        "one. Past one pass of its path the orbit goes round again; climb-hover-depart and "
        "lawnmower fly their path back and forth (depart, return, descend; sweep up the "
        "pylon, then down), turning where they stop.",
    )
    p.add_argument(
        "--map", type=Path, default=None, help="sign map YAML (default: the bundled demo pylon)"
    )
    p.add_argument("--out", type=out_folder_arg, required=True, help="output folder")
    length = p.add_mutually_exclusive_group()
    length.add_argument(
        "--frames",
        type=int,
        default=None,
        help=f"frames; the flight lasts FRAMES / fps seconds (default {d.frames})",
    )
    length.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="SECONDS",
        help="the flight's length instead of --frames: round(SECONDS * fps) frames",
    )
    p.add_argument("--fps", type=float, default=d.fps, help=f"frame rate (default {d.fps:g})")
    p.add_argument(
        "--speed",
        type=float,
        default=None,
        metavar="M/S",
        help="cruise speed, the mean speed over one pass of the path (path length / pass "
        "time), in (0, 30] m/s; the summary line prints the flight's mean and peak (default: "
        + ", ".join(f"{name} {v:g}" for name, v in DEFAULT_SPEED_MPS.items())
        + ")",
    )
    p.add_argument(
        "--trajectory",
        choices=TRAJECTORIES,
        default=d.trajectory,
        help=f"flight (default {d.trajectory})",
    )
    p.add_argument("--seed", type=count_arg, default=d.seed, help="random seed (default 0)")
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
    t = p.add_argument_group("drone telemetry (docs/telemetry.md)")
    t.add_argument(
        "--telemetry",
        action="store_true",
        help="also write telemetry.csv: GNSS 10 Hz (1.2 m / 1.8 m noise, drift, multipath "
        "bursts near the conductors) and a 200 Hz MEMS IMU from the flight's ground truth, "
        "2 s before the first frame to 2 s after the last; map.yaml gets an origin (the "
        f"map's own, else lat {SIM_ORIGIN.lat_deg:g} lon {SIM_ORIGIN.lon_deg:g} height "
        f"{SIM_ORIGIN.height_m:g} m) so `signpose run ... --telemetry` can fuse it",
    )
    t.add_argument(
        "--clock-offset",
        type=float,
        default=None,
        metavar="S",
        help="with --telemetry: telemetry time minus video time [s], rounded to 1 ms (default 0)",
    )
    g = p.add_argument_group("real-pylon conditions (recorded in boxes.jsonl)")
    g.add_argument(
        "--hard",
        action="store_true",
        help="every condition below on at realistic rates (the options below override it)",
    )
    for name, kind, text in CONDITIONS:
        how = {"action": "store_true"} if kind is bool else {"type": kind}
        flag = "--" + name.replace("_", "-")
        g.add_argument(flag, default=None, help=_hard(text, name), **how)
    add_quiet(p)
    p.set_defaults(func=run)


def _hard(text: str, name: str) -> str:
    """An option's help with its default (off) and the value --hard gives it."""
    value = HARD[name]
    if value is True:
        return f"{text} (default: off; on with --hard)"
    shown = ",".join(map(str, value)) if isinstance(value, tuple) else f"{value:g}"
    return f"{text} (default: off; {shown} with --hard)"


def _quality_range(text: str) -> tuple[int, int]:
    """argparse type for ``--jpeg-range 70,90``."""
    try:
        lo, hi = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LO,HI such as 70,90, got {text!r}") from None
    return lo, hi


# The real-pylon conditions: option (SimSettings field), type (bool: a switch), help.
CONDITIONS = (
    ("members", float, "share of signs crossed by a member"),
    ("conductors", int, "extra conductors in front"),
    ("insulators", bool, "insulator strings"),
    ("faded", float, "share of faces with faded paint"),
    ("glare", float, "share of faces with specular glare"),
    ("photo", bool, "photographs as backgrounds"),
    ("jpeg_range", _quality_range, "per-frame JPEG quality LO,HI"),
    ("vibration", float, "vibration blur bursts per s"),
    ("exposure_steps", float, "auto-exposure gain steps per s"),
)
CONDITION_OPTIONS = tuple(name for name, _, _ in CONDITIONS)


def _telemetry_settings(args: argparse.Namespace) -> TelemetrySimSettings | None:
    """The sensor errors for --telemetry (the library's defaults), None without it."""
    if args.clock_offset is not None and not args.telemetry:
        raise InputError("--clock-offset needs --telemetry (it is the telemetry's clock)")
    if not args.telemetry:
        return None
    offset = 0.0 if args.clock_offset is None else args.clock_offset
    if not (math.isfinite(offset) and abs(offset) <= 60.0):
        raise InputError(f"--clock-offset must be a number of seconds within +-60, got {offset}")
    return TelemetrySimSettings(clock_offset_s=offset)


def run(args: argparse.Namespace) -> int:
    map_path = args.map if args.map is not None else bundled_map_path()
    sign_map = load_map(map_path)
    if args.duration is not None:
        frames = frames_for_duration(args.duration, args.fps)
    else:
        frames = SimSettings.frames if args.frames is None else args.frames
    settings = SimSettings(
        frames=frames,
        fps=args.fps,
        speed_mps=DEFAULT_SPEED_MPS[args.trajectory] if args.speed is None else args.speed,
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
    )
    if args.hard:
        settings = settings.hard()
    given = {k: getattr(args, k) for k in CONDITION_OPTIONS if getattr(args, k) is not None}
    settings = replace(settings, **given).validate()
    telemetry = _telemetry_settings(args)
    result = simulate(sign_map, args.out, settings, progress=args.progress, telemetry=telemetry)
    print(
        f"simulated {result.n_frames} frames ({result.duration_s:.2f} s, {settings.trajectory}, "
        f"mean {result.mean_speed_mps:.2f} m/s, peak {result.peak_speed_mps:.2f} m/s, "
        f"seed {settings.seed}) of {map_path} into {result.out_dir}" + ("" if args.quiet else ":")
    )
    if not args.quiet:  # --quiet: the result line only
        for path in result.paths():
            print(f"  {path}")
    return 0
