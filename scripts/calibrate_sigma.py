#!/usr/bin/env python
"""Calibrate the decoder's keypoint sigma model against the simulator's truth (issue 11, item 3).

Renders crops with ``signpose.sim.crops.render_crop`` in the conditions of
``scripts/eval_decoder.py`` (its main mix and each Table 3 condition),
decodes them, and fits ``frontend.keypoint_noise.SigmaModel`` so that
rms(error / sigma) is close to 1 for every condition and keypoint kind
(least squares on log rms(z), Nelder-Mead on the log parameters). Prints the
table before and after, and the fitted model to paste into frontend/keypoint_noise.py.

The independent scenes (``scripts/eval_decoder.py --independent``) are the
check on data the fit never saw.

    .venv/bin/python scripts/calibrate_sigma.py [--n 120] [--seed 11] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict
from dataclasses import asdict, fields
from pathlib import Path

import numpy as np
from scipy.optimize import minimize
from signpose.frontend.decoder import decode_roi
from signpose.frontend.keypoint_noise import SIGMA_MODEL, SigmaModel, keypoint_sigmas
from tqdm import tqdm

from signpose.core.fileio import atomic_write
from signpose.sim.crops import render_crop

sys.path.insert(0, str(Path(__file__).resolve().parent))
from eval_decoder import CONDITIONS, condition_params, main_params  # noqa: E402

KINDS = ("center", "direction", "slot")


def _kind(name: str) -> str:
    return name if name in ("center", "direction") else "slot"


def collect(n: int, seed: int, quiet: bool) -> list[dict]:
    """Correct decodes: per keypoint the sigma inputs and the error [px]."""
    rng = np.random.default_rng(seed)
    rows = []
    sets = [("main mix", lambda i: main_params(rng, i))] + [
        (c, lambda i, c=c: condition_params(rng, i, c)) for c in CONDITIONS
    ]
    for name, make in sets:
        for i in tqdm(range(n), desc=name, disable=quiet, leave=False):
            p = make(i)
            code = p.pop("code")
            crop = render_crop(code, rng, **p)
            res = decode_roi(crop.image)
            if res.code != code or res.sigma_inputs is None:
                continue
            for kp, uv in res.keypoints_px.items():
                err = np.subtract(uv, crop.keypoints_px[kp])
                rows.append({"condition": name, "kp": kp, "inputs": res.sigma_inputs, "err": err})
    return rows


def table(rows: list[dict], model: SigmaModel) -> dict[tuple[str, str], tuple[int, float, float]]:
    """(condition, kind) -> (n, rms(err_u / sigma_u), rms(err_v / sigma_v))."""
    acc: dict = defaultdict(list)
    for r in rows:
        su, sv = keypoint_sigmas(r["inputs"], [r["kp"]], model)[r["kp"]]
        acc[(r["condition"], _kind(r["kp"]))].append((r["err"][0] / su, r["err"][1] / sv))
    out = {}
    for key, zs in acc.items():
        z = np.asarray(zs)
        ru, rv = np.sqrt((z**2).mean(axis=0))
        out[key] = (len(z), float(ru), float(rv))
    return out


def fit(rows: list[dict], start: SigmaModel) -> SigmaModel:
    names = [f.name for f in fields(SigmaModel)]

    def model_of(x: np.ndarray) -> SigmaModel:
        return SigmaModel(**dict(zip(names, np.exp(x).tolist(), strict=True)))

    def cost(x: np.ndarray) -> float:
        t = table(rows, model_of(x))
        # Every (condition, kind) group weighs the same: the target holds per group.
        return sum(math.log(ru) ** 2 + math.log(rv) ** 2 for _, ru, rv in t.values())

    # Zero terms restart from a small value (the fit is on log parameters).
    x0 = np.log([max(getattr(start, n), 1e-3) for n in names])
    # Every factor between 1/1000 and 1000 of its start; "occluded" only
    # between 1 and 40 (few calibration crops show a crossing occluder).
    lo = x0 - math.log(1000.0)
    hi = x0 + math.log(1000.0)
    k = names.index("occluded")
    lo[k], hi[k] = 0.0, math.log(40.0)
    res = minimize(
        cost,
        np.clip(x0, lo, hi),
        method="Powell",
        bounds=list(zip(lo, hi, strict=True)),
        options={"maxiter": 4000, "xtol": 1e-3},
    )
    return model_of(res.x)


def _print(t: dict, title: str) -> None:
    print(f"\n{title}: rms(error / sigma), u and v")
    print(f"{'condition':<30}{'kind':<11}{'n':>6}{'u':>7}{'v':>7}")
    for (cond, kind), (n, ru, rv) in sorted(t.items()):
        print(f"{cond:<30}{kind:<11}{n:>6}{ru:>7.2f}{rv:>7.2f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=120, help="crops per condition")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("-q", "--quiet", action="store_true")
    args = ap.parse_args(argv)
    rows = collect(args.n, args.seed, args.quiet)
    before = table(rows, SIGMA_MODEL)
    _print(before, f"Current model {SIGMA_MODEL}")
    model = fit(rows, SIGMA_MODEL)
    after = table(rows, model)
    _print(after, "Fitted model")
    print("\nSigmaModel(" + ", ".join(f"{k}={v:.4g}" for k, v in asdict(model).items()) + ")")
    if args.json is not None:
        out = {
            "seed": args.seed,
            "n_per_condition": args.n,
            "model": asdict(model),
            "before": {f"{c}/{k}": v for (c, k), v in before.items()},
            "after": {f"{c}/{k}": v for (c, k), v in after.items()},
        }
        with atomic_write(args.json) as f:
            json.dump(out, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
