#!/usr/bin/env python
"""Evaluate the estimators on simulated flights (the paper's Table 4, and more).

Paper-like geometry: the bundled 10-sign map, a 1920x1080 camera (60 deg
horizontal field of view unless --hfov), flights 25-30 m from the signs, keypoint
noise as the decoder measures it (--sigma-px, default 0.13 px:
scripts/eval_decoder.py measures 0.134 px RMS centre error on signs >= 40 px,
and the full pipeline on simulated video 0.08 px), with and without
injected faults (5 % of observations given another sign's code, 2 % false
observations at random pixels). Two maps: ``planar`` (the demo map flattened
onto its best-fit plane, the paper's assumption) and ``demo`` (signs up to
0.3 m off the plane). Prints, per scenario, per-axis mean absolute error, ATE
and coverage for: baseline (paper), pnp, smoothed batch, smoothed iSAM2
(final) and causal (iSAM2's estimate of each frame when it arrived); then the
motion-prior comparison and the planarity sweep of the paper's method.

    .venv/bin/python scripts/eval_estimator.py [--quick] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace

import numpy as np
from signpose.estimator.camera import pinhole_camera
from signpose.estimator.estimate import (
    EstimatorSettings,
    estimate_trajectories,
    gate_measurements,
)
from signpose.estimator.metrics import Metrics, compute_metrics, format_table
from signpose.estimator.perframe import PerFrameSettings, run_per_frame
from signpose.estimator.projection import pose_covariance, position_cov_world
from signpose.estimator.robust import OutlierSettings
from signpose.estimator.smoother import (
    LANDMARK_MODELS,
    SmootherSettings,
    collect_measurements,
    covariances_at,
    default_pose,
    smooth_batch,
    smooth_isam2,
)
from signpose.estimator.status import PoseStatus
from signpose.estimator.trajectory import Trajectory
from signpose.maps.loader import bundled_map_path, load_map

from signpose.core.fileio import atomic_write
from signpose.io.results import status_shares
from signpose.sim.observations import SyntheticSettings, flatten_map, paper_like_frames
from signpose.sim.scenarios import build_scenario

FAULTS = {"clean": (0.0, 0.0), "faults": (0.05, 0.02)}


def _traj(stamps, poses) -> Trajectory:
    ok = [p is not None for p in poses]
    T = np.array([p for p in poses if p is not None]).reshape(-1, 4, 4)
    return Trajectory.from_matrices(np.asarray(stamps)[ok], T)


def run_scenario(sign_map, camera, flight, n_frames, fault, sigma_px, seed, motion, isam=True):
    """Metrics of every method on one simulated flight."""
    rng = np.random.default_rng(seed)
    wrong, false = FAULTS[fault]
    syn = SyntheticSettings(sigma_px=sigma_px, wrong_code_rate=wrong, false_rate=false)
    frames, gt, _ = paper_like_frames(
        sign_map, camera, n_frames, rng, syn, flight=flight, seed=seed
    )
    stamps = gt.stamps_s
    pf = PerFrameSettings()
    out: dict[str, Metrics] = {}
    base = run_per_frame(frames, sign_map, camera, "baseline", pf)
    pnp = run_per_frame(frames, sign_map, camera, "pnp", pf)
    out["baseline"] = compute_metrics(_traj(stamps, [p.world_T_cam for p in base]), gt)
    out["pnp"] = compute_metrics(_traj(stamps, [p.world_T_cam for p in pnp]), gt)
    meas, _ = gate_measurements(
        collect_measurements(frames, sign_map, camera),
        [p.world_T_cam for p in pnp],
        camera,
        EstimatorSettings().gate_px,
    )
    init = [
        a.world_T_cam if a.world_T_cam is not None else b.world_T_cam
        for a, b in zip(pnp, base, strict=True)
    ]
    default = default_pose(sign_map)
    extra = {}
    for m in (motion,) if isinstance(motion, str) else motion:
        sm = SmootherSettings(motion=m, compute_sigmas=False)
        r = smooth_batch(meas, stamps, init, camera, sm, default)
        key = "smoothed" if isinstance(motion, str) else f"smoothed[{m}]"
        out[key] = compute_metrics(_traj(stamps, list(r.world_T_cam)), gt)
        extra[key + "_s"] = r.seconds
        if isam and isinstance(motion, str):
            ri = smooth_isam2(meas, stamps, [p.world_T_cam for p in pnp], camera, sm, default)
            out["isam2"] = compute_metrics(_traj(stamps, list(ri.world_T_cam)), gt)
            out["causal"] = compute_metrics(_traj(stamps, list(ri.causal_world_T_cam)), gt)
            d = np.abs(ri.world_T_cam[:, :3, 3] - r.world_T_cam[:, :3, 3]).max()
            extra["isam2_vs_batch_max_m"] = float(d)
            extra["isam2_median_ms"] = float(np.median(ri.per_frame_ms))
    return out, extra


# --------------------------------------------------------------------------- issue 12


def _errors(m, truth: Trajectory) -> np.ndarray:
    """(N, 3) position error of a MethodEstimate [m], NaN where it has no pose."""
    e = m.world_T_cam[:, :3, 3] - truth.world_t_cam
    e[~m.valid] = np.nan
    return e


def honesty(err: np.ndarray, sigma: np.ndarray) -> dict:
    """Per axis: share of |error| < 2 sigma and rms(error / sigma) over poses with both."""
    ok = np.all(np.isfinite(err), axis=1) & np.all(np.isfinite(sigma) & (sigma > 0), axis=1)
    if not ok.any():
        return {"share_2sigma": [None] * 3, "rms_z": [None] * 3, "n": 0}
    z = err[ok] / sigma[ok]
    return {
        "share_2sigma": [float(x) for x in np.mean(np.abs(z) < 2.0, axis=0)],
        "rms_z": [float(x) for x in np.sqrt(np.mean(z**2, axis=0))],
        "n": int(ok.sum()),
    }


def method_numbers(m, truth: Trajectory) -> dict:
    """Worst-axis MAE, max error, honesty, ok poses beyond 4 sigma and status shares."""
    e = _errors(m, truth)
    norm = np.linalg.norm(e, axis=1)
    z = np.abs(e) / m.sigma_xyz
    ok = np.array([st is PoseStatus.OK for st in m.status])
    beyond = ok & (np.nanmax(np.where(np.isfinite(z), z, 0.0), axis=1) > 4.0)
    return {
        "worst_axis_mae_m": float(np.nanmax(np.nanmean(np.abs(e), axis=0))),
        "max_error_m": float(np.nanmax(norm)),
        "rmse_m": float(np.sqrt(np.nanmean(norm**2))),
        "ok_beyond_4sigma": int(beyond.sum()),
        "status": status_shares(m),
        **honesty(e, m.sigma_xyz),
    }


FAULT_CONFIGS = {
    "issue12": EstimatorSettings(methods=("pnp", "smoothed")),
    "gnc": EstimatorSettings(methods=("pnp", "smoothed"), final_kernel="gnc"),
    "huber": EstimatorSettings(  # as before issue 12: no innovation test, no final kernel
        methods=("pnp", "smoothed"), outliers=OutlierSettings(rounds=0), final_kernel="huber"
    ),
}


def fault_section(seeds: list[int]) -> dict:
    """Issue 12's fault scenario, clean and faulty, per seed and configuration."""
    print(
        "\n## fault scenario (issue 12): figure-eight 22-32 m, 9 centre-only signs, 0.3 px, "
        "20 frames with 2 signs and a wrong code, 5 % wrong codes, 2 % false observations"
    )
    print(
        f"{'seed':>4} {'config':<8} {'method':<9} {'MAE clean':>9} {'faulty':>8} {'ratio':>6} "
        f"{'max clean':>9} {'faulty':>7} {'ratio':>6} {'ok>4sig':>7} {'2sig x/y/z faulty':>18} "
        f"{'status faulty':<}"
    )
    out: dict = {}
    for seed in seeds:
        runs = {}
        for faults in (False, True):
            sc = build_scenario(np.random.default_rng(seed), faults=faults)
            for name, cfg in FAULT_CONFIGS.items():
                r = estimate_trajectories(sc.frames, sc.sign_map, sc.camera, cfg, progress=False)
                runs[(name, faults)] = {
                    k: method_numbers(m, sc.truth) for k, m in r.methods.items()
                }
                runs[(name, faults)]["rejected"] = len(r.outliers.rejected)
        for name in FAULT_CONFIGS:
            clean, faulty = runs[(name, False)], runs[(name, True)]
            for method in ("pnp", "smoothed"):
                c, f = clean[method], faulty[method]
                row = {
                    "clean": c,
                    "faulty": f,
                    "mae_ratio": f["worst_axis_mae_m"] / c["worst_axis_mae_m"],
                    "max_ratio": f["max_error_m"] / c["max_error_m"],
                }
                out.setdefault(str(seed), {}).setdefault(name, {})[method] = row
                share = "/".join(
                    f"{100 * x:.0f}" if x is not None else "-" for x in f["share_2sigma"]
                )
                st = " ".join(f"{k} {100 * v:.0f}%" for k, v in f["status"].items() if v)
                print(
                    f"{seed:>4} {name:<8} {method:<9} {c['worst_axis_mae_m']:9.4f} "
                    f"{f['worst_axis_mae_m']:8.4f} {row['mae_ratio']:6.2f} "
                    f"{c['max_error_m']:9.3f} {f['max_error_m']:7.3f} {row['max_ratio']:6.2f} "
                    f"{c['ok_beyond_4sigma']:>3}/{f['ok_beyond_4sigma']:<3} {share:>18} {st}"
                )
    return out


