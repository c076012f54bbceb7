#!/usr/bin/env python
"""Calibrate the decoder's keypoint sigma model against the simulator's truth (issue 11, item 3).

Renders crops with ``signpose.sim.crops.render_crop`` in the conditions of
``scripts/eval_decoder.py`` (its main mix and each Table 3 condition) and in
five more that the independent scenes also show (a member in front, a bar over
one slot, specular glare, JPEG 70-80, a faded face), and the independent
scenes of scripts/independent_scene.py (``--scenes`` per condition, 150 by
default, seed ``--seed`` + 1000: photographs, 3D bars, JPEG; another
renderer, whose clean signs the simulator-only fit left 1.3-1.4x too
cautious and whose conductors 1.3-2.6x too confident), decodes them, and
fits ``frontend.keypoint_noise.SigmaModel`` per keypoint kind:

1. a Gaussian likelihood fit of the additive variance model
   (``keypoint_noise.variance_terms``), every condition weighing the same;
2. from there, the constants that bring log rms(error / sigma) of every
   (condition, axis) group closest to 0 (Powell), held near the likelihood
   fit (the errors are heavy-tailed: a few large ones drive the rms); run
   also from the current model (terms it leaves at 0 from ``_SMALL``) and
   the better of the two kept: with the per-part pulls (issue 11) the
   likelihood start alone ended below the previous model (17-18 of 36
   groups inside 0.8-1.25 against its 22).

Prints per condition and kind rms(error / sigma) on u and v and the share of
|z| > 3, before and after, rows outside 0.8-1.25 marked, and the fitted model
to paste into frontend/keypoint_noise.py.

The independent scenes of ``scripts/eval_decoder.py --independent-only``
(seeds 2017 and 99) are the check on scenes the fit never saw (the same
renderer, other draws).

    .venv/bin/python scripts/calibrate_sigma.py [--n 150] [--scenes 150] [--seed 11] [--json P]
    .venv/bin/python scripts/calibrate_sigma.py --n 0 --scenes 1000 --scene-seed 31 --check-only
        (the current model on eval_decoder.py --independent-only --seed 31's crops,
        with the share of |z| > 3 that eval_decoder does not print)
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections import defaultdict
from dataclasses import asdict
from pathlib import Path

import numpy as np
from scipy.optimize import minimize
from signpose.frontend.decoder import decode_roi
from signpose.frontend.keypoint_noise import (
    SIGMA_MODEL,
    TERMS,
    KindNoise,
    SigmaModel,
    keypoint_sigmas,
    kind_of,
    variance_terms,
)
from signpose.frontend.sign import PAPER_CODES
from tqdm import tqdm

from signpose.core.fileio import atomic_write
from signpose.sim.crop_occluders import CropOccluder
from signpose.sim.crops import render_crop

sys.path.insert(0, str(Path(__file__).resolve().parent))
from eval_decoder import CONDITIONS, condition_params, main_params  # noqa: E402
from independent_scene import CONDITIONS as SCENE_CONDITIONS  # noqa: E402
from independent_scene import render_scene_crop, scene_settings  # noqa: E402

KINDS = ("center", "direction", "slot")
EXTRA_CONDITIONS = ("member in front", "bar over one slot", "specular glare", "jpeg 70-80", "faded")
# Few crops with a bar in front decode (most are refused as occluded), so
# those groups stay under MIN_GROUP and do not steer the fit: rendering 6x
# more of them made the fit chase the simulator's member crossings (direction
# errors of 2-3.6 px, crossed_px 1.9 px) and put the directional keypoint's
# sigma at 20x its error on the independent "one slot covered" scenes.
TARGET = (0.8, 1.25)
# Groups with fewer keypoints than this do not steer the fit (their rms is noise).
MIN_GROUP = 20
# Where step 2 starts a term the current model leaves at 0 (its constant's unit).
_SMALL = 0.01
# Terms held at 0 (see ``fit``): ``crossed`` (a fraction of the minor axis
# whenever an occluder crosses the face) went to 0.11 for the directional
# keypoint from a start of 0.1, i.e. 5 px sigmas on 50 px signs whose
# crossed directional errors are 0.1-0.5 px (the sim's power-line
# crossings drove it; the pulls and ``closed_px`` see those now).
DROPPED: tuple[str, ...] = ("crossed",)
# Least constants (per kind, all kinds alike): with the independent scenes in
# the fit the RMS residual of the homography fit went to ~1e-6 for the centre
# and the directional keypoint (the per-part residuals carry it where more
# than four parts over-determine the fit), so a sign whose parts disagree by
# 0.3 px kept a clean sign's sigma. The fit's residual r over 2P coordinates
# with 8 parameters says the centroids' noise is about r sqrt(2P / (2P - 8)),
# and a keypoint the homography predicts is about that uncertain: held at
# least r / 2 (a conservative half; P = 6 gives 1.7 r).
#
# ``closed_px`` went to ~2e-9 for the directional keypoint (348ebbb): a
# reading through the "open" fallback, whose measures never saw the line,
# then kept a clean sign's directional sigma. Held at least 0.1 px, below
# what centre and slot took then (0.16 / 0.18).
LEAST: dict[str, float] = {"residual": 0.5, "closed_px": 0.1}
# Least constants of one kind (over ``LEAST``). With ``scale`` in the model
# the fit traded the floors for it (0.017-0.018 -> 0.003-0.006 px), which
# the independent scenes' clean centres want (0.77 -> 0.80), but the
# directional keypoint's clean sigma of a 25 px sign fell by 40 % and the
# members flight's directional keypoints went from 1.19 to 1.27 on v
# (scripts/eval_flight.py --flights lens members): its floor is held at
# the value it had before ``scale`` (its scale then goes to ~0; 1.20).
LEAST_OF_KIND: dict[str, dict[str, float]] = {"direction": {"floor_px": 0.0183}}


def extra_params(rng: np.random.Generator, i: int, condition: str) -> dict:
    """Parameters of crop ``i`` of one of ``EXTRA_CONDITIONS``: nominal except for it."""
    p = condition_params(rng, i, "complex surroundings")
    p["background"] = str(rng.choice(["plain", "sky"]))
    if condition == "member in front":
        p["member"] = True
    elif condition == "bar over one slot":
        slot = f"slot{int(rng.integers(1, 5))}"
        p["occluders"] = (CropOccluder("member", through=slot),)
    elif condition == "specular glare":
        p["glare_dn"] = float(rng.uniform(40, 140))
    elif condition == "jpeg 70-80":
        p["jpeg_quality"] = int(rng.integers(70, 81))
    elif condition == "faded":
        p["fade"] = float(rng.uniform(0.2, 0.5))
        p["dirt"] = bool(rng.random() < 0.5)
    else:
        raise ValueError(condition)
    return p


def collect(n: int, seed: int, quiet: bool) -> list[dict]:
    """Correct decodes: per keypoint the sigma inputs and the error [px]."""
    rng = np.random.default_rng(seed)
    rows = []
    sets = [("main mix", lambda i: main_params(rng, i))]
    sets += [(c, lambda i, c=c: condition_params(rng, i, c)) for c in CONDITIONS]
    sets += [(c, lambda i, c=c: extra_params(rng, i, c)) for c in EXTRA_CONDITIONS]
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


def collect_scenes(n: int, seed: int, quiet: bool) -> list[dict]:
    """As ``collect`` on the independent scenes (scripts/independent_scene.py:
    photographs, 3D bars, JPEG), ``n`` per condition, conditions named
    "scene: <condition>", codes the paper's map."""
    rng = np.random.default_rng(seed)
    rows = []
    for cond in SCENE_CONDITIONS:
        for i in tqdm(range(n), desc=cond, disable=quiet, leave=False):
            s = scene_settings(rng, cond)
            crop = render_scene_crop(PAPER_CODES[i % len(PAPER_CODES)], s, rng)
            res = decode_roi(crop.image, PAPER_CODES)
            if res.code != crop.code or res.sigma_inputs is None:
                continue
            for kp, uv in res.keypoints_px.items():
                err = np.subtract(uv, crop.keypoints_px[kp])
                inputs = res.sigma_inputs
                rows.append({"condition": f"scene: {cond}", "kp": kp, "inputs": inputs, "err": err})
    return rows


