#!/usr/bin/env python
"""Frontend timing per 1080p frame on one core: detector modes, tracking, ArUco.

Simulates a short held-out flight (``signpose.sim.flight``), then times on the
same frames, with ``cv2.setNumThreads(1)``:

* ``fast``: full-frame cold detection, fast mode (cascade + merge + decoder);
* ``paper``: full-frame cold detection, the paper's sliding window;
* ``track``: ``detect_tracked`` with predictions (code, centre, diameter)
  taken from the previous frame's truth, as the pipeline's pose prediction;
* ``aruco``: ``cv2.aruco.ArucoDetector.detectMarkers`` (DICT_4X4_50), the
  usual fiducial alternative, on the same frames.

    .venv/bin/python scripts/bench_frontend.py [--quick] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
from signpose.frontend.detector import SignDetector
from signpose.maps.loader import bundled_map_path, load_map

from signpose.core.fileio import atomic_write
from signpose.io.boxes import read_boxes
from signpose.sim.flight import SimSettings, simulate

BENCH_SEED = 5151


def _median_ms(fn, frames, repeat: int = 1) -> tuple[float, list]:
    out, times = [], []
    for i, f in enumerate(frames):
        best = float("inf")
        for _ in range(repeat):
            t0 = time.perf_counter()
            r = fn(i, f)
            best = min(best, time.perf_counter() - t0)
        times.append(best * 1e3)
        out.append(r)
    return statistics.median(times), out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 frames instead of 40")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--cascade", type=Path, default=None, help="cascade XML (default: bundled)")
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    n = args.frames or (10 if args.quick else 40)
    sign_map = load_map(bundled_map_path())
    codes = sign_map.codes
    with tempfile.TemporaryDirectory() as tmp:
        settings = SimSettings(frames=n + 1, seed=BENCH_SEED, format="png")
        simulate(sign_map, tmp, settings, progress=False)
        boxes = read_boxes(Path(tmp) / "boxes.jsonl")
        frames = [
            cv2.imread(str(Path(tmp) / "frames" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
            for i in range(n + 1)
        ]
    det = SignDetector(args.cascade)
    results: dict[str, float] = {}
    found: dict[str, float] = {}
    n_true = sum(len(b["signs"]) for b in boxes[1:])
    for mode in ("fast", "paper"):
        ms, res = _median_ms(lambda i, f, m=mode: det.detect(f, codes, mode=m), frames[1:])
        results[mode] = ms
        results[f"{mode}_cascade_only"] = statistics.median(r.timing["cascade"] for r in res)
        results[f"{mode}_decode"] = statistics.median(r.timing["decode"] for r in res)
        found[mode] = sum(len(r.detections) for r in res) / max(n_true, 1)

    def track(i, f):
        prev = boxes[i]  # frames[1:][i] is frame i + 1; predict from frame i
        preds = [(s["code"], tuple(s["center_px"]), s["diameter_px"]) for s in prev["signs"]]
        return det.detect_tracked(f, preds, codes)

    ms, res = _median_ms(track, frames[1:])
    results["track"] = ms
    results["track_cascade_only"] = statistics.median(r.timing["cascade"] for r in res)
    results["track_decode"] = statistics.median(r.timing["decode"] for r in res)
    results["track_fallbacks"] = sum(r.fell_back for r in res)
    found["track"] = sum(len(r.detections) for r in res) / max(n_true, 1)
    aruco = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), cv2.aruco.DetectorParameters()
    )
    ms, _ = _median_ms(lambda i, f: aruco.detectMarkers(f), frames[1:])
    results["aruco"] = ms
    print(f"{n} frames 1920x1080 (simulated, seed {BENCH_SEED}), one core, median ms per frame")
    for k in ("fast", "paper", "track", "aruco"):
        extra = f"  (signs found {100 * found[k]:.1f} %)" if k in found else ""
        print(f"  {k:6s} {results[k]:8.1f} ms{extra}")
    print("  medians of the parts (ms):")
    for k in ("fast", "paper", "track"):
        print(
            f"    {k:6s} cascade {results[k + '_cascade_only']:7.1f}   "
            f"decoder {results[k + '_decode']:7.1f}"
        )
    print(f"  tracking fell back to the full frame {results['track_fallbacks']} times")
    for k in ("fast", "paper", "track"):
        print(f"  {k} / aruco = {results[k] / results['aruco']:.2f}")
    results["ratios_to_aruco"] = {
        k: results[k] / results["aruco"] for k in ("fast", "paper", "track")
    }
    results["found_fraction"] = found
    if args.json:
        with atomic_write(args.json) as f:
            json.dump({"frames": n, "seed": BENCH_SEED, **results}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