def _perturbed_survey(sign_map, rng: np.random.Generator):
    """The map a survey of sigma_m would give: each sign's centre moved by N(0, sigma_m)."""
    signs = tuple(
        replace(s, center_m=s.center_m + rng.normal(0.0, s.sigma_m, 3)) for s in sign_map.signs
    )
    return replace(sign_map, signs=signs)


def crb_position(
    frames, sign_map, camera, truth: Trajectory, smoother: SmootherSettings
) -> tuple[np.ndarray, np.ndarray]:
    """Cramér-Rao position covariances, world axes: ((N, 3, 3) per frame, (N, 3, 3) smoother).

    Per frame: the inverse Fisher information of the frame's observed
    keypoints at the true pose with the true noise (pixel and survey). Smoother: the
    full graph (motion prior and survey priors) linearised at the truth.
    """
    meas = collect_measurements(frames, sign_map, camera)
    poses = truth.world_T_cam()
    per_frame = np.full((len(poses), 3, 3), np.nan)
    for i, T in enumerate(poses):
        ids = np.nonzero(meas.frame == i)[0]
        if len(ids) >= 3:
            lm = meas.landmark[ids]
            sign_id = np.unique(np.asarray(meas.landmark_code)[lm], return_inverse=True)[1]
            cov = pose_covariance(
                camera,
                T,
                meas.landmark_world[lm],
                meas.sigma_px[ids],
                meas.landmark_sigma_m[lm],
                sign_id,
            )
            if cov is not None:
                per_frame[i] = position_cov_world(cov, T[:3, :3])
    cov6 = covariances_at(meas, truth.stamps_s, poses, camera, smoother)
    smoothed = np.array(
        [position_cov_world(c, T[:3, :3]) for c, T in zip(cov6, poses, strict=True)]
    )
    return per_frame, smoothed