def table(rows: list[dict], model: SigmaModel) -> dict[tuple[str, str], tuple]:
    """(condition, kind) -> (n, rms z_u, rms z_v, share of |z| > 3 over both axes)."""
    acc: dict = defaultdict(list)
    for r in rows:
        su, sv = keypoint_sigmas(r["inputs"], [r["kp"]], model)[r["kp"]]
        acc[(r["condition"], kind_of(r["kp"]))].append((r["err"][0] / su, r["err"][1] / sv))
    out = {}
    for key, zs in acc.items():
        z = np.asarray(zs)
        ru, rv = np.sqrt((z**2).mean(axis=0))
        out[key] = (len(z), float(ru), float(rv), float((np.abs(z) > 3).mean()))
    return out


def tails(rows: list[dict], model: SigmaModel) -> dict[str, tuple[int, float]]:
    """Share of |error / sigma| > 3 over both axes (Gaussian: 0.27 %), on all
    keypoints and on crossed readings only: "all" / "crossed" -> (n, share)."""
    z: dict[str, list] = {"all": [], "crossed": []}
    for r in rows:
        su, sv = keypoint_sigmas(r["inputs"], [r["kp"]], model)[r["kp"]]
        zz = (abs(r["err"][0] / su), abs(r["err"][1] / sv))
        z["all"].extend(zz)
        if r["inputs"].crossed:
            z["crossed"].extend(zz)
    return {k: (len(v) // 2, float(np.mean(np.asarray(v) > 3)) if v else 0.0) for k, v in z.items()}


def _print_tails(rows: list[dict], model: SigmaModel) -> None:
    t = tails(rows, model)
    print(
        "share of |z| > 3 (Gaussian 0.27 %): "
        + ", ".join(f"{k} {100 * share:.2f} % of {n} keypoints" for k, (n, share) in t.items())
    )


def _design(rows: list[dict], kind: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Squared terms (2N, T), errors (2N,), group index (2N,) and axis (2N,) of one kind."""
    x, e, g, ax = [], [], [], []
    groups: dict[str, int] = {}
    for r in rows:
        if kind_of(r["kp"]) != kind:
            continue
        x.extend(variance_terms(r["inputs"], r["kp"]))
        e.extend(r["err"])
        gid = groups.setdefault(r["condition"], len(groups))
        g.extend([gid, gid])
        ax.extend([0, 1])
    return np.asarray(x), np.asarray(e), np.asarray(g), np.asarray(ax)


def _likelihood_fit(x: np.ndarray, e: np.ndarray, g: np.ndarray, lo: np.ndarray) -> np.ndarray:
    """log of the squared constants maximising the Gaussian likelihood, groups
    weighed equally, each at least ``lo``."""
    w = 1.0 / np.bincount(g)[g]

    def nll(lc2: np.ndarray) -> tuple[float, np.ndarray]:
        c2 = np.exp(lc2)
        s2 = x @ c2
        r = e**2 / s2
        grad = ((w * (1.0 - r) / s2) @ x) * c2
        return float(np.sum(w * (np.log(s2) + r))), grad

    best = None
    for start in (-12.0, -6.0):
        x0 = np.maximum(np.full(x.shape[1], start), lo)
        x0[0] = math.log(np.mean(e**2) / 4)
        bounds = [(max(-40.0, b), 10.0) for b in lo]
        res = minimize(nll, x0, jac=True, method="L-BFGS-B", bounds=bounds)
        if best is None or res.fun < best.fun:
            best = res
    return best.x


def _group_fit(x, e, g, ax, start: np.ndarray, lo: np.ndarray) -> tuple[np.ndarray, float]:
    """From ``start``: log squared constants (each at least ``lo``) minimising
    sum (log rms z)^2 over groups and axes, and that cost."""
    ng = int(g.max()) + 1

    def cost(lc2: np.ndarray) -> float:
        z2 = e**2 / (x @ np.exp(np.maximum(lc2, lo)))
        c = 0.0
        for a in (0, 1):
            m = ax == a
            num = np.bincount(g[m], z2[m], ng)
            den = np.bincount(g[m], None, ng)
            ok = den >= MIN_GROUP
            c += float(np.sum(np.log(num[ok] / den[ok]) ** 2))
        # Held near the likelihood fit: a term may move by a factor ~e per 0.1 of cost.
        return c + 1e-2 * float(np.sum((lc2 - start) ** 2))

    res = minimize(cost, start, method="Powell", options={"maxiter": 20000, "xtol": 1e-3})
    # Powell moves one direction at a time; a simplex from there finds the
    # joint moves (the terms overlap: floor, size and spread).
    res = minimize(
        cost, res.x, method="Nelder-Mead", options={"maxiter": 20000, "xatol": 1e-3, "fatol": 1e-6}
    )
    return res.x, float(res.fun)


def fit(
    rows: list[dict],
    groups: bool = True,
    start: SigmaModel = SIGMA_MODEL,
    dropped: tuple[str, ...] = DROPPED,
) -> SigmaModel:
    """The model fitted per keypoint kind (module docstring, steps 1-2; 1 only
    without ``groups``). Step 2 runs from the likelihood fit and from
    ``start`` (terms it leaves at 0 from a small value) and keeps the better:
    the cost has several local minima (the terms overlap). Terms in
    ``dropped`` are held at 0."""
    kinds = {}
    keep = np.array([t not in dropped for t in TERMS], dtype=float)
    for kind in KINDS:
        least = {**LEAST, **LEAST_OF_KIND.get(kind, {})}
        lo = np.array([2 * math.log(least[t]) if t in least else -np.inf for t in TERMS])
        x, e, g, ax = _design(rows, kind)
        x = x * keep
        lc2 = _likelihood_fit(x, e, g, lo)
        if groups:
            prior = np.log(np.maximum(getattr(start, kind).coefficients(), _SMALL) ** 2)
            prior = np.maximum(prior, lo)
            fits = (_group_fit(x, e, g, ax, s, lo) for s in (lc2, prior))
            lc2 = min(fits, key=lambda r: r[1])[0]
        c = np.sqrt(np.exp(np.maximum(lc2, lo))) * keep
        kinds[kind] = KindNoise(**{n: float(f"{v:.3g}") for n, v in zip(TERMS, c, strict=True)})
    return SigmaModel(**kinds)


def _print(t: dict, title: str) -> None:
    lo, hi = TARGET
    print(f"\n{title}: rms(error / sigma) on u and v, share of |z| > 3 ('<' outside {lo}-{hi})")
    print(f"{'condition':<30}{'kind':<11}{'n':>6}{'u':>7}{'v':>7}{'|z|>3':>8}")
    for (cond, kind), (n, ru, rv, tail) in sorted(t.items()):
        flag = "" if lo <= ru <= hi and lo <= rv <= hi else "  <"
        print(f"{cond:<30}{kind:<11}{n:>6}{ru:>7.2f}{rv:>7.2f}{100 * tail:>7.1f}%{flag}")
    inside = sum(1 for n, ru, rv, _ in t.values() if lo <= ru <= hi and lo <= rv <= hi)
    print(f"groups inside {lo}-{hi} on both axes: {inside} of {len(t)}")


def _model_source(model: SigmaModel) -> str:
    lines = ["SIGMA_MODEL = SigmaModel("]
    for kind in KINDS:
        k = getattr(model, kind)
        args = ", ".join(f"{n}={getattr(k, n):.3g}" for n in TERMS)
        lines.append(f"    {kind}=KindNoise({args}),")
    return "\n".join(lines + [")"])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=150, help="crops per condition")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument(
        "--likelihood-only", action="store_true", help="skip step 2 (the per-group fit)"
    )
    ap.add_argument(
        "--scenes",
        type=int,
        default=150,
        help="independent-scene crops per condition in the fit (0: simulator crops only)",
    )
    ap.add_argument(
        "--scene-seed",
        type=int,
        default=None,
        help="the independent scenes' seed (default --seed + 1000; eval_decoder.py "
        "--independent-only --seed S renders the same crops with S)",
    )
    ap.add_argument(
        "--check-only", action="store_true", help="print the current model's table, fit nothing"
    )
    ap.add_argument("-q", "--quiet", action="store_true")
    args = ap.parse_args(argv)
    rows = collect(args.n, args.seed, args.quiet)
    if args.scenes > 0:
        # Their own stream: eval_decoder's checks use seeds 2017 and 99.
        scene_seed = args.seed + 1000 if args.scene_seed is None else args.scene_seed
        rows += collect_scenes(args.scenes, scene_seed, args.quiet)
    before = table(rows, SIGMA_MODEL)
    _print(before, "Current model (frontend/keypoint_noise.py)")
    _print_tails(rows, SIGMA_MODEL)
    if args.check_only:
        return 0
    model = fit(rows, groups=not args.likelihood_only)
    after = table(rows, model)
    _print(after, "Fitted model")
    _print_tails(rows, model)
    print("\n" + _model_source(model))
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
