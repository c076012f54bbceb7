"""PX4 ULog (``.ulg``) in, through ``pyulog``: GNSS fixes and IMU samples.

Topics read (the first instance of each):

* GNSS: ``sensor_gps`` (PX4 >= 1.14) or ``vehicle_gps_position`` (older):
  ``latitude_deg``/``longitude_deg`` (or ``lat``/``lon`` in 1e-7 deg),
  ``altitude_ellipsoid_m`` (or ``alt_ellipsoid`` [mm]; the MSL ``alt`` only
  where neither is logged, with a vertical sigma of at least ``MSL_SIGMA_V_M``:
  the geoid is tens of metres from the ellipsoid), ``eph``/``epv`` as the
  sigmas, ``fix_type`` (< 3:
  no 3D fix, skipped as ``no_fix``).
* IMU: ``sensor_combined`` (``gyro_rad``, ``accelerometer_m_s2``), else
  ``vehicle_imu`` (``delta_angle`` / ``delta_velocity`` over their ``_dt``).
  PX4's body frame is FRD (x forward, y right, z down); the samples are
  turned into the telemetry's FLU (y and z negated).

Clock: PX4 stamps are microseconds since boot. Where the GNSS logs
``time_utc_usec``, every stream is moved onto UTC (seconds since 1970, the
clock of an MP4's ``creation_time`` and of ROS logs) by the median of
``time_utc_usec - timestamp`` over the fixes; otherwise times stay since boot.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
from pyulog import ULog

from signpose.core.errors import InputError
from signpose.estimator.telemetry import ImuSamples, Telemetry
from signpose.io.telemetry_build import count, gnss_fixes, imu_samples, reasons

GNSS_TOPICS = ("sensor_gps", "vehicle_gps_position")
IMU_TOPICS = ("sensor_combined", "vehicle_imu")
MIN_3D_FIX = 3
MSL_SIGMA_V_M = 30.0
FRD_TO_FLU = np.array([1.0, -1.0, -1.0])


def _dataset(ulog: ULog, name: str) -> dict[str, np.ndarray] | None:
    instances = [d for d in ulog.data_list if d.name == name]
    if not instances:
        return None
    return min(instances, key=lambda d: d.multi_id).data


def _first(data: dict, *names: str, scale: float = 1.0) -> np.ndarray | None:
    for name in names:
        if name in data:
            return np.asarray(data[name], dtype=float) * scale
    return None


def _vector(data: dict, name: str) -> np.ndarray | None:
    cols = [f"{name}[{i}]" for i in range(3)]
    if not all(c in data for c in cols):
        return None
    return np.stack([np.asarray(data[c], dtype=float) for c in cols], axis=1)


def _gnss(p: Path, data: dict, skipped: dict[str, int]):
    t = np.asarray(data["timestamp"], dtype=float) * 1e-6
    lat = (
        _first(data, "latitude_deg") if "latitude_deg" in data else _first(data, "lat", scale=1e-7)
    )
    lon = (
        _first(data, "longitude_deg")
        if "longitude_deg" in data
        else _first(data, "lon", scale=1e-7)
    )
    h = _first(data, "altitude_ellipsoid_m")
    if h is None:
        h = _first(data, "alt_ellipsoid", scale=1e-3)
    msl = h is None
    if msl:
        h = (
            _first(data, "altitude_msl_m")
            if "altitude_msl_m" in data
            else _first(data, "alt", scale=1e-3)
        )
    if lat is None or lon is None or h is None:
        raise InputError(f"{p}: the GNSS topic has no latitude, longitude or altitude field")
    fix = _first(data, "fix_type")
    keep = fix >= MIN_3D_FIX if fix is not None else np.ones(len(t), dtype=bool)
    count(skipped, "no_fix", int((~keep).sum()))
    eph, epv = _first(data, "eph"), _first(data, "epv")
    if msl:  # above the geoid, not the ellipsoid: weigh the height little
        epv = np.maximum(epv if epv is not None else 0.0, MSL_SIGMA_V_M) * np.ones(len(t))
    gnss = gnss_fixes(
        t[keep],
        lat[keep],
        lon[keep],
        h[keep],
        skipped,
        eph[keep] if eph is not None else None,
        epv[keep] if epv is not None else None,
    )
    utc = _first(data, "time_utc_usec")
    shift = 0.0
    if utc is not None:
        valid = keep & (utc > 0)
        if valid.any():
            shift = float(np.median(utc[valid] * 1e-6 - t[valid]))
    return gnss, shift


def _imu(data: dict, name: str, skipped: dict[str, int]) -> ImuSamples | None:
    if name == "sensor_combined":
        t = np.asarray(data["timestamp"], dtype=float) * 1e-6
        gyro, accel = _vector(data, "gyro_rad"), _vector(data, "accelerometer_m_s2")
    else:
        t = _first(data, "timestamp_sample", "timestamp") * 1e-6
        d_angle, d_vel = _vector(data, "delta_angle"), _vector(data, "delta_velocity")
        dt_a = _first(data, "delta_angle_dt", scale=1e-6)
        dt_v = _first(data, "delta_velocity_dt", scale=1e-6)
        if d_angle is None or d_vel is None or dt_a is None or dt_v is None:
            return None
        with np.errstate(divide="ignore", invalid="ignore"):
            gyro = d_angle / np.where(dt_a > 0, dt_a, np.nan)[:, None]
            accel = d_vel / np.where(dt_v > 0, dt_v, np.nan)[:, None]
    if gyro is None or accel is None:
        return None
    return imu_samples(t, gyro * FRD_TO_FLU, accel * FRD_TO_FLU, skipped)


def read_ulog(path: str | Path) -> Telemetry:
    """Read a PX4 ULog's GNSS fixes and IMU samples.

    Raises:
        InputError: not a readable ULog, or one without a GNSS topic or fix.
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(f"{p}: telemetry file not found")
    try:
        ulog = ULog(str(p), list(GNSS_TOPICS + IMU_TOPICS))
    except Exception as exc:  # noqa: BLE001 - pyulog raises many kinds on a bad file
        text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise InputError(f"{p}: not a readable PX4 ULog ({text})") from None
    skipped: dict[str, int] = {}
    if ulog.file_corruption:
        count(skipped, "corrupt_data")
    name = next((n for n in GNSS_TOPICS if _dataset(ulog, n) is not None), None)
    if name is None:
        raise InputError(
            f"{p}: the ULog has no GNSS topic ({' or '.join(GNSS_TOPICS)}); log the GPS "
            "(SDLOG_PROFILE default) or pass a telemetry file with fixes"
        )
    gnss, shift = _gnss(p, _dataset(ulog, name), skipped)
    if gnss is None:
        why = reasons(skipped) or "none logged"
        raise InputError(f"{p}: {name} holds no usable 3D fix ({why})")
    imu = None
    for imu_name in IMU_TOPICS:
        data = _dataset(ulog, imu_name)
        if data is not None:
            imu = _imu(data, imu_name, skipped)
            if imu is not None:
                break
    if shift:  # onto UTC
        gnss = replace(gnss, t_s=gnss.t_s + shift)
        imu = replace(imu, t_s=imu.t_s + shift) if imu is not None else None
    return Telemetry(source=str(p), gnss=gnss, imu=imu, skipped=skipped)