def _bound_rmse(cov: np.ndarray, mask: np.ndarray) -> float:
    """sqrt(mean trace) of the position covariances where ``mask``: an efficient RMSE."""
    tr = np.trace(cov[mask], axis1=1, axis2=2)
    return float(np.sqrt(np.nanmean(tr)))


def gaussian_section(camera, flights: list[str], n: int, sigma_px: float, seed: int) -> dict:
    """Honest uncertainty and the Cramér-Rao bound on Gaussian flights (no faults).

    Two maps: the demo map with every keypoint, and its centres only. The
    estimator gets the map a survey of sigma_m would give (centres moved by
    N(0, sigma_m)), so the survey prior it uses is the truth's model.
    """
    print(
        "\n## honest uncertainty and the Cramér-Rao bound (Gaussian observations, "
        f"{sigma_px} px, survey error N(0, sigma_m) per sign centre)"
    )
    print(
        f"{'map':<8} {'flight':<19} {'method':<9} {'RMSE':>7} {'CRB':>7} {'ratio':>6} "
        f"{'2sig x/y/z %':>13} {'rms(e/s) x/y/z':>16}"
    )
    demo = load_map(bundled_map_path())
    centre = replace(demo, signs=tuple(replace(s, normal=None, up=None) for s in demo.signs))
    out: dict = {}
    for map_name, truth_map in (("all-kp", demo), ("centre", centre)):
        for k, flight in enumerate(flights):
            rng = np.random.default_rng(seed + 10 * k)
            kp = "all" if map_name == "all-kp" else "center"
            syn = SyntheticSettings(sigma_px=sigma_px, keypoints=kp)
            frames, gt, _ = paper_like_frames(truth_map, camera, n, rng, syn, flight=flight)
            survey = _perturbed_survey(truth_map, rng)
            settings = EstimatorSettings(methods=("pnp", "smoothed"))
            r = estimate_trajectories(frames, survey, camera, settings, progress=False)
            # The bound of the model the estimator used: its chosen motion prior.
            used = r.motion.settings if r.motion is not None else settings.smoother
            crb_pf, crb_sm = crb_position(frames, survey, camera, gt, used)
            for method, crb in (("pnp", crb_pf), ("smoothed", crb_sm)):
                m = r.methods[method]
                num = method_numbers(m, gt)
                mask = m.valid & np.all(np.isfinite(crb.reshape(len(crb), -1)), axis=1)
                err = _errors(m, gt)[mask]
                rmse = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
                bound = _bound_rmse(crb, mask)
                num.update(rmse_on_bound_frames_m=rmse, crb_rmse_m=bound, crb_ratio=rmse / bound)
                out.setdefault(map_name, {}).setdefault(flight, {})[method] = num
                share = "/".join(f"{100 * x:.0f}" for x in num["share_2sigma"])
                rz = "/".join(f"{x:.2f}" for x in num["rms_z"])
                print(
                    f"{map_name:<8} {flight:<19} {method:<9} {rmse:7.4f} {bound:7.4f} "
                    f"{rmse / bound:6.2f} {share:>13} {rz:>16}"
                )
    return out


