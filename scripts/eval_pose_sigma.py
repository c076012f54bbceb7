#!/usr/bin/env python
"""Do the pose sigmas match the errors? End to end, on rendered flights (issue 11, item 3).

Renders flights with ``signpose simulate`` (an orbit at 1280x720, clean and
``--hard``: photographs, members and conductors across signs, glare, faded
faces, JPEG, vibration), observes each once (``signpose observe``) and
estimates it (``signpose estimate --method all``) against three maps:

* ``exact, fixed``: the map the scene was rendered from, treated as exact
  (``--map-fixed``): the pose sigmas then come from the keypoint sigmas alone;
* ``surveyed``: the signs moved by N(0, sigma_m) per axis, as a real survey
  with the map's stated ``sigma_m`` would leave them, estimated as a user
  would (the default: each sign with its survey prior); ``--surveys K``
  draws per flight, since all frames of one draw share its error;
* ``exact, with prior``: the rendered map with its survey prior (the default
  settings on a map that happens to be exact): the sigmas carry the survey's
  1 cm per sign that the errors do not show, so they are cautious by design.

The baseline writes no sigmas (``estimate.BASELINE_SIGMAS``): its rows say
so. With ``--map-fixed`` PnP's sigmas are its pixel noise alone; with a survey
prior they carry the survey share too (``projection.pose_fit``).

Prints, per scene, map and method, over all posed frames of all seeds:
rms(error / sigma) per world axis, the share of errors within 2 sigma, the
share beyond 3 sigma, and how many poses labelled ``ok`` are beyond 3 sigma
on some axis (a pose a user would trust and should not).

    .venv/bin/python scripts/eval_pose_sigma.py [--seeds 5 6] [--duration 6] [--surveys 4]
        [--scenes clean hard] [--work DIR] [--json PATH]
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
from signpose.maps.loader import load_map, write_map

from signpose.cli import main as signpose
from signpose.core.fileio import atomic_write

MAPS = ("exact, fixed", "surveyed", "exact, with prior")
METHODS = ("baseline", "pnp", "smoothed")
AXES = "xyz"


def _cli(*argv: str) -> None:
    code = signpose([*argv])
    if code != 0:
        raise SystemExit(f"signpose {' '.join(argv)} exited {code}")


def surveyed_map(src: Path, dst: Path, seed: int) -> float:
    """Write ``src`` with each centre moved by N(0, sigma_m) per axis; return the RMS move."""
    m = load_map(src)
    rng = np.random.default_rng(10_000 + seed)
    moved, signs = [], []
    for s in m.signs:
        d = rng.normal(0.0, s.sigma_m, 3)
        moved.append(d)
        signs.append(replace(s, center_m=np.asarray(s.center_m, float) + d))
    write_map(dst, replace(m, signs=tuple(signs)))
    return float(np.sqrt(np.mean(np.square(moved))))


def flight(work: Path, scene: str, seed: int, duration: float) -> Path:
    """Render and observe one flight; return its folder."""
    d = work / f"{scene}_{seed}"
    sim = d / "sim"
    if not (d / "observations.jsonl").exists():
        extra = ["--hard"] if scene == "hard" else []
        _cli(
            "simulate", "--out", str(sim), "--trajectory", "orbit", "--duration", str(duration),
            "--width", "1280", "--height", "720", "--seed", str(seed), "-q", *extra,
        )  # fmt: skip
        _cli(
            "observe", str(sim / "video.mp4"), "--map", str(sim / "map.yaml"),
            "--camera", str(sim / "camera.yaml"), "--out", str(d / "observations.jsonl"), "-q",
        )  # fmt: skip
    return d


def estimate(d: Path, which: str, draw: int) -> Path:
    """Estimate flight ``d`` against map ``which`` (survey ``draw``); return the output folder."""
    sim = d / "sim"
    out = d / which.replace(", ", "_").replace(" ", "_")
    args = ["--map", str(sim / "map.yaml")]
    if which == "exact, fixed":
        args.append("--map-fixed")
    elif which == "surveyed":
        out = out.with_name(f"{out.name}_{draw}")
        surveyed_map(sim / "map.yaml", d / f"map_surveyed_{draw}.yaml", draw)
        args = ["--map", str(d / f"map_surveyed_{draw}.yaml")]
    _cli(
        "estimate", str(d / "observations.jsonl"), *args, "--camera", str(sim / "camera.yaml"),
        "--out", str(out), "--method", "all", "-q",
    )  # fmt: skip
    return out


def normalised_errors(out: Path, gt_path: Path) -> dict[str, dict[str, np.ndarray]]:
    """method -> {"z": (N, 3) error / sigma, "ok": (N,) status ok}, posed frames with sigmas."""
    gt = np.loadtxt(gt_path, comments="#", ndmin=2)
    acc: dict[str, dict[str, list]] = {m: {"z": [], "ok": []} for m in METHODS}
    with open(out / "trajectory.csv", newline="") as f:
        for r in csv.DictReader(f):
            if r["method"] not in acc or r["x_m"] == "" or r["sigma_x_m"] == "":
                continue
            k = int(np.argmin(np.abs(gt[:, 0] - float(r["t_s"]))))
            e = [float(r[f"{a}_m"]) - gt[k, 1 + i] for i, a in enumerate(AXES)]
            s = [float(r[f"sigma_{a}_m"]) for a in AXES]
            acc[r["method"]]["z"].append(np.divide(e, s))
            acc[r["method"]]["ok"].append(r["status"] == "ok")
    return {
        m: {"z": np.asarray(v["z"], float).reshape(-1, 3), "ok": np.asarray(v["ok"], bool)}
        for m, v in acc.items()
    }


def summary(z: np.ndarray, ok: np.ndarray) -> dict:
    if len(z) == 0:
        return {"n": 0}
    return {
        "n": int(len(z)),
        "rms_z": np.sqrt(np.mean(z**2, axis=0)).round(3).tolist(),
        "within_2sigma": (np.abs(z) <= 2).mean(axis=0).round(3).tolist(),
        "beyond_3sigma": (np.abs(z) > 3).mean(axis=0).round(4).tolist(),
        "ok": int(ok.sum()),
        "ok_beyond_3sigma": int((ok & (np.abs(z) > 3).any(axis=1)).sum()),
    }


def _print(results: dict) -> None:
    print(
        f"\n{'scene':<7}{'map':<19}{'method':<10}{'n':>5}  {'rms(e/sigma) x y z':<20}"
        f"{'within 2 sigma':<20}{'beyond 3 sigma':<23}ok beyond 3 sigma"
    )
    for (scene, which, method), r in results.items():
        if r["n"] == 0:
            print(f"{scene:<7}{which:<19}{method:<10}{0:>5}  (no poses with sigmas)")
            continue
        rz = " ".join(f"{v:.2f}" for v in r["rms_z"])
        w2 = " ".join(f"{100 * v:.0f}%" for v in r["within_2sigma"])
        b3 = " ".join(f"{100 * v:.1f}%" for v in r["beyond_3sigma"])
        print(
            f"{scene:<7}{which:<19}{method:<10}{r['n']:>5}  {rz:<20}{w2:<20}{b3:<23}"
            f"{r['ok_beyond_3sigma']} of {r['ok']}"
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[5, 6])
    ap.add_argument("--duration", type=float, default=6.0, help="seconds per flight")
    ap.add_argument("--surveys", type=int, default=4, help="survey draws per flight")
    ap.add_argument("--scenes", nargs="+", choices=("clean", "hard"), default=["clean", "hard"])
    ap.add_argument("--work", type=Path, default=None, help="keep the flights here (reused)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="signpose_pose_sigma_"))
    print(f"flights in {work}")
    pooled: dict[tuple[str, str, str], dict[str, list]] = {}
    for scene in args.scenes:
        for seed in args.seeds:
            d = flight(work, scene, seed, args.duration)
            runs = [
                (w, 1000 * seed + j)
                for w in MAPS
                for j in range(args.surveys if w == "surveyed" else 1)
            ]
            for which, draw in runs:
                errs = normalised_errors(estimate(d, which, draw), d / "sim" / "groundtruth.tum")
                for method, e in errs.items():
                    p = pooled.setdefault((scene, which, method), {"z": [], "ok": []})
                    p["z"].append(e["z"])
                    p["ok"].append(e["ok"])
    results = {
        key: summary(np.concatenate(v["z"]), np.concatenate(v["ok"])) for key, v in pooled.items()
    }
    print(
        f"\nseeds {args.seeds}, {args.duration:g} s orbits at 1280x720, {args.surveys} survey"
        " draws per flight, all posed frames"
    )
    _print(results)
    if args.json is not None:
        with atomic_write(args.json) as f:
            json.dump({" / ".join(k): v for k, v in results.items()}, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
