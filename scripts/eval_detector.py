#!/usr/bin/env python
"""Detector evaluation on simulated flights, as the paper's Table 1.

Simulates held-out flights with ``signpose.simulate`` (seeds never used in
training: the detector is trained on ``frontend.synth`` crops only), runs the
detector on every frame and scores it against ``boxes.jsonl``:

    N  signs present (not truncated, disc >= 18 px)
    D  of those, signs the decoder reads from the true box (the ceiling)
    S  regions reported (decoded detections)
    T  true: right code, centre within half a diameter of the truth
    F  false: S - T
    precision = T / S, recall = S / N (the paper's definitions), T / N and T / D

split by sign size (18-30, 30-60, 60-200 px), for the paper's merge and
``cv2.groupRectangles``, in ``fast`` and ``paper`` modes.

``--photo-flights K`` adds K short flights with real photographs behind the
pylon (``SimSettings(photo=True)``, scikit-image's data images; each flight
gets the photograph its seed picks) and prints, for the default detector
(group merge), a table per background and mode: recall S/N and T/N over
signs >= 18 px, precision and T/D (``--json``: the same under
``backgrounds``).

    .venv/bin/python scripts/eval_detector.py [--quick] [--photo-flights 8] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
from signpose.frontend.detector import DetectorSettings, SignDetector
from signpose.maps.loader import bundled_map_path, load_map

from signpose.core.fileio import atomic_write
from signpose.io.boxes import read_boxes
from signpose.sim.flight import SimSettings, simulate

BINS = ((18, 30), (30, 60), (60, 200))
# Held-out flights: (trajectory, distance [m], share of the frames). Far, middle
# and near so that every size bin is populated.
# (The lawnmower flight is left out: at these ranges its speed smears the signs
# beyond what the decoder reads even from the true boxes.)
FLIGHTS = (
    ("orbit", 62.0, 0.34),
    ("climb-hover-depart", 32.0, 0.33),
    ("climb-hover-depart", 15.0, 0.33),
)
EVAL_SEED = 4242
# Procedural-background flights run beside the photo flights, for reference.
REFERENCE_FLIGHTS = 2


def _frames(out: Path, n: int):
    boxes = read_boxes(out / "boxes.jsonl")
    for i in range(n):
        gray = cv2.imread(str(out / "frames" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
        yield gray, boxes[i]


def _bin(d: float) -> str | None:
    for lo, hi in BINS:
        if lo <= d < hi:
            return f"{lo}-{hi}"
    return None


def _empty() -> dict:
    return {"N": 0, "D": 0, "S": 0, "T": 0, "F": 0}


def decodable(gray: np.ndarray, truth: dict) -> set[str]:
    """Codes the decoder reads from the true boxes (the ceiling for any detector)."""
    from signpose.frontend.decoder import decode_region

    return {
        s["code"]
        for s in truth["signs"]
        if not s["truncated"] and decode_region(gray, s["bbox_px"]).code == s["code"]
    }


def score(detections, truth: dict, table: dict, readable: set[str]) -> None:
    signs = [s for s in truth["signs"] if not s["truncated"]]
    by_code = {}
    for s in truth["signs"]:
        by_code.setdefault(s["code"], []).append(s)
    for s in signs:
        b = _bin(s["diameter_px"])
        if b:
            table[b]["N"] += 1
            table[b]["D"] += s["code"] in readable
    for d in detections:
        match = None
        for s in by_code.get(d.code, []):
            if np.hypot(*(np.subtract(d.center_px, s["center_px"]))) <= 0.5 * s["diameter_px"]:
                match = s
        size = match["diameter_px"] if match else max(d.bbox_px[2], d.bbox_px[3])
        if match is not None and (match["truncated"] or _bin(size) is None):
            continue  # a sign outside the table (cut by the border or < 18 px): not counted
        b = _bin(size) or ("18-30" if size < 18 else "60-200")
        table[b]["S"] += 1
        table[b]["T" if match else "F"] += 1


def _background_tables(
    root: Path,
    sign_map,
    detector: SignDetector,
    modes: list[str],
    flights: int,
    frames: int,
    seed: int,
) -> dict:
    """background -> mode -> summarized table, over flights with photographs behind.

    Two flights of the same kind with the procedural background come first,
    as the reference.
    """
    tables: dict[str, dict[str, dict]] = {}
    for k in range(flights + REFERENCE_FLIGHTS):
        out = root / f"photo{k}"
        settings = SimSettings(
            frames=frames,
            trajectory="climb-hover-depart",
            distance_m=28.0,
            seed=seed + 100 + k,
            format="png",
            photo=k >= REFERENCE_FLIGHTS,
        )
        simulate(sign_map, out, settings, progress=False)
        for gray, truth in _frames(out, frames):
            background = truth.get("conditions", {}).get("background", "procedural")
            readable = decodable(gray, truth)
            for mode in modes:
                tab = tables.setdefault(background, {}).setdefault(
                    mode, {f"{lo}-{hi}": _empty() for lo, hi in BINS}
                )
                res = detector.detect(gray, sign_map.codes, mode=mode)
                score(res.detections, truth, tab, readable)
        print(f"background flight {k}: seed {seed + 100 + k}, {frames} frames", file=sys.stderr)
    return {
        bg: {mode: summarize(tab) for mode, tab in by_mode.items()}
        for bg, by_mode in sorted(tables.items())
    }


def _print_backgrounds(backgrounds: dict) -> None:
    print("\nper background (merge group), signs >= 18 px:")
    print(
        f"{'background':>26} {'mode':>5} {'N':>5} {'S':>5} {'F':>3} {'precision':>10} "
        f"{'recall S/N':>10} {'T/N':>7} {'T/D':>7}"
    )
    for bg, by_mode in backgrounds.items():
        for mode, summ in by_mode.items():
            r = summ["all"]
            print(
                f"{bg:>26} {mode:>5} {r['N']:5d} {r['S']:5d} {r['F']:3d} "
                f"{100 * r['precision']:9.2f}% {100 * r['recall']:9.2f}% "
                f"{100 * r['true_recall']:6.2f}% {100 * r['recall_of_decodable']:6.2f}%"
            )


def summarize(table: dict) -> dict:
    total = _empty()
    for row in table.values():
        for k in total:
            total[k] += row[k]
    out = {}
    for name, row in [*table.items(), ("all", total)]:
        r = dict(row)
        r["precision"] = r["T"] / r["S"] if r["S"] else float("nan")
        r["recall"] = r["S"] / r["N"] if r["N"] else float("nan")
        r["true_recall"] = r["T"] / r["N"] if r["N"] else float("nan")
        r["recall_of_decodable"] = r["T"] / r["D"] if r["D"] else float("nan")
        out[name] = r
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="30 frames instead of 300")
    ap.add_argument("--frames", type=int, default=None, help="total frames (default 300)")
    ap.add_argument("--modes", default="fast,paper", help="detection modes to score")
    ap.add_argument("--cascade", type=Path, default=None, help="cascade XML (default: bundled)")
    ap.add_argument("--seed", type=int, default=EVAL_SEED, help="simulation seed (held out)")
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    ap.add_argument("--keep", type=Path, default=None, help="simulate into this folder")
    ap.add_argument(
        "--photo-flights", type=int, default=0, help="flights with photographs behind (default 0)"
    )
    ap.add_argument("--photo-frames", type=int, default=10, help="frames per photo flight")
    ap.add_argument(
        "--skip-main", action="store_true", help="only the photo flights (with --photo-flights)"
    )
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    total = args.frames or (30 if args.quick else 300)
    modes = [m for m in args.modes.split(",") if m]
    sign_map = load_map(bundled_map_path())
    base = DetectorSettings()
    detectors = {m: SignDetector(args.cascade, replace(base, merge=m)) for m in ("paper", "group")}
    tables = {
        (mode, merge): {f"{lo}-{hi}": _empty() for lo, hi in BINS}
        for mode in modes
        for merge in detectors
    }
    times: dict[tuple[str, str], list[float]] = {k: [] for k in tables}
    extra = {k: {"regions": 0, "undecoded": 0} for k in tables}
    n_frames = 0
    backgrounds: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        if args.photo_flights:
            backgrounds = _background_tables(
                root,
                sign_map,
                detectors["group"],
                modes,
                args.photo_flights,
                args.photo_frames,
                args.seed,
            )
        for k, (traj, dist, share) in enumerate(() if args.skip_main else FLIGHTS):
            n = max(1, round(total * share))
            out = root / f"flight{k}_{traj}"
            settings = SimSettings(
                frames=n, trajectory=traj, distance_m=dist, seed=args.seed + k, format="png"
            )
            simulate(sign_map, out, settings, progress=False)
            for gray, truth in _frames(out, n):
                n_frames += 1
                readable = decodable(gray, truth)
                for mode in modes:
                    t0 = time.perf_counter()
                    raw = detectors["paper"].raw_windows(gray, mode)
                    t_raw = time.perf_counter() - t0
                    for merge, det in detectors.items():
                        t1 = time.perf_counter()
                        res = det._finish(gray, raw, sign_map.codes, mode, {}, t1)
                        times[(mode, merge)].append((t_raw + time.perf_counter() - t1) * 1e3)
                        tab = tables[(mode, merge)]
                        score(res.detections, truth, tab, readable)
                        extra[(mode, merge)]["regions"] += res.n_regions
                        extra[(mode, merge)]["undecoded"] += res.n_undecoded
            print(
                f"flight {k}: {traj} at {dist:g} m, {n} frames, seed {args.seed + k}",
                file=sys.stderr,
            )
    results = {}
    print(f"held-out simulated flights: {n_frames} frames 1920x1080, seeds {args.seed}+")
    for (mode, merge), tab in tables.items():
        summ = summarize(tab)
        key = f"{mode}/{merge}"
        ex = extra[(mode, merge)]
        results[key] = {
            "table": summ,
            "median_ms": float(np.median(times[(mode, merge)])),
            **ex,
        }
        print(
            f"\nmode {mode}, merge {merge}: cascade regions {ex['regions']}, dropped as "
            f"undecoded {ex['undecoded']}, median {results[key]['median_ms']:.0f} ms/frame"
        )
        print(
            f"{'size px':>8} {'N':>6} {'S':>6} {'T':>6} {'F':>4} {'precision':>10} "
            f"{'recall S/N':>10} {'T/N':>7} {'D':>6} {'T/D':>7}"
        )
        for name, r in summ.items():
            print(
                f"{name:>8} {r['N']:6d} {r['S']:6d} {r['T']:6d} {r['F']:4d} "
                f"{100 * r['precision']:9.2f}% {100 * r['recall']:9.2f}% "
                f"{100 * r['true_recall']:6.2f}% {r['D']:6d} "
                f"{100 * r['recall_of_decodable']:6.2f}%"
            )
    if backgrounds:
        _print_backgrounds(backgrounds)
    if args.json:
        data = {"frames": n_frames, "seed": args.seed, "results": results}
        data["backgrounds"] = backgrounds
        with atomic_write(args.json) as f:
            json.dump(data, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