def gaussian_over_seeds(
    camera, flights: list[str], n: int, sigma_px: float, seeds: list[int]
) -> dict:
    """``gaussian_section`` on each seed, then RMSE / CRB per map, flight and method over them.

    One seed's ratio is one draw of the survey error (ten signs' centres):
    at 210 frames, 0.3 px, the smoothed ratio of one flight spans 0.4-1.6
    over seeds 0-7 (climb-hover-depart, every keypoint), so a single seed
    cannot tell a regression from a draw. ``pooled`` is
    sqrt(sum RMSE^2 / sum CRB^2) over the seeds.
    """
    runs = [gaussian_section(camera, flights, n, sigma_px, seed) for seed in seeds]
    print(f"\n## RMSE / CRB over seeds {','.join(map(str, seeds))}")
    print(
        f"{'map':<8} {'flight':<19} {'method':<9} {'mean':>6} {'pooled':>7} {'min':>6} {'max':>6}"
    )
    summary: dict = {}
    for map_name, per_flight in runs[0].items():
        for flight, per_method in per_flight.items():
            for method in per_method:
                nums = [run[map_name][flight][method] for run in runs]
                ratio = np.array([x["crb_ratio"] for x in nums])
                rmse = np.array([x["rmse_on_bound_frames_m"] for x in nums])
                bound = np.array([x["crb_rmse_m"] for x in nums])
                pooled = float(np.sqrt(np.sum(rmse**2) / np.sum(bound**2)))
                row = {
                    "crb_ratio_mean": float(ratio.mean()),
                    "crb_ratio_pooled": pooled,
                    "crb_ratio_min": float(ratio.min()),
                    "crb_ratio_max": float(ratio.max()),
                    "rmse_mean_m": float(rmse.mean()),
                }
                summary.setdefault(map_name, {}).setdefault(flight, {})[method] = row
                print(
                    f"{map_name:<8} {flight:<19} {method:<9} {ratio.mean():6.2f} {pooled:7.2f} "
                    f"{ratio.min():6.2f} {ratio.max():6.2f}"
                )
    return {"seeds": seeds, "runs": runs, "summary": summary}


