#!/usr/bin/env python
"""Decoder evaluation on synthetic crops, as the paper's Tables 2 and 3.

Renders crops with ``frontend.synth`` (every code, random rotation, sizes
18-200 px log-uniform, view angles 0-60 degrees, six backgrounds, noise,
some blur, dirt and power lines; seeded) and decodes each with
``frontend.decoder.decode_roi``. Prints:

* Table 2: per code, count / wrong code / no decode;
* Table 3: per condition (complex surroundings, motion blur, dirt, power line
  across the sign, 18 px, oblique view), the share decoded correctly, each on
  its own set of crops;
* the centre error (RMS px) against the true projection of the sign centre,
  for signs >= 40 px and overall, and by view angle;
* the perspective bias: how far the centroid of the location rectangle and
  the centre of the disc's ellipse lie from the projected centre (exact
  geometry), and the decoder's mean centre error with and without its
  perspective correction;
* the median decoding time per crop.

    .venv/bin/python scripts/eval_decoder.py [--quick] [--json PATH] [--seed N]
        [--independent N] [--independent-only] [--dump-wrong DIR] [--search-bars]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import Counter, defaultdict
from dataclasses import asdict, replace
from pathlib import Path

import cv2
import numpy as np
from signpose.frontend.decoder import DecoderSettings, decode_roi
from signpose.frontend.homography import apply_homography, disc_ellipse, polygon_centroids
from signpose.frontend.sign import ALL_CODES, PAPER_CODES, sign_shape
from tqdm import tqdm

from signpose.core.fileio import atomic_path, atomic_write, ensure_dir
from signpose.sim.crops import render_crop

sys.path.insert(0, str(Path(__file__).resolve().parent))
from independent_scene import CONDITIONS as INDEPENDENT_CONDITIONS  # noqa: E402
from independent_scene import render_scene_crop, scene_settings  # noqa: E402

BACKGROUND_WEIGHTS = {
    "plain": 0.2,
    "sky": 0.25,
    "lattice": 0.15,
    "lines": 0.15,
    "ground": 0.1,
    "clutter": 0.15,
}
CONDITIONS = (
    "complex surroundings",
    "motion blur",
    "dirt",
    "power line across the sign",
    "18 px",
    "oblique view (45-60 deg)",
)
TILT_BINS = ((0, 15), (15, 30), (30, 45), (45, 60))


def _choice(rng: np.random.Generator, weights: dict[str, float]) -> str:
    keys = list(weights)
    p = np.array([weights[k] for k in keys])
    return keys[int(rng.choice(len(keys), p=p / p.sum()))]


def main_params(rng: np.random.Generator, i: int) -> dict:
    """Parameters of crop ``i`` of the main set (Table 2)."""
    sign_px = float(math.exp(rng.uniform(math.log(18), math.log(200))))
    blur = 0.0
    if rng.random() < 0.25:
        blur = float(rng.uniform(1.0, max(1.5, min(6.0, 0.06 * sign_px))))
    return {
        "code": ALL_CODES[i % len(ALL_CODES)],
        "sign_px": sign_px,
        "rotation_deg": float(rng.uniform(0, 360)),
        "tilt_deg": float(rng.uniform(0, 60)),
        "tilt_axis_deg": float(rng.uniform(0, 180)),
        "background": _choice(rng, BACKGROUND_WEIGHTS),
        "noise_sigma": float(rng.uniform(0, 4)),
        "blur_px": blur,
        "dirt": bool(rng.random() < 0.1),
        "power_line": bool(rng.random() < 0.1),
        "contrast": float(rng.uniform(0.6, 1.1)),
        "brightness": float(rng.uniform(-20, 20)),
        "focal_px": float(rng.choice([500.0, 800.0, 1400.0])),
        "offset_px": tuple(float(x) for x in rng.uniform(-0.05, 0.05, 2) * sign_px),
    }


def condition_params(rng: np.random.Generator, i: int, condition: str) -> dict:
    """Parameters of crop ``i`` of one Table 3 condition: nominal except for it."""
    p = {
        "code": ALL_CODES[i % len(ALL_CODES)],
        "sign_px": float(math.exp(rng.uniform(math.log(30), math.log(120)))),
        "rotation_deg": float(rng.uniform(0, 360)),
        "tilt_deg": float(rng.uniform(0, 30)),
        "tilt_axis_deg": float(rng.uniform(0, 180)),
        "background": str(rng.choice(["plain", "sky"])),
        "noise_sigma": float(rng.uniform(0, 3)),
        "blur_px": 0.0,
        "dirt": False,
        "power_line": False,
        "contrast": float(rng.uniform(0.8, 1.0)),
        "brightness": float(rng.uniform(-10, 10)),
        "focal_px": 800.0,
        "offset_px": (0.0, 0.0),
    }
    if condition == "complex surroundings":
        p["background"] = str(rng.choice(["lattice", "lines", "clutter", "ground"]))
    elif condition == "motion blur":
        p["blur_px"] = float(max(2.0, rng.uniform(0.04, 0.08) * p["sign_px"]))
    elif condition == "dirt":
        p["dirt"] = True
    elif condition == "power line across the sign":
        p["power_line"] = True
    elif condition == "18 px":
        p["sign_px"] = 18.0
    elif condition == "oblique view (45-60 deg)":
        p["tilt_deg"] = float(rng.uniform(45, 60))
    else:
        raise ValueError(condition)
    return p


def geometric_bias(crop) -> tuple[np.ndarray, np.ndarray]:
    """Exact offsets [px] from the projected centre of (location centroid, ellipse centre)."""
    h = crop.crop_H_sign
    square = sign_shape("0000", crop.diameter_m).white_parts["center"]
    centroid = polygon_centroids(apply_homography(h, square)[None])[0]
    centre = np.asarray(crop.keypoints_px["center"])
    ellipse_c = np.asarray(disc_ellipse(h, crop.diameter_m)[0])
    return centroid - centre, ellipse_c - centre


def run_set(params_list, rng, settings, desc, quiet):
    rows = []
    for p in tqdm(params_list, desc=desc, disable=quiet, leave=False):
        kw = dict(p)
        code = kw.pop("code")
        crop = render_crop(code, rng, **kw)
        t0, c0 = time.perf_counter(), time.process_time()
        res = decode_roi(crop.image, None, settings)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        row = {"p": p, "crop": crop, "res": res, "wall_s": wall, "cpu_s": cpu}
        if res.code == code:
            row["err"] = np.subtract(res.keypoints_px["center"], crop.keypoints_px["center"])
        rows.append(row)
    return rows


def rms(errs) -> float:
    e = np.asarray(errs, float).reshape(-1, 2)
    return float(np.sqrt((e**2).sum(axis=1).mean())) if len(e) else float("nan")


# ---- The independent scenes (scripts/independent_scene.py).


def _group(crop) -> str:
    """Occlusion group of a scene crop, from its covered-part truth."""
    if max(crop.covered.values()) < 0.02:
        return "unoccluded"
    n = len(crop.covered_slots)
    return (
        "occluded, 0 slots" if n == 0 else ("occluded, 1 slot" if n == 1 else "occluded, 2+ slots")
    )


def _unique_with_one_erased(code: str, slot: int, codes) -> bool:
    flipped = code[: slot - 1] + ("0" if code[slot - 1] == "1" else "1") + code[slot:]
    return flipped not in codes


def _dump_wrong(dump_dir: Path, cond: str, i: int, crop, res) -> dict:
    """Write one wrong reading's crop (PNG) and return what the record says of it."""
    name = f"{cond.replace(' ', '_')}_{i:05d}_{crop.code}_read_{res.code}.png"
    with atomic_path(dump_dir / name) as tmp:
        cv2.imwrite(str(tmp), crop.image)
    return {
        "png": name,
        "condition": cond,
        "index": i,
        "code": crop.code,
        "read": res.code,
        "erased_slots": list(res.erased_slots),
        "covered": {k: round(v, 3) for k, v in crop.covered.items() if v > 0.005},
        "covered_slots": list(crop.covered_slots),
        "bars": crop.bars,
        "settings": asdict(crop.settings),
    }


