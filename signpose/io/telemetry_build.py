"""Rows read from a telemetry file -> the estimator's ``Telemetry`` streams.

Every telemetry reader (SRT, ULog, CSV, ROS 2 logs) collects plain rows and
builds its streams here, so every format drops and counts bad samples the
same way: a row with a non-finite number (``non_finite``), a GNSS fix outside
WGS84's ranges or at (0, 0), which DJI and u-blox write before a fix
(``no_fix``), a time not after the previous kept one (``non_monotonic``).
What is kept never holds a NaN. Long pauses between fixes are counted as
``gap`` (the samples are kept; the fusion bridges them).
"""

from __future__ import annotations

import numpy as np

from signpose.estimator.telemetry import GimbalAngles, GnssFixes, ImuSamples

# Claimed GNSS accuracy when a format gives none: a consumer receiver [m].
DEFAULT_SIGMA_H_M = 2.0
DEFAULT_SIGMA_V_M = 4.0
# A pause between fixes longer than this many times the median interval is a gap.
GAP_FACTOR = 5.0


def count(skipped: dict[str, int], reason: str, n: int = 1) -> None:
    """Add ``n`` dropped samples of ``reason`` to ``skipped`` (no entry for 0)."""
    if n > 0:
        skipped[reason] = skipped.get(reason, 0) + n


def reasons(skipped: dict[str, int]) -> str:
    """The dropped samples for a message: ``"2 garbled, 1 no_fix"`` (by reason; "" for none)."""
    return ", ".join(f"{v} {k}" for k, v in sorted(skipped.items()))


def _increasing(t_s: np.ndarray, skipped: dict[str, int]) -> np.ndarray:
    """Mask of the samples whose time is after every earlier kept sample's."""
    # A sample is kept when it is after the running maximum of all earlier ones
    # (every sample that raises that maximum is kept, so it is the kept ones' too).
    before = np.maximum.accumulate(np.concatenate([[-np.inf], t_s]))[:-1]
    keep = t_s > before
    count(skipped, "non_monotonic", int((~keep).sum()))
    return keep


def _finite_rows(columns: list[np.ndarray], skipped: dict[str, int]) -> np.ndarray:
    n = len(columns[0])
    finite = np.ones(n, dtype=bool)
    for c in columns:
        finite &= np.all(np.isfinite(c.reshape(n, c.size // n if n else 1)), axis=1)
    count(skipped, "non_finite", int((~finite).sum()))
    return finite


def _gaps(t_s: np.ndarray) -> int:
    if len(t_s) < 3:
        return 0
    dt = np.diff(t_s)
    return int((dt > GAP_FACTOR * float(np.median(dt))).sum())


def gnss_fixes(
    t_s,
    lat_deg,
    lon_deg,
    height_m,
    skipped: dict[str, int],
    sigma_h_m=None,
    sigma_v_m=None,
) -> GnssFixes | None:
    """Fixes from row arrays (N,) with bad ones dropped and counted; None when none is left.

    Args:
        sigma_h_m, sigma_v_m: (N,) claimed standard deviations [m], or None for
            the defaults; a non-positive or non-finite one takes the default.
    """
    t = np.asarray(t_s, dtype=float)
    lat, lon, h = (np.asarray(a, dtype=float) for a in (lat_deg, lon_deg, height_m))
    n = len(t)
    sh = _sigmas(sigma_h_m, n, DEFAULT_SIGMA_H_M)
    sv = _sigmas(sigma_v_m, n, DEFAULT_SIGMA_V_M)
    keep = _finite_rows([t, lat, lon, h], skipped)
    no_fix = keep & ((np.abs(lat) > 90.0) | (np.abs(lon) > 180.0) | ((lat == 0.0) & (lon == 0.0)))
    count(skipped, "no_fix", int(no_fix.sum()))
    keep &= ~no_fix
    idx = np.flatnonzero(keep)
    idx = idx[_increasing(t[idx], skipped)]
    if len(idx) == 0:
        return None
    count(skipped, "gap", _gaps(t[idx]))
    return GnssFixes(t[idx], lat[idx], lon[idx], h[idx], sh[idx], sv[idx])


def _sigmas(values, n: int, default: float) -> np.ndarray:
    if values is None:
        return np.full(n, default)
    s = np.asarray(values, dtype=float).reshape(n)
    return np.where(np.isfinite(s) & (s > 0), s, default)


def imu_samples(t_s, gyro_rad_s, accel_m_s2, skipped: dict[str, int]) -> ImuSamples | None:
    """IMU samples from (N,), (N, 3), (N, 3) rows, bad ones dropped and counted; or None."""
    t = np.asarray(t_s, dtype=float).reshape(-1)
    gyro = np.asarray(gyro_rad_s, dtype=float).reshape(-1, 3)
    accel = np.asarray(accel_m_s2, dtype=float).reshape(-1, 3)
    idx = np.flatnonzero(_finite_rows([t, gyro, accel], skipped))
    idx = idx[_increasing(t[idx], skipped)]
    if len(idx) == 0:
        return None
    return ImuSamples(t[idx], gyro[idx], accel[idx])


def gimbal_angles(
    t_s, yaw_deg, pitch_deg, roll_deg, skipped: dict[str, int]
) -> GimbalAngles | None:
    """Gimbal angles from (N,) rows, bad ones dropped and counted; or None."""
    t, yaw, pitch, roll = (np.asarray(a, dtype=float) for a in (t_s, yaw_deg, pitch_deg, roll_deg))
    idx = np.flatnonzero(_finite_rows([t, yaw, pitch, roll], skipped))
    idx = idx[_increasing(t[idx], skipped)]
    if len(idx) == 0:
        return None
    return GimbalAngles(t[idx], yaw[idx], pitch[idx], roll[idx])


def fixes_from_rows(rows: list, skipped: dict[str, int]) -> GnssFixes | None:
    """``gnss_fixes`` of rows ``(t_s, lat_deg, lon_deg, height_m, sigma_h_m, sigma_v_m)``."""
    f = np.array(rows, dtype=float).reshape(-1, 6)
    if not len(f):
        return None
    return gnss_fixes(f[:, 0], f[:, 1], f[:, 2], f[:, 3], skipped, f[:, 4], f[:, 5])


def imu_from_rows(rows: list, skipped: dict[str, int]) -> ImuSamples | None:
    """``imu_samples`` of rows ``(t_s, gyro x y z, accel x y z)``."""
    s = np.array(rows, dtype=float).reshape(-1, 7)
    return imu_samples(s[:, 0], s[:, 1:4], s[:, 4:7], skipped) if len(s) else None


def gimbal_from_rows(rows: list, skipped: dict[str, int]) -> GimbalAngles | None:
    """``gimbal_angles`` of rows ``(t_s, yaw_deg, pitch_deg, roll_deg)``."""
    a = np.array(rows, dtype=float).reshape(-1, 4)
    return gimbal_angles(a[:, 0], a[:, 1], a[:, 2], a[:, 3], skipped) if len(a) else None
