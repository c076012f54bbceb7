"""Telemetry in, WGS84 out: what goes in comes out, garbled samples are counted (issue 17, TEL).

Usage:
    .venv/bin/python scripts/eval_telemetry_io.py [--minutes 10] [--garbled 0.05]
        [--repeat 3] [--json FILE]

1. Readers. A flight of ``--minutes`` is written here in each format
   ``signpose.io.telemetry.read_telemetry`` takes: DJI SRT in the current and
   the older layout (one subtitle per frame at 30 fps, gimbal angles in the
   current one), the telemetry CSV (GNSS 10 Hz + IMU 200 Hz) and a rosbag2 bag
   (MCAP storage, NavSatFix 10 Hz + Imu 200 Hz, written with the ``rosbags``
   writer). ``--garbled`` of the SRT subtitles are damaged in four ways (a
   letter in the latitude, the longitude missing, a (0, 0) fix, a ``nan``).
   For each file: fixes and samples read against those written, garbled
   subtitles counted against those damaged, NaN in what was read, the largest
   position difference read - written [m], and the speed as flight seconds
   read per second of reading (min / median over ``--repeat`` reads).
2. Georeferenced outputs. A trajectory of 2000 poses in the map's ENU frame
   (sigmas, statuses) goes through ``geo_out.write_run_geo`` and
   ``mcap_write.write_result_mcap``; each file (trajectory_wgs84.csv,
   trajectory.geojson, trajectory.kml, LocationFix in result.mcap) is read
   back, converted to ENU with ``maps.geodesy``, and the largest distance from
   the trajectory is printed [mm].

3. ``--run``: end to end through ``signpose run --telemetry``. A rendered
   flight (``--run-frames`` at 1280x720, 3 m/s, the bundled map anchored at an
   origin) and its GNSS made here from the true camera centres (10 Hz, 1.5 m
   horizontal / 3 m vertical white noise, one 12 m multipath burst of 1 s,
   the telemetry clock 0.25 s ahead of the video's) go through
   ``pipeline.run`` with the real detector, the offset given as
   ``--telemetry-offset`` does (``--estimate-clock``: left to the fusion);
   ``trajectory_wgs84.csv`` is compared with the truth converted to WGS84:
   horizontal RMS / max error [m] of the fused track, beside the smoothed one
   (its TUM converted the same way) and the raw fixes, and the clock offset found.

Deterministic (seeded); about a minute for 10 minutes of flight, plus about
two minutes with ``--run``.
"""

from __future__ import annotations

import argparse
import csv
import json
import statistics
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from signpose.estimator.estimate import MethodEstimate
from signpose.estimator.status import PoseStatus
from signpose.frontend.observations import FrameObservations
from signpose.maps.geodesy import GeoOrigin, enu_from_geodetic, geodetic_from_enu
from signpose.maps.loader import SignMap, bundled_map_path, load_map

from signpose import pipeline
from signpose.core.fileio import atomic_write
from signpose.io import mcap as mcap_io
from signpose.io.geo_out import method_track, run_geo, write_run_geo
from signpose.io.mcap_write import write_result_mcap
from signpose.io.telemetry import TelemetryRequest, read_telemetry
from signpose.io.tum import read_tum
from signpose.sim.flight import SimSettings, simulate

ORIGIN = GeoOrigin(46.95, 7.44, 560.0)
SRT_FPS = 30.0
GNSS_HZ = 10.0
IMU_HZ = 200.0
T0_S = 1_780_000_000.0
STORE = get_typestore(Stores.ROS2_HUMBLE)


def flight_enu(t_s: np.ndarray) -> np.ndarray:
    """(N, 3) a slow lawnmower over a few hundred metres, 20-40 m up [m]."""
    return np.stack(
        [
            150.0 * np.sin(2 * np.pi * t_s / 300.0),
            2.0 * t_s - 300.0 * np.floor(t_s / 300.0),
            30.0 + 10.0 * np.sin(2 * np.pi * t_s / 120.0),
        ],
        axis=1,
    )


def _tc(t: float) -> str:
    ms = int(round(t * 1000))
    h, ms = divmod(ms, 3_600_000)
    m, ms = divmod(ms, 60_000)
    s, ms = divmod(ms, 1000)
    return f"{h:02d}:{m:02d}:{s:02d},{ms:03d}"