def run_independent(
    n_per_condition: int,
    seed: int,
    quiet: bool,
    dump_dir: Path | None = None,
    settings: DecoderSettings | None = None,
) -> dict:
    """Decode ``n_per_condition`` independent crops per condition; print and return the table.

    ``dump_dir``: write every wrong reading there (PNG per crop, wrong.jsonl).
    ``settings``: the decoder's (default ``DecoderSettings()``).
    """
    settings = DecoderSettings() if settings is None else settings
    codes = PAPER_CODES
    rng = np.random.default_rng(seed)
    table: dict = {}
    sigma_rows = []
    dumped = []
    if dump_dir is not None:
        ensure_dir(dump_dir)
    print(
        f"\nIndependent scenes (scripts/independent_scene.py, photographs, 3D bars, JPEG; "
        f"{n_per_condition} crops per condition, map = the paper's 10 codes, seed {seed}"
        + (", search_bars" if settings.search_bars else "")
        + ")"
    )
    print(f"{'Condition':<22}{'group':<20}{'n':>6}{'correct':>9}{'refused':>9}{'WRONG':>7}")
    for cond in INDEPENDENT_CONDITIONS:
        counts: dict[str, Counter] = defaultdict(Counter)
        for i in tqdm(range(n_per_condition), desc=cond, disable=quiet, leave=False):
            s = scene_settings(rng, cond)
            crop = render_scene_crop(codes[i % len(codes)], s, rng)
            res = decode_roi(crop.image, codes, settings)
            group = _group(crop)
            outcome = (
                "correct" if res.code == crop.code else ("refused" if res.code is None else "wrong")
            )
            keys = [group]
            if group == "unoccluded" and s.sign_px >= 18:
                keys.append("unoccluded >= 18 px")
            if group == "occluded, 1 slot":
                slot = crop.covered_slots[0]
                # Exactly one slot covered: the centre and directional
                # rectangles untouched, other slots at most grazed.
                alone = max(crop.covered["center"], crop.covered["direction"]) < 0.02
                if _unique_with_one_erased(crop.code, slot, codes) and alone:
                    keys.append("1 slot, unique in map")
            for key in keys + ["all"]:
                counts[key]["n"] += 1
                counts[key][outcome] += 1
                counts[key]["reason:" + str(res.reason)] += 1
            if outcome == "correct":
                sigma_rows.append(_sigma_row(cond, group, crop, res))
            if outcome == "wrong" and dump_dir is not None:
                dumped.append(_dump_wrong(dump_dir, cond, i, crop, res))
        table[cond] = {k: dict(v) for k, v in counts.items()}
        for key in (
            "all",
            "unoccluded >= 18 px",
            "occluded, 0 slots",
            "occluded, 1 slot",
            "1 slot, unique in map",
            "occluded, 2+ slots",
        ):
            c = counts.get(key)
            if not c:
                continue
            print(
                f"{cond:<22}{key:<20}{c['n']:>6}{100 * c['correct'] / c['n']:>8.1f}%"
                f"{100 * c['refused'] / c['n']:>8.1f}%{c['wrong']:>7}"
            )
    total_wrong = sum(t["all"].get("wrong", 0) for t in table.values())
    total_n = sum(t["all"]["n"] for t in table.values())
    print(f"  wrong codes overall: {total_wrong} of {total_n}")
    if dump_dir is not None:
        with atomic_write(dump_dir / "wrong.jsonl") as f:
            for rec in dumped:
                f.write(json.dumps(rec) + "\n")
        print(f"  wrong readings written to {dump_dir} ({len(dumped)})")
    calib = _sigma_table(sigma_rows)
    return {
        "n_per_condition": n_per_condition,
        "seed": seed,
        "table": table,
        "wrong": total_wrong,
        "n": total_n,
        "sigma_calibration": calib,
    }


