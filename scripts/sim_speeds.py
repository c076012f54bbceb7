"""Speeds the simulated flights fly: each trajectory at its default cruise speed, and squeezed.

Usage:
    .venv/bin/python scripts/sim_speeds.py [--frames 60 210] [--fps 30] [--json FILE]

For every trajectory over the bundled map (27 m from the signs): its path length,
its default cruise speed (``DEFAULT_SPEED_MPS``, the mean path speed
``signpose simulate`` flies), and for each frame count the mean (distance /
time) and peak (fastest frame step) speed of the flight ``signpose simulate
--frames N`` flies now, beside the flight the library's old behaviour gives
(the whole path squeezed into the N frames, ``speed_mps=None``, which
``simulate --frames N`` flew before issue 16). Also the largest position
difference between the default ``simulate`` flight (210 frames) now and
before. Only geometry: no rendering, deterministic, a second or two.

``--detect lawnmower``: also renders that trajectory's flight of the first
``--frames`` count at 1920x1080 both ways (now and squeezed) and runs the
frontend (``signpose.pipeline.observe``, tracking on) over each, printing the
frames in which no sign was decoded (issue 16: 27 of 60 squeezed lawnmower
frames). About a minute.

    .venv/bin/python scripts/sim_speeds.py --frames 60 210 --detect lawnmower
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from signpose.maps.loader import bundled_map_path, load_map

from signpose.core.fileio import atomic_write
from signpose.io.sources import open_source
from signpose.pipeline import observe
from signpose.sim.flight import SimSettings, simulate
from signpose.sim.trajectories import (
    DEFAULT_SPEED_MPS,
    TRAJECTORIES,
    make_trajectory,
    path_length_m,
    speed_stats,
)


def _frames_without_signs(sign_map, name: str, frames: int, speed: float | None) -> dict:
    """Render ``frames`` of trajectory ``name`` and observe them: frames with no decoded sign."""
    settings = SimSettings(frames=frames, trajectory=name, speed_mps=speed)
    with tempfile.TemporaryDirectory(prefix="sim_speeds_") as tmp:
        sim = simulate(sign_map, Path(tmp) / "flight", settings, progress=False)
        result = observe(open_source(sim.frames_path), sign_map, sim.camera, progress=False)
    empty = sum(1 for f in result.frames if not f.signs)
    return {
        "trajectory": name,
        "frames": frames,
        "speed_mps": speed,
        "mean_speed_mps": round(sim.mean_speed_mps, 3),
        "peak_speed_mps": round(sim.peak_speed_mps, 3),
        "frames_without_signs": empty,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[60, 210])
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument(
        "--detect",
        choices=TRAJECTORIES,
        help="also render this trajectory's flight (first --frames) and count undetected frames",
    )
    parser.add_argument("--json", help="also write the numbers to this JSON file")
    args = parser.parse_args(argv)
    sign_map = load_map(bundled_map_path())
    rows = []
    print(
        f"{'trajectory':20} {'path m':>7} {'speed':>6} {'frames':>6} "
        f"{'mean now':>9} {'peak now':>9} {'mean old':>9} {'peak old':>9}  (m/s)"
    )
    for name in TRAJECTORIES:
        speed = DEFAULT_SPEED_MPS[name]
        length = path_length_m(name, sign_map)
        for n in args.frames:
            now = make_trajectory(name, sign_map, n, args.fps, speed_mps=speed)
            old = make_trajectory(name, sign_map, n, args.fps)
            (mean_now, peak_now), (mean_old, peak_old) = speed_stats(now), speed_stats(old)
            moved = float(np.abs(now.world_t_cam - old.world_t_cam).max())
            print(
                f"{name:20} {length:7.2f} {speed:6.2f} {n:6d} "
                f"{mean_now:9.2f} {peak_now:9.2f} {mean_old:9.2f} {peak_old:9.2f}"
            )
            rows.append(
                {
                    "trajectory": name,
                    "path_m": round(length, 3),
                    "speed_mps": speed,
                    "frames": n,
                    "fps": args.fps,
                    "mean_speed_mps": round(mean_now, 3),
                    "peak_speed_mps": round(peak_now, 3),
                    "old_mean_speed_mps": round(mean_old, 3),
                    "old_peak_speed_mps": round(peak_old, 3),
                    "max_position_change_m": round(moved, 4),
                }
            )
    default = next(
        (r for r in rows if r["trajectory"] == TRAJECTORIES[0] and r["frames"] == 210), None
    )
    if default is not None:
        print(
            f"default flight ({TRAJECTORIES[0]}, 210 frames): positions moved by at most "
            f"{default['max_position_change_m'] * 100:.1f} cm against the old timing"
        )
    detected = []
    if args.detect:
        n = args.frames[0]
        for label, speed in (("now", DEFAULT_SPEED_MPS[args.detect]), ("old", None)):
            d = _frames_without_signs(sign_map, args.detect, n, speed)
            detected.append({"timing": label, **d})
            print(
                f"{args.detect} {n} frames 1920x1080, {label} (mean {d['mean_speed_mps']:.2f} m/s, "
                f"peak {d['peak_speed_mps']:.2f} m/s): no sign decoded in "
                f"{d['frames_without_signs']} of {n} frames"
            )
    if args.json:
        with atomic_write(args.json, encoding="utf-8") as f:
            json.dump({"rows": rows, "detect": detected}, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