def write_srt(path: Path, minutes: float, garbled: float, older: bool, seed: int) -> dict:
    """An SRT of ``minutes`` at 30 fps; returns what was written and what was damaged."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, minutes * 60.0, 1.0 / SRT_FPS)
    lat, lon, h = geodetic_from_enu(ORIGIN, flight_enu(t))
    damage = rng.random(len(t)) < garbled
    kinds = rng.integers(0, 4, len(t))
    parts, good = [], []
    for i in range(len(t)):
        la, lo = f"{lat[i]:.7f}", f"{lon[i]:.7f}"
        lon_field = f"[longtitude : {lo}]" if older else f"[longitude: {lo}]"
        if damage[i]:
            if kinds[i] == 0:
                la = la[:4] + "x" + la[5:]
            elif kinds[i] == 1:
                lon_field = ""
            elif kinds[i] == 2:
                la, lo = "0.000000", "0.000000"
                lon_field = f"[longtitude : {lo}]" if older else f"[longitude: {lo}]"
            else:
                la = "nan"
        else:
            good.append(i)
        if older:
            fields = (
                f"[iso : 100] [shutter : 1/500.0] [fnum : 280] [latitude : {la}] {lon_field} "
                f"[altitude: {h[i]:.6f}]"
            )
        else:
            fields = (
                f"[iso: 100] [shutter: 1/500.0] [fnum: 2.8] [latitude: {la}] {lon_field} "
                f"[rel_alt: {h[i] - 560.0:.3f} abs_alt: {h[i]:.3f}] "
                f"[gb_yaw: {(i * 0.01) % 360:.1f} gb_pitch: -30.0 gb_roll: 0.0]"
            )
        parts.append(
            f"{i + 1}\n{_tc(t[i])} --> {_tc(t[i] + 1 / SRT_FPS)}\n"
            f'<font size="28">FrameCnt: {i + 1}, DiffTime: 33ms\n{fields}</font>\n'
        )
    path.write_text("\n".join(parts))
    g = np.array(good)
    return {"t_s": t[g], "enu": flight_enu(t[g]), "damaged": int(damage.sum()), "written": len(t)}


def _imu_rows(t: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
    gyro = rng.normal(0.0, 0.01, (len(t), 3))
    accel = rng.normal(0.0, 0.05, (len(t), 3)) + [0.0, 0.0, 9.81]
    return gyro, accel


def write_csv(path: Path, minutes: float, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    tg = np.arange(0.0, minutes * 60.0, 1.0 / GNSS_HZ) + T0_S
    ti = np.arange(0.0, minutes * 60.0, 1.0 / IMU_HZ) + T0_S
    lat, lon, h = geodetic_from_enu(ORIGIN, flight_enu(tg - T0_S))
    gyro, accel = _imu_rows(ti, rng)
    rows = [(t, 0, k) for k, t in enumerate(tg)] + [(t, 1, k) for k, t in enumerate(ti)]
    rows.sort()
    lines = [
        "t_s,lat_deg,lon_deg,height_m,sigma_h_m,sigma_v_m,gyro_x_rad_s,gyro_y_rad_s,"
        "gyro_z_rad_s,accel_x_m_s2,accel_y_m_s2,accel_z_m_s2"
    ]
    for t, kind, k in rows:
        if kind == 0:
            lines.append(f"{t:.6f},{lat[k]:.9f},{lon[k]:.9f},{h[k]:.4f},1.5,3.0,,,,,,")
        else:
            g, a = gyro[k], accel[k]
            lines.append(
                f"{t:.6f},,,,,,{g[0]:.6f},{g[1]:.6f},{g[2]:.6f},{a[0]:.5f},{a[1]:.5f},{a[2]:.5f}"
            )
    path.write_text("\n".join(lines) + "\n")
    return {"t_s": tg, "enu": flight_enu(tg - T0_S), "imu": len(ti), "written": len(tg)}


def _header(stamp_ns: int, frame_id: str):
    Header, Time = STORE.types["std_msgs/msg/Header"], STORE.types["builtin_interfaces/msg/Time"]
    return Header(stamp=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=frame_id)


def write_bag(path: Path, minutes: float, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    tg = np.arange(0.0, minutes * 60.0, 1.0 / GNSS_HZ) + T0_S
    ti = np.arange(0.0, minutes * 60.0, 1.0 / IMU_HZ) + T0_S
    lat, lon, h = geodetic_from_enu(ORIGIN, flight_enu(tg - T0_S))
    gyro, accel = _imu_rows(ti, rng)
    Fix, Imu = STORE.types["sensor_msgs/msg/NavSatFix"], STORE.types["sensor_msgs/msg/Imu"]
    Status = STORE.types["sensor_msgs/msg/NavSatStatus"]
    V3, Q = STORE.types["geometry_msgs/msg/Vector3"], STORE.types["geometry_msgs/msg/Quaternion"]
    cov = np.array([2.25, 0, 0, 0, 2.25, 0, 0, 0, 9.0])
    events = sorted([(t, 0, k) for k, t in enumerate(tg)] + [(t, 1, k) for k, t in enumerate(ti)])
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        cf = w.add_connection("/fix", Fix.__msgtype__, typestore=STORE)
        ci = w.add_connection("/imu", Imu.__msgtype__, typestore=STORE)
        for t, kind, k in events:
            ns = int(round(t * 1e9))
            if kind == 0:
                msg = Fix(
                    header=_header(ns, "gps"),
                    status=Status(status=0, service=1),
                    latitude=float(lat[k]),
                    longitude=float(lon[k]),
                    altitude=float(h[k]),
                    position_covariance=cov,
                    position_covariance_type=2,
                )
                w.write(cf, ns, STORE.serialize_cdr(msg, Fix.__msgtype__))
            else:
                g, a = gyro[k], accel[k]
                msg = Imu(
                    header=_header(ns, "imu"),
                    orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
                    orientation_covariance=np.array([-1.0] + [0.0] * 8),
                    angular_velocity=V3(x=g[0], y=g[1], z=g[2]),
                    angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=V3(x=a[0], y=a[1], z=a[2]),
                    linear_acceleration_covariance=np.zeros(9),
                )
                w.write(ci, ns, STORE.serialize_cdr(msg, Imu.__msgtype__))
    return {"t_s": tg, "enu": flight_enu(tg - T0_S), "imu": len(ti), "written": len(tg)}


def _nan_count(tel) -> int:
    n = 0
    for stream in (tel.gnss, tel.imu, tel.gimbal):
        if stream is not None:
            n += sum(int(np.sum(~np.isfinite(np.asarray(v, float)))) for v in vars(stream).values())
    return n


def check_reader(name: str, path: Path, truth: dict, minutes: float, repeat: int) -> dict:
    speeds, tel = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        tel = read_telemetry(path)
        speeds.append(minutes * 60.0 / (time.perf_counter() - t0))
    g = tel.gnss
    enu = enu_from_geodetic(ORIGIN, g.lat_deg, g.lon_deg, g.height_m)
    same_times = len(g) == len(truth["t_s"]) and np.allclose(g.t_s, truth["t_s"], atol=1e-3)
    diff = float(np.max(np.linalg.norm(enu - truth["enu"], axis=1))) if same_times else None
    row = {
        "format": name,
        "file_mb": round(path.stat().st_size / 1e6 if path.is_file() else _size(path) / 1e6, 1),
        "fixes_written": truth["written"],
        "fixes_read": len(g),
        "garbled_written": truth.get("damaged", 0),
        "skipped_counted": int(sum(tel.skipped.values())),
        "skipped": dict(tel.skipped),
        "imu_written": truth.get("imu", 0),
        "imu_read": 0 if tel.imu is None else len(tel.imu),
        "gimbal_read": 0 if tel.gimbal is None else len(tel.gimbal),
        "nan_read": _nan_count(tel),
        "max_position_diff_m": diff,
        "realtime_factor_min": round(min(speeds), 1),
        "realtime_factor_median": round(statistics.median(speeds), 1),
    }
    return row


def _size(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def _estimate(n: int) -> MethodEstimate:
    t = np.arange(n) * 0.1
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, :3, 3] = flight_enu(t)
    sigma = np.full((n, 3), 0.02)
    status = tuple(PoseStatus.BRIDGED if i % 50 == 0 else PoseStatus.OK for i in range(n))
    return MethodEstimate("fused", T0_S + t, T, np.ones(n, bool), sigma, np.full(n, 3), status)


def check_geo_outputs(folder: Path, sign_map: SignMap, n: int = 2000) -> dict:
    m = _estimate(n)
    want = m.world_T_cam[:, :3, 3]
    geo = run_geo(sign_map, {"fused": m})
    write_run_geo(folder, geo)
    frames = [FrameObservations(i, int(round(t * 1e9)), (64, 48)) for i, t in enumerate(m.stamps_s)]
    write_result_mcap(folder / "result.mcap", sign_map, frames, {}, geo_tracks=geo.tracks())
    got = {}
    with open(folder / "trajectory_wgs84.csv") as f:
        rows = list(csv.DictReader(f))
    got["trajectory_wgs84.csv"] = [
        [float(r[k]) for k in ("lat_deg", "lon_deg", "height_m")] for r in rows
    ]
    gj = json.loads((folder / "trajectory.geojson").read_text())
    got["trajectory.geojson"] = [
        [c[1], c[0], c[2]]
        for f in gj["features"]
        if f["geometry"]["type"] == "Point"
        for c in [f["geometry"]["coordinates"]]
    ]
    ns = "{http://www.opengis.net/kml/2.2}"
    root = ET.parse(folder / "trajectory.kml").getroot()
    coords = root.find(f".//{ns}LineString/{ns}coordinates").text.split()
    got["trajectory.kml"] = [
        [float(v) for v in c.split(",")][1::-1] + [float(c.split(",")[2])] for c in coords
    ]
    fixes = mcap_io.read_json_messages(folder / "result.mcap", "/signpose/fused/fix")
    got["result.mcap LocationFix"] = [[x["latitude"], x["longitude"], x["altitude"]] for x in fixes]
    out = {}
    for name, llh in got.items():
        a = np.asarray(llh, float)
        enu = enu_from_geodetic(ORIGIN, a[:, 0], a[:, 1], a[:, 2])
        d = np.linalg.norm(enu - want, axis=1) if len(enu) == n else None
        out[name] = {
            "poses": len(enu),
            "max_diff_mm": None if d is None else round(1000 * float(d.max()), 3),
            "max_horizontal_diff_mm": None
            if d is None
            else round(1000 * float(np.linalg.norm((enu - want)[:, :2], axis=1).max()), 3),
        }
    track = method_track(m, ORIGIN)
    back = enu_from_geodetic(ORIGIN, track.lat_deg, track.lon_deg, track.height_m)
    out["conversion (float64, no file)"] = {
        "poses": n,
        "max_diff_mm": round(1000 * float(np.linalg.norm(back - want, axis=1).max()), 6),
    }
    return out


RUN_OFFSET_S = 0.25


def _horizontal_m(llh: np.ndarray, truth_enu: np.ndarray) -> np.ndarray:
    enu = enu_from_geodetic(ORIGIN, llh[:, 0], llh[:, 1], llh[:, 2])
    return np.linalg.norm((enu - truth_enu)[:, :2], axis=1)


def _stats(d: np.ndarray) -> dict:
    return {"rms_m": round(float(np.sqrt(np.mean(d**2))), 4), "max_m": round(float(d.max()), 4)}


def check_run(
    folder: Path, sign_map: SignMap, frames: int, seed: int, estimate_clock: bool
) -> dict:
    """A rendered flight with GNSS through pipeline.run; the WGS84 track against the truth."""
    sim = simulate(
        sign_map,
        folder / "flight",
        SimSettings(frames=frames, width=1280, height=720, speed_mps=3.0, seed=seed),
        progress=False,
    )
    gt = read_tum(sim.groundtruth_path)
    rng = np.random.default_rng(seed)
    t = np.arange(gt.stamps_s[0] + 0.037, gt.stamps_s[-1], 1.0 / GNSS_HZ)
    true = np.stack([np.interp(t, gt.stamps_s, gt.world_t_cam[:, k]) for k in range(3)], 1)
    noisy = true + rng.normal(0.0, 1.0, true.shape) * [1.5, 1.5, 3.0]
    burst = (t > t[len(t) // 2]) & (t < t[len(t) // 2] + 1.0)
    noisy[burst] += [12.0, 0.0, 0.0]
    lat, lon, h = geodetic_from_enu(ORIGIN, noisy)
    tel = folder / "gnss.csv"
    lines = ["t_s,lat_deg,lon_deg,height_m,sigma_h_m,sigma_v_m"]
    lines += [
        f"{t[k] + RUN_OFFSET_S:.6f},{lat[k]:.9f},{lon[k]:.9f},{h[k]:.4f},1.5,3.0"
        for k in range(len(t))
    ]
    tel.write_text("\n".join(lines) + "\n")
    out = folder / "run"
    request = TelemetryRequest(tel, None, None if estimate_clock else RUN_OFFSET_S)
    settings = pipeline.RunSettings(telemetry=request, plots=False, mcap=False)
    result = pipeline.run(
        sim.frames_path, sign_map, out, camera=sim.camera, settings=settings, progress=False
    )
    with open(out / "trajectory_wgs84.csv") as f:
        rows = list(csv.DictReader(f))
    stamps = np.array([float(r["t_s"]) for r in rows])
    llh = np.array([[float(r[k]) for k in ("lat_deg", "lon_deg", "height_m")] for r in rows])
    truth = np.stack([np.interp(stamps, gt.stamps_s, gt.world_t_cam[:, k]) for k in range(3)], 1)
    smoothed = read_tum(out / "smoothed.tum")
    s_truth = np.stack(
        [np.interp(smoothed.stamps_s, gt.stamps_s, gt.world_t_cam[:, k]) for k in range(3)], 1
    )
    s_llh = np.stack(geodetic_from_enu(ORIGIN, smoothed.world_t_cam), 1)
    return {
        "frames": result.n_frames,
        "fused_poses": len(rows),
        "fused_wgs84_csv": _stats(_horizontal_m(llh, truth)),
        "smoothed": _stats(_horizontal_m(s_llh, s_truth)),
        "gnss_fixes": _stats(np.linalg.norm((noisy - true)[:, :2], axis=1)),
        "gnss_fixes_outside_burst": _stats(np.linalg.norm((noisy - true)[~burst, :2], axis=1)),
        "burst_fixes": int(burst.sum()),
        "clock_offset_true_s": RUN_OFFSET_S,
        "clock_offset_estimated": estimate_clock,
        "notes": list(result.notes),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="flight length [min]")
    ap.add_argument("--garbled", type=float, default=0.05, help="share of damaged SRT subtitles")
    ap.add_argument("--repeat", type=int, default=3, help="reads per file (speed min/median)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--run", action="store_true", help="also run a rendered flight end to end")
    ap.add_argument("--run-frames", type=int, default=150, help="frames of that flight")
    ap.add_argument(
        "--estimate-clock",
        action="store_true",
        help="leave that flight's clock offset to the fusion (default: given, --telemetry-offset)",
    )
    ap.add_argument("--json", help="also write the numbers to this JSON file")
    args = ap.parse_args(argv)
    sign_map = load_map(bundled_map_path())
    sign_map = SignMap(sign_map.frame, sign_map.signs, "bundled demo map + origin", ORIGIN)
    with tempfile.TemporaryDirectory(prefix="signpose-telio-") as tmp:
        d = Path(tmp)
        files = {
            "DJI SRT (current)": (
                d / "cur.SRT",
                write_srt(d / "cur.SRT", args.minutes, args.garbled, False, args.seed),
            ),
            "DJI SRT (older)": (
                d / "old.SRT",
                write_srt(d / "old.SRT", args.minutes, args.garbled, True, args.seed + 1),
            ),
            "telemetry CSV": (d / "tel.csv", write_csv(d / "tel.csv", args.minutes, args.seed)),
            "rosbag2 (mcap)": (d / "bag", write_bag(d / "bag", args.minutes, args.seed)),
        }
        readers = [
            check_reader(k, p, truth, args.minutes, args.repeat) for k, (p, truth) in files.items()
        ]
        (d / "geo").mkdir()
        geo = check_geo_outputs(d / "geo", sign_map)
        run = None
        if args.run:
            run = check_run(d, sign_map, args.run_frames, args.seed, args.estimate_clock)
    share = 100 * args.garbled
    print(f"readers, {args.minutes:g} min of flight, {share:g} % of SRT subtitles damaged:")
    for r in readers:
        diff = r["max_position_diff_m"]
        diff = "n/a" if diff is None else f"{diff:.4f} m"
        print(
            f"  {r['format']:<18} {r['file_mb']:6.1f} MB: "
            f"fixes {r['fixes_read']}/{r['fixes_written']}, "
            f"damaged {r['garbled_written']} -> skipped {r['skipped_counted']} {r['skipped']}, "
            f"IMU {r['imu_read']}/{r['imu_written']}, gimbal {r['gimbal_read']}, "
            f"NaN {r['nan_read']}, max |read - written| {diff}, "
            f"{r['realtime_factor_min']:g}x / {r['realtime_factor_median']:g}x real time "
            "(min / median)"
        )
    print("georeferenced outputs, 2000 poses, read back and converted to ENU:")
    for name, v in geo.items():
        print(f"  {name:<30} {v['poses']} poses, max |file - estimate| {v['max_diff_mm']} mm")
    if run is not None:
        print(f"signpose run --telemetry, {run['frames']} rendered frames, horizontal error:")
        for key in ("fused_wgs84_csv", "smoothed", "gnss_fixes", "gnss_fixes_outside_burst"):
            v = run[key]
            print(f"  {key:<24} RMS {v['rms_m']:.3f} m, max {v['max_m']:.3f} m")
        print(f"  (true clock offset {RUN_OFFSET_S:+.3f} s; {'; '.join(run['notes'][1:2])})")
    if args.json:
        numbers = {"settings": vars(args), "readers": readers, "geo_outputs": geo, "run": run}
        with atomic_write(args.json, encoding="utf-8") as f:
            json.dump(numbers, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