def _flight_cases(camera, flights: list[str], n: int, sigma_px: float, seed: int) -> list:
    """(name, frames, estimator's map, truth) per paper-like flight; survey error N(0, sigma_m)."""
    demo = load_map(bundled_map_path())
    cases = []
    for k, flight in enumerate(flights):
        rng = np.random.default_rng(seed + 10 * k)
        syn = SyntheticSettings(sigma_px=sigma_px)
        frames, gt, _ = paper_like_frames(demo, camera, n, rng, syn, flight=flight, seed=k)
        cases.append((flight, frames, _perturbed_survey(demo, rng), gt))
    return cases


def _smoothed_numbers(frames, sign_map, camera, truth, settings: EstimatorSettings) -> dict:
    r = estimate_trajectories(frames, sign_map, camera, settings, progress=False)
    num = method_numbers(r.methods["smoothed"], truth)
    if r.motion is not None:
        num["motion_prior"] = r.motion.to_dict()
    return num


def landmark_section(
    camera, flights: list[str], n: int, sigma_px: float, seed: int, draws: int = 3
) -> dict:
    """Keypoint landmarks vs rigid signs vs the fixed map, survey exact and with error.

    The survey error is drawn ``draws`` times per flight (one draw decides a
    lot: every frame sees the same misplaced signs); means are printed.
    """
    print(
        "\n## landmark models: smoothed position RMSE [m] and share |e| < 2 sigma (all axes), "
        f"{sigma_px} px, mean over {draws} survey draws"
    )
    print(f"{'survey':<9} {'flight':<19} " + " ".join(f"{m:>18}" for m in LANDMARK_MODELS))
    exact = load_map(bundled_map_path())
    out: dict = {}
    for case in _flight_cases(camera, flights, n, sigma_px, seed):
        flight, frames, _, gt = case
        rng = np.random.default_rng(seed + 1000)
        maps = {"exact": [exact], "N(0,sig)": [_perturbed_survey(exact, rng) for _ in range(draws)]}
        for survey, sign_maps in maps.items():
            cells = []
            for model in LANDMARK_MODELS:
                s = EstimatorSettings(
                    methods=("smoothed",), smoother=SmootherSettings(landmarks=model)
                )
                nums = [_smoothed_numbers(frames, m, camera, gt, s) for m in sign_maps]
                rmse = float(np.mean([x["rmse_m"] for x in nums]))
                share = float(np.mean([np.mean(x["share_2sigma"]) for x in nums]))
                out.setdefault(survey, {}).setdefault(flight, {})[model] = {
                    "rmse_m": rmse,
                    "share_2sigma": share,
                    "draws": nums,
                }
                cells.append(f"{rmse:.4f} ({100 * share:3.0f}%)")
            print(f"{survey:<9} {flight:<19} " + " ".join(f"{c:>18}" for c in cells))
    return out


def motion_section(camera, flights: list[str], n: int, sigma_px: float, seed: int) -> dict:
    """The motion prior chosen from the flight against the fixed default, every flight."""
    print("\n## motion prior from the flight vs the fixed default (smoothed position RMSE [m])")
    print(f"{'flight':<19} {'fixed':>8} {'chosen':>8} {'gain':>7} {'cv_sigma_acc':>12}")
    cases = _flight_cases(camera, flights, n, sigma_px, seed)
    for s0 in (0, 1):
        for faults in (False, True):
            sc = build_scenario(np.random.default_rng(s0), faults=faults)
            tag = f"fig8-{s0}{'-faults' if faults else ''}"
            cases.append((tag, sc.frames, sc.sign_map, sc.truth))
    out: dict = {}
    for flight, frames, sign_map, gt in cases:
        fixed = _smoothed_numbers(
            frames,
            sign_map,
            camera,
            gt,
            EstimatorSettings(methods=("smoothed",), tune_motion=False),
        )
        tuned = _smoothed_numbers(
            frames, sign_map, camera, gt, EstimatorSettings(methods=("smoothed",))
        )
        gain = 1.0 - tuned["rmse_m"] / fixed["rmse_m"]
        chosen = tuned["motion_prior"]["position"]
        out[flight] = {"fixed": fixed, "chosen": tuned, "gain": gain}
        print(
            f"{flight:<19} {fixed['rmse_m']:8.4f} {tuned['rmse_m']:8.4f} {100 * gain:6.1f}% "
            f"{chosen:12.3g}"
        )
    return out


