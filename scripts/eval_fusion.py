"""GNSS/IMU fusion on simulated flights (issue 17): every Number with pass/fail.

Flights: ``signpose.sim.telemetry.away_and_back`` in front of the bundled
10-sign map (anchored at an arbitrary WGS84 origin): the UAV looks at the signs,
turns 110 deg away and flies along the line for about 12 s with no sign in
view, comes back. Observations are synthesised (map keypoints projected with
0.4 px noise, 1920x1080 60 deg camera, ``sim.observations``); telemetry by
``sim.telemetry``: GNSS 10 Hz, 1.2 m / 1.8 m white noise, Gauss-Markov drift
(0.8 / 1.2 m, 60 s), multipath bursts of 5-20 m for 1-3 s near the
conductors; a 200 Hz MEMS IMU with noise and bias random walks; a clock offset.

Methods on the same flights: vision only (the smoother: the constant-velocity
prior bridges the sign-free stretch), GNSS only (the fixes interpolated at the
frame times, lever arm removed with the true attitude), vision+GNSS,
vision+GNSS+IMU (``estimator.fusion``), each in the frames with signs and in
the longest stretch without; vision+GNSS+IMU also on the same flight without
multipath bursts.

Without an IMU: vision+GNSS with the clock left to the GNSS (refused by the
fusion: a guessed clock is not fused), and with the clock given, with and
without bursts; per case and region the share of poses beyond 3 of their own
sigmas (all, and among ok/weak poses: bridged ones say they are a bridge).

Numbers: sign-free stretch error (<= 0.3 m RMS); with signs, fused vs vision
(within 5 %); multipath rejected and the error in bursts vs burst-free (<=
1.5x); clock offset error (<= 5 ms for offsets up to 1 s); WGS84 sign centres
triangulated from the fused poses vs the map's own (<= 2 cm horizontal).

    .venv/bin/python scripts/eval_fusion.py [--seeds 3] [--quick] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace

import numpy as np
from signpose.estimator.camera import pinhole_camera, undistort_px
from signpose.estimator.fusion import (
    FusionSettings,
    estimate_clock_offset,
    fuse_trajectory,
    vision_solve,
)
from signpose.estimator.smoother import collect_measurements
from signpose.maps.geodesy import GeoOrigin, enu_from_geodetic, geodetic_from_enu
from signpose.maps.loader import bundled_map_path, load_map

from signpose.core.fileio import atomic_write
from signpose.sim.observations import SyntheticSettings, synthesize_observations
from signpose.sim.telemetry import (
    SIM_ORIGIN,
    TelemetrySimSettings,
    away_and_back,
    default_body_T_cam,
    simulate_telemetry,
)

ORIGIN = SIM_ORIGIN  # the simulator's anchor for maps without an origin


def rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.asarray(x) ** 2))) if len(x) else float("nan")


def longest_run(mask: np.ndarray) -> np.ndarray:
    """Indices of the longest run of True in ``mask``."""
    best, start = (0, 0), None
    for i, m in enumerate(np.append(mask, False)):
        if m and start is None:
            start = i
        elif not m and start is not None:
            if i - start > best[1] - best[0]:
                best = (start, i)
            start = None
    return np.arange(*best)


def gnss_only(tel, truth_T: np.ndarray, stamps: np.ndarray, offset: float, arm) -> np.ndarray:
    """(N, 3) camera positions from the fixes alone, interpolated at the frame times."""
    g = tel.gnss
    z = enu_from_geodetic(ORIGIN, g.lat_deg, g.lon_deg, g.height_m)
    tv = np.asarray(g.t_s) - offset
    ant = np.stack([np.interp(stamps, tv, z[:, a]) for a in range(3)], axis=1)
    return ant - np.einsum("nij,j->ni", truth_T[:, :3, :3], np.asarray(arm, float))


def triangulate_centres(frames, sign_map, camera, poses: np.ndarray) -> dict[str, np.ndarray]:
    """Each sign's centre [m] from the rays of all its observed keypoints at ``poses``.

    Keypoint k of a sign is taken at centre + (its map offset from the centre):
    the sign's shape and orientation from the map, its position from the rays
    only (not the survey's centre).
    """
    Kinv = np.linalg.inv(camera.K)
    A: dict[str, np.ndarray] = {}
    b: dict[str, np.ndarray] = {}
    for i, f in enumerate(frames):
        for o in f.signs:
            sign = sign_map.sign(o.code)
            kps = sign.keypoints_world()
            names = [n for n in o.keypoints_px if n in kps]
            uv = undistort_px(camera, np.array([o.keypoints_px[n] for n in names], float))
            for n, (u, v) in zip(names, uv, strict=True):
                d = poses[i, :3, :3] @ (Kinv @ np.array([u, v, 1.0]))
                d /= np.linalg.norm(d)
                P = np.eye(3) - np.outer(d, d)
                offset = kps[n] - sign.center_m
                A[o.code] = A.get(o.code, np.zeros((3, 3))) + P
                b[o.code] = b.get(o.code, np.zeros(3)) + P @ (poses[i, :3, 3] - offset)
    return {code: np.linalg.solve(A[code], b[code]) for code in A}


def graph_centres(fused, frames, sign_map, camera) -> dict[str, np.ndarray]:
    """The fused graph's own estimate of each sign's centre (its 'center' landmark) [m]."""
    meas = collect_measurements(frames, sign_map, camera)
    return {
        code: fused.landmarks_world[j]
        for j, (code, name) in enumerate(zip(meas.landmark_code, meas.landmark_name, strict=True))
        if name == "center"
    }


def georef_errors_m(centres: dict[str, np.ndarray], sign_map) -> np.ndarray:
    """Horizontal distance [m] between each triangulated centre and the map's own, in WGS84."""
    codes = sorted(centres)
    lat, lon, h = geodetic_from_enu(ORIGIN, np.array([centres[c] for c in codes]))
    ref = np.array([sign_map.sign(c).center_m for c in codes])
    rlat, rlon, rh = geodetic_from_enu(ORIGIN, ref)
    out = []
    for k in range(len(codes)):
        local = GeoOrigin(float(rlat[k]), float(rlon[k]), float(rh[k]))
        enu = enu_from_geodetic(local, lat[k], lon[k], h[k])[0]
        out.append(float(np.hypot(enu[0], enu[1])))
    return np.array(out)


def run_flight(seed: int, fps: float, offset: float) -> dict:
    """Every method on one flight; errors per region."""
    sign_map = replace(load_map(bundled_map_path()), origin=ORIGIN)
    camera = pinhole_camera(1920, 1080, 60.0)
    flight = away_and_back(sign_map, seed=seed)
    gt = flight.trajectory(fps)
    truth_T = gt.world_T_cam()
    rng = np.random.default_rng(1000 + seed)
    frames, _ = synthesize_observations(sign_map, camera, gt, rng, SyntheticSettings())
    sim = TelemetrySimSettings(clock_offset_s=offset)
    tel, truth = simulate_telemetry(flight, sign_map, np.random.default_rng(2000 + seed), sim)
    tel_clean, _ = simulate_telemetry(
        flight, sign_map, np.random.default_rng(2000 + seed), replace(sim, multipath=False)
    )
    stamps = gt.stamps_s
    fs = FusionSettings(
        cam_t_antenna_m=sim.cam_t_antenna_m,
        body_T_cam=tuple(map(tuple, default_body_T_cam())),
    )
    t0 = time.perf_counter()
    vision = vision_solve(frames, sign_map, camera, stamps, fs.smoother)
    seen = vision.observed
    gap = longest_run(~seen)

    def err(P: np.ndarray) -> np.ndarray:
        return np.linalg.norm(P[:, :3] - truth_T[:, :3, 3], axis=1)

    runs = {
        "vision": vision.world_T_cam[:, :3, 3],
        "gnss": gnss_only(tel, truth_T, stamps, offset, sim.cam_t_antenna_m),
        "gnss burst-free": gnss_only(tel_clean, truth_T, stamps, offset, sim.cam_t_antenna_m),
    }
    fused = {}
    no_imu = replace(fs, use_imu=False, clock_offset_s=offset)
    cases = [
        ("vision+gnss", replace(fs, use_imu=False), tel),  # clock left to the GNSS: refused
        ("vision+gnss clock given", no_imu, tel),
        ("vision+gnss clock given burst-free", no_imu, tel_clean),
        ("vision+gnss+imu", fs, tel),
    ]
    cases.append(("vision+gnss+imu burst-free", fs, tel_clean))
    for name, settings, telemetry in cases:
        fused[name] = fuse_trajectory(
            frames, sign_map, camera, stamps, telemetry, settings, vision_result=vision
        )
        runs[name] = fused[name].world_T_cam[:, :3, 3]
    errors = {k: err(v) for k, v in runs.items()}
    honesty = {k: sigma_honesty(errors[k], r, seen) for k, r in fused.items() if not r.refused}
    full = fused["vision+gnss+imu"]
    # Frames whose nearest fix is in a burst.
    tv = truth.gnss_t_s - offset
    nearest = np.abs(stamps[:, None] - tv[None, :]).argmin(axis=1)
    in_burst = truth.burst[nearest]
    burst_used = truth.burst[full.gnss_used]
    centres = triangulate_centres(frames, sign_map, camera, full.world_T_cam)
    in_graph = graph_centres(full, frames, sign_map, camera)
    return {
        "seed": seed,
        "frames": len(stamps),
        "gap_s": float(len(gap) / fps),
        "seconds": time.perf_counter() - t0,
        "rms_seen_m": {k: rms(e[seen]) for k, e in errors.items()},
        "rms_gap_m": {k: rms(e[gap]) for k, e in errors.items()},
        "gap_sigma_median_m": float(np.median(np.linalg.norm(full.sigma_xyz[gap], axis=1))),
        "gap_within_3_sigma": float(
            np.mean(
                errors["vision+gnss+imu"][gap] <= 3 * np.linalg.norm(full.sigma_xyz[gap], axis=1)
            )
        ),
        "burst_frames": int(in_burst.sum()),
        "rms_burst_m": rms(errors["vision+gnss+imu"][in_burst]),
        "rms_burst_free_same_frames_m": rms(errors["vision+gnss+imu burst-free"][in_burst]),
        "burst_fixes": int(burst_used.sum()),
        "burst_fixes_rejected": int((full.gnss_outlier & burst_used).sum()),
        "clean_fixes_rejected": int((full.gnss_outlier & ~burst_used).sum()),
        "clean_fixes": int((~burst_used).sum()),
        "clock": {"true_s": offset, "est_s": full.clock.offset_s, "sigma_s": full.clock.sigma_s},
        "clock_by_method": {
            k: {"est_s": r.clock.offset_s, "sigma_s": r.clock.sigma_s, "source": r.clock.source}
            for k, r in fused.items()
        },
        "fused_seconds": {k: r.seconds for k, r in fused.items()},
        "georef_graph_h_m": georef_errors_m(in_graph, sign_map).tolist(),
        "georef_triangulated_h_m": georef_errors_m(centres, sign_map).tolist(),
        "statuses": {
            st: sum(1 for x in full.status if x.value == st) for st in ("ok", "weak", "bridged")
        },
        "refused": {k: r.refused for k, r in fused.items()},
        "no_imu_burst_fixes_rejected": int(
            (fused[NO_IMU[0]].gnss_outlier & truth.burst[fused[NO_IMU[0]].gnss_used]).sum()
        ),
        "no_imu_burst_fixes": int(truth.burst[fused[NO_IMU[0]].gnss_used].sum()),
        "no_imu_clean_fixes": int((~truth.burst[fused[NO_IMU[0]].gnss_used]).sum()),
        "no_imu_clean_fixes_rejected": int(
            (fused[NO_IMU[0]].gnss_outlier & ~truth.burst[fused[NO_IMU[0]].gnss_used]).sum()
        ),
        "notes": {k: list(r.notes) for k, r in fused.items() if r.notes},
        "honesty": honesty,
    }


def sigma_honesty(error: np.ndarray, fused, seen: np.ndarray) -> dict:
    """Per region, the share of poses whose error exceeds 3 of their own sigmas (the
    norm of the marginal's x, y, z sigmas), and that share among ok/weak poses only
    (bridged ones say they are a bridge); the statuses per region."""
    sig = np.linalg.norm(fused.sigma_xyz, axis=1)
    beyond = ~(error <= 3 * sig)  # a NaN sigma counts as beyond
    flagged = np.array([st.value in ("ok", "weak") for st in fused.status])
    out = {}
    for region, mask in (("seen", seen), ("gap", ~seen), ("all", np.ones_like(seen))):
        ow = mask & flagged
        out[region] = {
            "beyond_3_sigma": float(np.mean(beyond[mask])) if mask.any() else 0.0,
            "ok_weak": int(ow.sum()),
            "ok_weak_beyond_3_sigma": float(np.mean(beyond[ow])) if ow.any() else 0.0,
            "statuses": {
                st: int(sum(1 for i in np.nonzero(mask)[0] if fused.status[i].value == st))
                for st in ("ok", "weak", "bridged", "suspect")
            },
            "sigma_median_m": float(np.median(sig[mask])) if mask.any() else float("nan"),
        }
    return out


def clock_sweep(seed: int, fps: float, offsets: list[float]) -> list[dict]:
    """The clock offset estimated from the gyro against the vision rotations, per offset."""
    sign_map = replace(load_map(bundled_map_path()), origin=ORIGIN)
    camera = pinhole_camera(1920, 1080, 60.0)
    flight = away_and_back(sign_map, seed=seed)
    gt = flight.trajectory(fps)
    frames, _ = synthesize_observations(
        sign_map, camera, gt, np.random.default_rng(3000 + seed), SyntheticSettings()
    )
    fs = FusionSettings(body_T_cam=tuple(map(tuple, default_body_T_cam())))
    vision = vision_solve(frames, sign_map, camera, gt.stamps_s, fs.smoother)
    out = []
    for k, off in enumerate(offsets):
        sim = TelemetrySimSettings(clock_offset_s=off)
        rng = np.random.default_rng(4000 + 100 * seed + k)
        tel, _ = simulate_telemetry(flight, sign_map, rng, sim)
        c = estimate_clock_offset(
            vision.world_T_cam, gt.stamps_s, vision.observed, tel, sign_map, fs
        )
        out.append({"seed": seed, "true_s": off, "est_s": c.offset_s, "sigma_s": c.sigma_s})
    return out


NO_IMU = ("vision+gnss clock given", "vision+gnss clock given burst-free")


def no_imu_numbers(flights: list[dict]) -> list[dict]:
    """Vision+GNSS without an IMU: GNSS does not pull the seen poses, honest statuses."""
    ratio = [f["rms_seen_m"][c] / f["rms_seen_m"]["vision"] for f in flights for c in NO_IMU]
    ok_weak = [
        f["honesty"][c][region]["ok_weak_beyond_3_sigma"]
        for f in flights
        for c in NO_IMU
        for region in ("seen", "gap")
    ]
    gap_ok = sum(f["honesty"][c]["gap"]["statuses"]["ok"] for f in flights for c in NO_IMU)

    def bridged(case: str) -> float:
        return max(f["honesty"][case]["gap"]["beyond_3_sigma"] for f in flights)

    refused = sum(f["refused"]["vision+gnss"] for f in flights)
    burst_out = sum(f["no_imu_burst_fixes_rejected"] for f in flights)
    bursts = sum(f["no_imu_burst_fixes"] for f in flights)
    clean_out = sum(f["no_imu_clean_fixes_rejected"] for f in flights)
    clean = sum(f["no_imu_clean_fixes"] for f in flights)
    return [
        {
            "number": "no IMU, clock given, with signs: fused RMS / vision-only RMS, worst",
            "value": max(ratio),
            "limit": 1.05,
            "pass": max(ratio) <= 1.05,
            "beside": {"GNSS-only clock refused": f"{refused}/{len(flights)} flights"},
        },
        {
            "number": "no IMU: share of ok/weak fused poses beyond 3 own sigmas, worst",
            "value": max(ok_weak),
            "limit": 0.01,
            "pass": max(ok_weak) <= 0.01 and gap_ok == 0,
            "beside": {
                "'ok' poses in sign-free stretches": gap_ok,
                "bridged poses beyond 3 sigma, worst flight, with bursts": round(
                    bridged(NO_IMU[0]), 3
                ),
                "burst-free": round(bridged(NO_IMU[1]), 3),
                "burst fixes rejected (no IMU)": f"{burst_out}/{bursts}",
                "clean fixes rejected (no IMU)": f"{clean_out}/{clean}",
            },
        },
    ]


def summarise(flights: list[dict], clocks: list[dict]) -> list[dict]:
    """The issue's Numbers with pass/fail (worst flight for each)."""
    gap_fused = [f["rms_gap_m"]["vision+gnss+imu"] for f in flights]
    gap_cv = [f["rms_gap_m"]["vision"] for f in flights]
    ratio_seen = [f["rms_seen_m"]["vision+gnss+imu"] / f["rms_seen_m"]["vision"] for f in flights]
    burst_ratio = [
        f["rms_burst_m"] / f["rms_burst_free_same_frames_m"] for f in flights if f["burst_frames"]
    ]
    rejected = sum(f["burst_fixes_rejected"] for f in flights)
    clean_out = sum(f["clean_fixes_rejected"] for f in flights)
    clean = sum(f["clean_fixes"] for f in flights)
    bursts = sum(f["burst_fixes"] for f in flights)
    clock_err = [abs(c["est_s"] - c["true_s"]) for c in clocks]
    geo = [g for f in flights for g in f["georef_graph_h_m"]]
    tri = [g for f in flights for g in f["georef_triangulated_h_m"]]
    return [
        *no_imu_numbers(flights),
        {
            "number": "sign-free stretch, fused (GNSS+IMU) RMS [m], worst flight",
            "value": max(gap_fused),
            "limit": 0.3,
            "pass": max(gap_fused) <= 0.3,
            "beside": {
                "median flight": round(float(np.median(gap_fused)), 4),
                "constant-velocity bridge RMS [m], best flight": round(min(gap_cv), 3),
            },
        },
        {
            "number": "with signs: fused RMS / vision-only RMS, worst flight",
            "value": max(ratio_seen),
            "limit": 1.05,
            "pass": max(ratio_seen) <= 1.05,
            "beside": {"median flight": round(float(np.median(ratio_seen)), 4)},
        },
        {
            "number": "multipath: fused RMS in bursts / same frames burst-free, worst flight",
            "value": max(burst_ratio) if burst_ratio else float("nan"),
            "limit": 1.5,
            "pass": bool(burst_ratio) and max(burst_ratio) <= 1.5,
            "beside": {
                "burst fixes rejected": f"{rejected}/{bursts}",
                "clean fixes rejected": f"{clean_out}/{clean}",
            },
        },
        {
            "number": "clock offset error [ms], worst of offsets up to 1 s",
            "value": 1e3 * max(clock_err),
            "limit": 5.0,
            "pass": max(clock_err) <= 5e-3,
            "beside": {"median [ms]": round(1e3 * float(np.median(clock_err)), 3)},
        },
        {
            "number": "WGS84 sign centres of the fused result vs the map's, horizontal [m], worst",
            "value": max(geo),
            "limit": 0.02,
            "pass": max(geo) <= 0.02,
            "beside": {
                "triangulated from the fused poses, worst sign [m]": round(max(tri), 4),
                "median [m]": round(float(np.median(tri)), 4),
            },
        },
    ]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3, help="flights (seeds 0..N-1)")
    ap.add_argument("--fps", type=float, default=10.0, help="camera frame rate [Hz]")
    ap.add_argument(
        "--offsets",
        default="-1.0,-0.5,0.0,0.137,0.5,1.0",
        help="clock offsets for the sweep [s], comma-separated",
    )
    ap.add_argument("--quick", action="store_true", help="one flight, three offsets")
    ap.add_argument("--json", help="write all numbers to this JSON file")
    args = ap.parse_args(argv)
    seeds = 1 if args.quick else args.seeds
    offsets = [float(x) for x in args.offsets.split(",")]
    if args.quick:
        offsets = offsets[:: max(1, len(offsets) // 3)][:3]
    flights = []
    for k in range(seeds):
        off = offsets[k % len(offsets)]
        flights.append(run_flight(k, args.fps, off))
        f = flights[-1]
        print(
            f"flight {k}: {f['frames']} frames, {f['gap_s']:.1f} s without signs, "
            f"{f['seconds']:.0f} s to solve; clock {f['clock']['est_s']:+.4f} s "
            f"(true {off:+.3f}, sigma {1e3 * f['clock']['sigma_s']:.1f} ms); sign-free: fused "
            f"sigma median {f['gap_sigma_median_m']:.3f} m, error <= 3 sigma in "
            f"{100 * f['gap_within_3_sigma']:.0f} % of frames"
        )
        for region in ("seen", "gap"):
            vals = ", ".join(f"{m} {v:.3f}" for m, v in f[f"rms_{region}_m"].items())
            print(f"  RMS {'with signs' if region == 'seen' else 'sign-free'} [m]: {vals}")
        for name, h in f["honesty"].items():
            parts = [
                f"{region} {100 * h[region]['beyond_3_sigma']:.1f} % beyond 3 sigma "
                f"(ok/weak {100 * h[region]['ok_weak_beyond_3_sigma']:.1f} % of "
                f"{h[region]['ok_weak']}; sigma median {h[region]['sigma_median_m']:.2f} m)"
                for region in ("seen", "gap")
            ]
            print(f"  {name}: {'; '.join(parts)}")
        for name, notes in f["notes"].items():
            print(f"  {name}: {' '.join(notes)}")
    clocks = [c for k in range(seeds) for c in clock_sweep(k, args.fps, offsets)]
    for c in clocks:
        err_ms = 1e3 * (c["est_s"] - c["true_s"])
        print(
            f"clock seed {c['seed']}: true {c['true_s']:+.3f} s, "
            f"est {c['est_s']:+.4f} s, error {err_ms:+.2f} ms, sigma {1e3 * c['sigma_s']:.2f} ms"
        )
    numbers = summarise(flights, clocks)
    ok = True
    for n in numbers:
        ok &= bool(n["pass"])
        beside = "".join(f"; {k}: {v}" for k, v in n.get("beside", {}).items())
        print(
            f"{'PASS' if n['pass'] else 'FAIL'}  {n['number']}: {n['value']:.4g} "
            f"(limit {n['limit']}){beside}"
        )
    if args.json:
        with atomic_write(args.json) as f:
            json.dump(
                {"args": vars(args), "flights": flights, "clock": clocks, "numbers": numbers},
                f,
                indent=2,
            )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
