"""Telemetry as a plain CSV (``docs/telemetry.md`` describes it for users).

One header row naming the columns (any order; lines starting with ``#`` are
comments), then one row per sample. ``t_s`` is required; each row feeds every
stream whose columns it fills, so GNSS at 10 Hz and IMU at 200 Hz share one
file with the other stream's cells left empty:

=====================  ========  ==============================================
column                 unit      meaning
=====================  ========  ==============================================
t_s                    s         time on the telemetry's clock (required)
lat_deg, lon_deg       deg       WGS84 latitude, longitude        (GNSS)
height_m               m         WGS84 ellipsoidal height         (GNSS)
sigma_h_m, sigma_v_m   m         claimed std. dev. (optional; default 2 / 4)
gyro_x_rad_s .. _z     rad/s     angular rate, IMU body frame FLU (IMU)
accel_x_m_s2 .. _z     m/s^2     specific force, FLU, +9.81 on z at rest (IMU)
gimbal_yaw_deg, ..     deg       gimbal yaw / pitch / roll, DJI convention (optional)
=====================  ========  ==============================================

A row whose cells of one stream are only partly filled, or hold something
that is not a number, is skipped for that stream and counted (``garbled``).
"""

from __future__ import annotations

import csv
from pathlib import Path

from signpose.core.errors import InputError
from signpose.estimator.telemetry import Telemetry
from signpose.io.telemetry_build import (
    count,
    fixes_from_rows,
    gimbal_from_rows,
    imu_from_rows,
    reasons,
)

TIME_COLUMN = "t_s"
GNSS_COLUMNS = ("lat_deg", "lon_deg", "height_m")
SIGMA_COLUMNS = ("sigma_h_m", "sigma_v_m")
IMU_COLUMNS = (
    "gyro_x_rad_s",
    "gyro_y_rad_s",
    "gyro_z_rad_s",
    "accel_x_m_s2",
    "accel_y_m_s2",
    "accel_z_m_s2",
)
GIMBAL_COLUMNS = ("gimbal_yaw_deg", "gimbal_pitch_deg", "gimbal_roll_deg")
ALL_COLUMNS = (TIME_COLUMN, *GNSS_COLUMNS, *SIGMA_COLUMNS, *IMU_COLUMNS, *GIMBAL_COLUMNS)
MAX_CSV_BYTES = 2 << 30


def _header(p: Path, rows) -> list[str]:
    for row in rows:
        if row and not row[0].lstrip().startswith("#") and any(c.strip() for c in row):
            names = [c.strip() for c in row]
            unknown = [n for n in names if n not in ALL_COLUMNS]
            if unknown:
                raise InputError(
                    f"{p}: unknown column '{unknown[0]}' in the header (columns: "
                    f"{', '.join(ALL_COLUMNS)}; see docs/telemetry.md)"
                )
            if TIME_COLUMN not in names:
                raise InputError(f"{p}: the header has no '{TIME_COLUMN}' column")
            has_gnss = all(c in names for c in GNSS_COLUMNS)
            has_imu = all(c in names for c in IMU_COLUMNS)
            if not has_gnss and not has_imu:
                raise InputError(
                    f"{p}: the header needs the GNSS columns {', '.join(GNSS_COLUMNS)} "
                    "or all six IMU columns (gyro_*_rad_s, accel_*_m_s2)"
                )
            return names
    raise InputError(f"{p}: empty telemetry CSV (no header row); see docs/telemetry.md")


def _group(cells: dict[str, str], columns: tuple[str, ...], skipped: dict, name: str):
    """The floats of one stream's cells, None when all are empty; garbled ones counted."""
    values = [cells.get(c, "") for c in columns]
    if all(v == "" for v in values):
        return None
    try:
        if any(v == "" for v in values):
            raise ValueError
        return [float(v) for v in values]
    except ValueError:
        count(skipped, "garbled" if name == "gnss" else f"garbled_{name}")
        return None


def read_telemetry_csv(path: str | Path) -> Telemetry:
    """Read a telemetry CSV (columns in the module docstring).

    Raises:
        InputError: unreadable file, bad header, or no usable row.
    """
    p = Path(path)
    try:
        if p.stat().st_size > MAX_CSV_BYTES:
            raise InputError(f"{p}: larger than {MAX_CSV_BYTES} bytes; split the telemetry")
        text = p.read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError(f"{p}: telemetry file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read telemetry CSV ({exc})") from None
    rows = csv.reader(text.splitlines())
    names = _header(p, rows)
    skipped: dict[str, int] = {}
    gnss, imu, gimbal = [], [], []
    for row in rows:
        if not row or row[0].lstrip().startswith("#") or not any(c.strip() for c in row):
            continue
        cells = {n: c.strip() for n, c in zip(names, row, strict=False)}
        t = _group(cells, (TIME_COLUMN,), skipped, "gnss")
        if t is None:
            continue
        g = _group(cells, GNSS_COLUMNS, skipped, "gnss")
        if g is not None:
            s = [_sigma(cells.get(c, "")) for c in SIGMA_COLUMNS]
            gnss.append(t + g + s)
        i = _group(cells, IMU_COLUMNS, skipped, "imu")
        if i is not None:
            imu.append(t + i)
        a = _group(cells, GIMBAL_COLUMNS, skipped, "gimbal")
        if a is not None:
            gimbal.append(t + a)
    return _telemetry(p, gnss, imu, gimbal, skipped)


def _sigma(cell: str) -> float:
    try:
        return float(cell)
    except ValueError:
        return float("nan")  # the default sigma (telemetry_build)


def _telemetry(p: Path, gnss: list, imu: list, gimbal: list, skipped: dict) -> Telemetry:
    fixes = fixes_from_rows(gnss, skipped)
    samples = imu_from_rows(imu, skipped)
    angles = gimbal_from_rows(gimbal, skipped)
    if fixes is None and samples is None:
        raise InputError(f"{p}: no usable GNSS or IMU row ({reasons(skipped) or 'no data rows'})")
    return Telemetry(source=str(p), gnss=fixes, imu=samples, gimbal=angles, skipped=skipped)