def _sigma_row(cond, group, crop, res) -> dict:
    """Per-keypoint normalised errors (error / sigma per axis) of one correct decode."""
    out = {"condition": cond, "group": group, "z": {}}
    sig = getattr(res, "keypoint_sigma_px", None) or {}
    for name, uv in res.keypoints_px.items():
        su, sv = sig.get(name, (res.sigma_px, res.sigma_px))
        e = np.subtract(uv, crop.keypoints_px[name])
        out["z"][name] = (float(e[0] / su), float(e[1] / sv), float(e[0]), float(e[1]))
    return out


def _sigma_table(rows) -> dict:
    """rms(error / sigma) per condition and keypoint kind (centre / direction / slots)."""
    acc: dict = defaultdict(list)
    for r in rows:
        for name, z in r["z"].items():
            kind = name if name in ("center", "direction") else "slot"
            acc[(r["condition"], kind)].append(z)
    print(
        "\n  sigma_px calibration, correct decodes: rms(error / sigma) per axis (u, v), "
        "rms error [px]"
    )
    out = {}
    for (cond, kind), zs in sorted(acc.items()):
        z = np.asarray(zs)
        ru, rv = np.sqrt((z[:, :2] ** 2).mean(axis=0))
        eu, ev = np.sqrt((z[:, 2:] ** 2).mean(axis=0))
        out[f"{cond}/{kind}"] = {
            "n": len(z),
            "rms_z_u": float(ru),
            "rms_z_v": float(rv),
            "rms_err_u_px": float(eu),
            "rms_err_v_px": float(ev),
        }
        print(
            f"  {cond:<22}{kind:<10}{len(z):>6}  z {ru:5.2f} {rv:5.2f}   err {eu:6.3f} {ev:6.3f} px"
        )
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="small run (a few hundred crops)")
    ap.add_argument("--n", type=int, default=None, help="crops in the main set (default 2048)")
    ap.add_argument("--per-condition", type=int, default=None, help="crops per Table 3 row")
    ap.add_argument("--seed", type=int, default=2017)
    ap.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    ap.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    ap.add_argument(
        "--independent",
        type=int,
        default=None,
        help="crops per condition of the independent scenes (default 100 quick, 400; 0: skip)",
    )
    ap.add_argument("--independent-only", action="store_true", help="only the independent scenes")
    ap.add_argument(
        "--search-bars",
        action="store_true",
        help="decode with DecoderSettings(search_bars=True) (straight print-black bars)",
    )
    ap.add_argument(
        "--dump-wrong",
        type=Path,
        default=None,
        metavar="DIR",
        help="write each wrong independent-scene reading to DIR (PNG + wrong.jsonl)",
    )
    args = ap.parse_args(argv)
    n_indep = args.independent if args.independent is not None else (100 if args.quick else 400)
    settings = DecoderSettings(search_bars=args.search_bars)
    if args.independent_only:
        indep = run_independent(n_indep, args.seed, args.quiet, args.dump_wrong, settings)
        if args.json is not None:
            with atomic_write(args.json) as f:
                json.dump({"independent": indep}, f, indent=2)
            print(f"wrote {args.json}")
        return 0
    n_main = args.n or (320 if args.quick else 2048)
    n_cond = args.per_condition or (48 if args.quick else 256)
    rng = np.random.default_rng(args.seed)

    # Warm-up (imports, first-call allocations) outside the timing.
    warm = render_crop("0101", np.random.default_rng(0), sign_px=40)
    for _ in range(5):
        decode_roi(warm.image)

    # ---- Table 2: main set.
    params = [main_params(rng, i) for i in range(n_main)]
    rows = run_set(params, rng, settings, "main set", args.quiet)
    per_code: dict[str, Counter] = defaultdict(Counter)
    for r in rows:
        code = r["p"]["code"]
        per_code[code]["n"] += 1
        if r["res"].code is None:
            per_code[code]["none"] += 1
        elif r["res"].code != code:
            per_code[code]["wrong"] += 1
    total = Counter()
    for c in per_code.values():
        total.update(c)
    reasons = Counter(r["res"].reason for r in rows if r["res"].code is None)

    print(f"Table 2: decoding of {n_main} synthetic crops (seed {args.seed})")
    print(
        f"{'Code':<6}{'Total':>7}{'Wrong':>7}{'No decode':>11}{'Wrong (%)':>11}{'Correct (%)':>13}"
    )
    for code in ALL_CODES:
        c = per_code[code]
        ok = c["n"] - c["wrong"] - c["none"]
        print(
            f"{code:<6}{c['n']:>7}{c['wrong']:>7}{c['none']:>11}"
            f"{100 * c['wrong'] / c['n']:>11.3f}{100 * ok / c['n']:>13.1f}"
        )
    ok_total = total["n"] - total["wrong"] - total["none"]
    print(
        f"{'Total':<6}{total['n']:>7}{total['wrong']:>7}{total['none']:>11}"
        f"{100 * total['wrong'] / total['n']:>11.3f}{100 * ok_total / total['n']:>13.1f}"
    )
    print("No decode by reason: " + ", ".join(f"{k} {v}" for k, v in reasons.most_common()))

    size_bins = ((18, 25), (25, 40), (40, 80), (80, 201))
    print("\nCorrect by size (main set):")
    size_table = {}
    for lo, hi in size_bins:
        sel = [r for r in rows if lo <= r["p"]["sign_px"] < hi]
        ok = sum(r["res"].code == r["p"]["code"] for r in sel)
        wrong = sum(r["res"].code not in (None, r["p"]["code"]) for r in sel)
        size_table[f"{lo}-{hi - 1}"] = {"n": len(sel), "correct": ok, "wrong": wrong}
        print(f"  {lo:>3}-{hi - 1:<3} px: {ok}/{len(sel)} = {100 * ok / max(len(sel), 1):.1f} %")

    # ---- Table 3: one set per condition.
    print(f"\nTable 3: robustness ({n_cond} crops per condition, share decoded correctly)")
    print(f"{'Disturbance':<30}{'Crops':>7}{'Correct (%)':>13}{'Wrong':>7}{'No decode':>11}")
    table3 = {}
    for cond in CONDITIONS:
        cparams = [condition_params(rng, i, cond) for i in range(n_cond)]
        crows = run_set(cparams, rng, settings, cond, args.quiet)
        ok = sum(r["res"].code == r["p"]["code"] for r in crows)
        wrong = sum(r["res"].code not in (None, r["p"]["code"]) for r in crows)
        none = sum(r["res"].code is None for r in crows)
        table3[cond] = {"n": n_cond, "correct": ok, "wrong": wrong, "no_decode": none}
        print(f"{cond:<30}{n_cond:>7}{100 * ok / n_cond:>13.1f}{wrong:>7}{none:>11}")

    # ---- Centre accuracy and perspective bias.
    good = [r for r in rows if "err" in r]
    big = [r for r in good if r["p"]["sign_px"] >= 40]
    rms_big, rms_all = rms([r["err"] for r in big]), rms([r["err"] for r in good])
    print("\nCentre error vs the true projection of the sign centre (correct decodes):")
    print(f"  signs >= 40 px: RMS {rms_big:.3f} px over {len(big)} crops")
    print(f"  all sizes:      RMS {rms_all:.3f} px over {len(good)} crops")
    sigma_ratio = [float(np.hypot(*r["err"]) / (math.sqrt(2) * r["res"].sigma_px)) for r in good]
    print(
        f"  reported sigma_px: median {np.median([r['res'].sigma_px for r in good]):.3f} px; "
        f"RMS(error / (sqrt(2) sigma)) = {math.sqrt(np.mean(np.square(sigma_ratio))):.2f}"
    )

    # Bias: exact geometry over the main set, and the decoder with/without
    # its perspective correction on clean oblique crops (large, near camera).
    print("\nPerspective bias by view angle (mean |offset| / max, px):")
    print(
        f"{'view angle':<12}{'loc. centroid':>16}{'ellipse centre':>17}"
        f"{'decoder, no corr.':>20}{'decoder, corrected':>20}"
    )
    bias_table = {}
    brng = np.random.default_rng(args.seed + 1)
    n_bias = 24 if args.quick else 64
    nocorr = replace(settings, perspective_correction=False)
    for lo, hi in TILT_BINS:
        sel = [r for r in rows if lo <= r["p"]["tilt_deg"] < hi]
        geo = [geometric_bias(r["crop"]) for r in sel]
        loc = np.array([np.hypot(*g[0]) for g in geo])
        ell = np.array([np.hypot(*g[1]) for g in geo])
        errs_nc, errs_c = [], []
        for k in range(n_bias):
            code = ALL_CODES[k % 16]
            kw = {
                "sign_px": float(brng.uniform(100, 200)),
                "rotation_deg": float(brng.uniform(0, 360)),
                "tilt_deg": float(brng.uniform(lo, hi)),
                "tilt_axis_deg": float(brng.uniform(0, 180)),
                "focal_px": 500.0,
                "noise_sigma": 1.0,
            }
            crop = render_crop(code, np.random.default_rng(k), **kw)
            truth = np.asarray(crop.keypoints_px["center"])
            a = decode_roi(crop.image, None, nocorr)
            b = decode_roi(crop.image, None, settings)
            if a.code == code and b.code == code:
                errs_nc.append(np.asarray(a.keypoints_px["center"]) - truth)
                errs_c.append(np.asarray(b.keypoints_px["center"]) - truth)
        mean_nc = float(np.hypot(*np.mean(errs_nc, axis=0))) if errs_nc else float("nan")
        mean_c = float(np.hypot(*np.mean(errs_c, axis=0))) if errs_c else float("nan")
        rms_nc, rms_c = rms(errs_nc), rms(errs_c)
        bias_table[f"{lo}-{hi}"] = {
            "location_centroid_mean_px": float(loc.mean()) if len(loc) else None,
            "location_centroid_max_px": float(loc.max()) if len(loc) else None,
            "ellipse_centre_mean_px": float(ell.mean()) if len(ell) else None,
            "ellipse_centre_max_px": float(ell.max()) if len(ell) else None,
            "decoder_uncorrected_rms_px": rms_nc,
            "decoder_corrected_rms_px": rms_c,
            "decoder_uncorrected_mean_px": mean_nc,
            "decoder_corrected_mean_px": mean_c,
            "n_near": len(errs_c),
        }
        print(
            f"{lo:>3}-{hi:<3} deg  {loc.mean():>7.3f} /{loc.max():>6.3f}"
            f"{ell.mean():>9.3f} /{ell.max():>6.3f}"
            f"{rms_nc:>14.3f} RMS{rms_c:>16.3f} RMS"
        )
    print(
        "  (decoder columns: 100-200 px signs, focal 500 px, i.e. close and wide-angle, "
        "where the bias is largest)"
    )

    # ---- Timing.
    wall = np.array([r["wall_s"] for r in rows]) * 1e3
    cpu = np.array([r["cpu_s"] for r in rows]) * 1e3
    print(
        f"\nDecoding time per crop: median {np.median(wall):.3f} ms wall "
        f"({np.median(cpu):.3f} ms CPU), 90th percentile {np.percentile(wall, 90):.3f} ms, "
        f"mean {wall.mean():.3f} ms wall ({cpu.mean():.3f} ms CPU)"
    )
    ok = np.array([r["res"].code is not None for r in rows])
    if ok.any() and (~ok).any():
        print(
            f"  median CPU: decoded {np.median(cpu[ok]):.3f} ms, "
            f"not decoded {np.median(cpu[~ok]):.3f} ms (every fallback tried)"
        )

    indep = (
        run_independent(n_indep, args.seed, args.quiet, args.dump_wrong, settings)
        if n_indep > 0
        else None
    )

    if args.json is not None:
        out = {
            "independent": indep,
            "seed": args.seed,
            "n_main": n_main,
            "table2": {
                code: {
                    "n": per_code[code]["n"],
                    "wrong": per_code[code]["wrong"],
                    "no_decode": per_code[code]["none"],
                }
                for code in ALL_CODES
            },
            "total": {"n": total["n"], "wrong": total["wrong"], "no_decode": total["none"]},
            "wrong_rate": total["wrong"] / total["n"],
            "no_decode_reasons": dict(reasons),
            "by_size": size_table,
            "table3": table3,
            "centre_rms_px_ge40": rms_big,
            "centre_rms_px_all": rms_all,
            "bias_by_view_angle": bias_table,
            "median_ms_wall": float(np.median(wall)),
            "median_ms_cpu": float(np.median(cpu)),
            "mean_ms_wall": float(wall.mean()),
            "mean_ms_cpu": float(cpu.mean()),
        }
        with atomic_write(args.json) as f:
            json.dump(out, f, indent=2)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