def mean_mae(m: Metrics) -> float:
    return float(np.mean(m.mae_xyz_m))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one flight, fewer frames")
    ap.add_argument("--json", help="write all numbers to this JSON file")
    ap.add_argument("--frames", type=int, default=210, help="frames per flight (paper: 210)")
    ap.add_argument("--sigma-px", type=float, default=0.13, help="keypoint noise [px]")
    ap.add_argument("--hfov", type=float, default=60.0, help="horizontal field of view [deg]")
    ap.add_argument("--fps", type=float, default=30.0, help="not used; flights are 30 fps")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--sections",
        default="table4,faults,gaussian,landmarks,motion",
        help="comma-separated: table4 (Table 4, motion priors, planarity), faults "
        "(issue 12's fault scenario), gaussian (2-sigma shares and Cramér-Rao bound), "
        "landmarks (keypoints / rigid / fixed), motion (prior from the flight vs fixed)",
    )
    ap.add_argument("--fault-seeds", default="0,1,2", help="seeds of the fault scenario")
    ap.add_argument(
        "--gaussian-seeds",
        default="",
        help="seeds of the gaussian section (comma-separated; each seed's table, then "
        "RMSE / CRB over them); default: --seed only",
    )
    args = ap.parse_args(argv)
    sections = set(args.sections.split(","))
    t_start = time.perf_counter()
    camera = pinhole_camera(1920, 1080, args.hfov)
    demo = load_map(bundled_map_path())
    maps = {"planar": flatten_map(demo), "demo": demo}
    flights = ["climb-hover-depart"] if args.quick else ["climb-hover-depart", "orbit", "lawnmower"]
    n = 120 if args.quick else args.frames
    default_motion = SmootherSettings().motion
    results: dict = {"settings": vars(args), "scenarios": {}}
    print(
        f"# {n} frames/flight at 30 fps, 1920x1080, hfov {args.hfov} deg, "
        f"noise {args.sigma_px} px, flights: {', '.join(flights)}; "
        f"smoother motion: {default_motion}"
    )
    if "table4" in sections:
        summary: dict[str, dict[str, dict[str, float]]] = {}
        for map_name, sign_map in maps.items():
            for fault in FAULTS:
                per_flight = []
                for k, flight in enumerate(flights):
                    m, extra = run_scenario(
                        sign_map,
                        camera,
                        flight,
                        n,
                        fault,
                        args.sigma_px,
                        args.seed + k,
                        default_motion,
                    )
                    per_flight.append((flight, m, extra))
                    results["scenarios"][f"{map_name}/{fault}/{flight}"] = {
                        "metrics": {name: x.to_dict() for name, x in m.items()},
                        **extra,
                    }
                print(f"\n## map={map_name} {fault}")
                for flight, m, extra in per_flight:
                    print(
                        f"-- {flight}  (iSAM2 final vs batch max "
                        f"{extra['isam2_vs_batch_max_m'] * 1e3:.3f} mm,"
                        f" iSAM2 median {extra['isam2_median_ms']:.1f} ms/frame)"
                    )
                    print(format_table(m))
                names = per_flight[0][1].keys()
                summary.setdefault(map_name, {})[fault] = {
                    name: float(np.mean([mean_mae(m[name]) for _, m, _ in per_flight]))
                    for name in names
                }
                summary[map_name].setdefault("coverage_" + fault, {})
                summary[map_name]["coverage_" + fault] = {
                    name: float(np.mean([m[name].coverage for _, m, _ in per_flight]))
                    for name in names
                }
        print("\n## mean per-axis MAE over flights [m] (mean of x, y, z), and growth with faults")
        print(f"{'map':<8} {'method':<9} {'clean':>8} {'faults':>8} {'growth':>8}")
        for map_name, s in summary.items():
            for name in s["clean"]:
                c, f = s["clean"][name], s["faults"][name]
                print(f"{map_name:<8} {name:<9} {c:8.4f} {f:8.4f} {100 * (f / c - 1):7.1f}%")
        results["summary"] = summary

        # Motion priors: both on every flight of the non-planar demo map, clean and with faults.
        print("\n## motion prior: smoothed (batch) mean per-axis MAE [m]")
        motions = ("random-walk", "constant-velocity")
        mres: dict[str, list[float]] = {mo: [] for mo in motions}
        for fault in FAULTS:
            for k, flight in enumerate(flights):
                m, _ = run_scenario(
                    demo, camera, flight, n, fault, args.sigma_px, 100 + k, motions, isam=False
                )
                for mo in motions:
                    mres[mo].append(mean_mae(m[f"smoothed[{mo}]"]))
                print(
                    f"{fault:<7} {flight:<20} "
                    + "  ".join(f"{mo}: {mean_mae(m[f'smoothed[{mo}]']):.4f}" for mo in motions)
                )
        rw, cv = np.mean(mres["random-walk"]), np.mean(mres["constant-velocity"])
        winner = "constant-velocity" if cv < rw else "random-walk"
        print(
            f"mean: random-walk {rw:.4f}  constant-velocity {cv:.4f}  -> {winner} "
            f"lower by {100 * abs(rw - cv) / max(rw, cv):.1f}%"
        )
        results["motion"] = {"random-walk": rw, "constant-velocity": cv, "winner": winner}

        # Planarity sweep of the paper's method: signs pushed off their plane by up to +-d.
        print(
            "\n## planarity sweep: baseline (paper) vs pnp, mean per-axis MAE [m], "
            "climb-hover-depart"
        )
        print(f"{'offset_m':>8} {'base 0px':>9} {'base':>8} {'pnp':>8} {'base cov':>9}")
        sweep = []
        flat = flatten_map(demo)
        offsets = (
            [0.0, 0.01, 0.02, 0.05, 0.1, 0.2, 0.3] if not args.quick else [0.0, 0.02, 0.1, 0.3]
        )
        for d in offsets:
            rng = np.random.default_rng(7)
            sm_map = flatten_map(flat, d, rng) if d > 0 else flat
            row = {"offset_m": d}
            for sigma, tag in ((0.0, "exact"), (args.sigma_px, "noisy")):
                m, _ = run_scenario(
                    sm_map,
                    camera,
                    "climb-hover-depart",
                    n,
                    "clean",
                    sigma,
                    3,
                    default_motion,
                    isam=False,
                )
                row[f"baseline_{tag}"] = mean_mae(m["baseline"])
                row[f"pnp_{tag}"] = mean_mae(m["pnp"])
                row[f"baseline_cov_{tag}"] = m["baseline"].coverage
            sweep.append(row)
            print(
                f"{d:8.3f} {row['baseline_exact']:9.4f} {row['baseline_noisy']:8.4f} "
                f"{row['pnp_noisy']:8.4f} {row['baseline_cov_noisy']:9.1%}"
            )
        results["planarity_sweep"] = sweep
    if "faults" in sections:
        seeds = [int(x) for x in args.fault_seeds.split(",")]
        results["fault_scenario"] = fault_section(seeds)
    if "gaussian" in sections:
        if args.gaussian_seeds:
            seeds = [int(x) for x in args.gaussian_seeds.split(",")]
            results["gaussian"] = gaussian_over_seeds(camera, flights, n, 0.3, seeds)
        else:
            results["gaussian"] = gaussian_section(camera, flights, n, 0.3, args.seed)
    if "landmarks" in sections:
        results["landmarks"] = landmark_section(camera, flights, n, 0.3, args.seed)
    if "motion" in sections:
        results["motion_prior"] = motion_section(camera, flights, n, 0.3, args.seed)
    print(f"\n# total {time.perf_counter() - t_start:.0f} s")
    if args.json:
        with atomic_write(args.json, encoding="utf-8") as f:
            json.dump(results, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
