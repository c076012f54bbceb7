"""PX4 ULog in: a tiny ULog written here from the format's specification, read by pyulog.

ULog (docs.px4.io, "ULog File Format"): a 16-byte header (magic, version,
start time [us]), then messages of ``uint16 size, uint8 type, payload``:
``B`` flag bits, ``F`` formats (``name:type field;...``), ``A`` subscriptions
(multi id, msg id, name) and ``D`` data (msg id, the packed fields).
"""

import struct
from pathlib import Path

import numpy as np
import pytest

from signpose.core.errors import InputError
from signpose.io.telemetry import read_telemetry
from signpose.io.telemetry_ulog import read_ulog

_PACK = {"uint64_t": "Q", "int32_t": "i", "uint8_t": "B", "float": "f", "double": "d"}
GPS_FIELDS = [
    ("uint64_t", "timestamp"),
    ("uint64_t", "time_utc_usec"),
    ("int32_t", "lat"),
    ("int32_t", "lon"),
    ("int32_t", "alt"),
    ("int32_t", "alt_ellipsoid"),
    ("float", "eph"),
    ("float", "epv"),
    ("uint8_t", "fix_type"),
]
IMU_FIELDS = [
    ("uint64_t", "timestamp"),
    ("float[3]", "gyro_rad"),
    ("float[3]", "accelerometer_m_s2"),
]
UTC_AT_BOOT_S = 1_780_000_000.0


def _message(kind: str, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def _pack(fields, values) -> bytes:
    out = b""
    for (ftype, _), v in zip(fields, values, strict=True):
        if ftype.endswith("[3]"):
            out += struct.pack("<3f", *v)
        else:
            out += struct.pack("<" + _PACK[ftype], v)
    return out


def write_ulog(path: Path, topics: dict[str, tuple[list, list]]) -> Path:
    """A ULog with ``{name: (fields, rows)}``, each topic one subscription, rows in order."""
    out = b"ULog\x01\x12\x35" + bytes([1]) + struct.pack("<Q", 0)
    out += _message("B", bytes(16) + bytes(24))
    for name, (fields, _) in topics.items():
        fmt = name + ":" + "".join(f"{t} {n};" for t, n in fields)
        out += _message("F", fmt.encode())
    for msg_id, name in enumerate(topics):
        out += _message("A", struct.pack("<BH", 0, msg_id) + name.encode())
    for msg_id, (fields, rows) in enumerate(topics.values()):
        for row in rows:
            out += _message("D", struct.pack("<H", msg_id) + _pack(fields, row))
    path.write_bytes(out)
    return path


def _gps_rows(n: int, fix_type=3):
    rows = []
    for i in range(n):
        t_us = 5_000_000 + i * 100_000
        utc_us = int((UTC_AT_BOOT_S + t_us * 1e-6) * 1e6)
        lat, lon = int((47.3769 + i * 1e-6) * 1e7), int((8.5417 + i * 2e-6) * 1e7)
        rows.append((t_us, utc_us, lat, lon, 490_000, 537_500 + i * 10, 0.8, 1.6, fix_type))
    return rows


def _imu_rows(n: int):
    # FRD: at rest the accelerometer reads -g on z; a right turn is +z rate.
    return [(5_000_000 + i * 5_000, (0.01, 0.02, 0.3), (0.1, 0.2, -9.81)) for i in range(n)]


def test_gps_and_imu_are_read_on_utc_and_turned_from_frd_to_flu(tmp_path):
    gps = _gps_rows(8)
    gps[2] = (*gps[2][:-1], 2)  # a 2D fix: skipped
    p = write_ulog(
        tmp_path / "log.ulg",
        {"vehicle_gps_position": (GPS_FIELDS, gps), "sensor_combined": (IMU_FIELDS, _imu_rows(40))},
    )
    t = read_telemetry(p)
    assert len(t.gnss) == 7 and t.skipped == {"no_fix": 1}
    assert t.gnss.t_s[0] == pytest.approx(UTC_AT_BOOT_S + 5.0, abs=1e-5)
    assert t.gnss.lat_deg[0] == pytest.approx(47.3769, abs=1e-7)
    assert t.gnss.lon_deg[-1] == pytest.approx(8.5417 + 7 * 2e-6, abs=1e-7)
    assert t.gnss.height_m[0] == pytest.approx(537.5)  # the ellipsoid height, not MSL
    np.testing.assert_allclose(t.gnss.sigma_h_m, 0.8, rtol=1e-6)
    np.testing.assert_allclose(t.gnss.sigma_v_m, 1.6, rtol=1e-6)
    assert len(t.imu) == 40
    assert t.imu.t_s[0] == pytest.approx(t.gnss.t_s[0], abs=1e-5)  # one clock for both
    np.testing.assert_allclose(t.imu.gyro_rad_s[0], [0.01, -0.02, -0.3], rtol=1e-6)
    np.testing.assert_allclose(t.imu.accel_m_s2[0], [0.1, -0.2, 9.81], rtol=1e-6)


def test_newer_sensor_gps_and_vehicle_imu_fields(tmp_path):
    fields = [
        ("uint64_t", "timestamp"),
        ("double", "latitude_deg"),
        ("double", "longitude_deg"),
        ("double", "altitude_ellipsoid_m"),
        ("uint8_t", "fix_type"),
    ]
    rows = [(1_000_000 * (i + 1), 47.0 + i * 1e-6, 8.0, 500.0 + i, 3) for i in range(4)]
    imu_fields = [
        ("uint64_t", "timestamp"),
        ("uint64_t", "timestamp_sample"),
        ("float[3]", "delta_angle"),
        ("float[3]", "delta_velocity"),
        ("float", "delta_angle_dt"),
        ("float", "delta_velocity_dt"),
    ]
    imu = [
        (
            1_000_000 + i * 5000,
            999_000 + i * 5000,
            (0.0, 0.0, 0.001),
            (0.0, 0.0, -0.049),
            5000.0,
            5000.0,
        )
        for i in range(10)
    ]
    p = write_ulog(
        tmp_path / "new.ulg", {"sensor_gps": (fields, rows), "vehicle_imu": (imu_fields, imu)}
    )
    t = read_ulog(p)
    np.testing.assert_allclose(t.gnss.t_s, [1.0, 2.0, 3.0, 4.0])  # no UTC: since boot
    np.testing.assert_allclose(t.gnss.height_m, [500.0, 501.0, 502.0, 503.0])
    np.testing.assert_allclose(t.gnss.sigma_h_m, 2.0)  # no eph: the default
    assert t.imu.t_s[0] == pytest.approx(0.999)
    np.testing.assert_allclose(t.imu.gyro_rad_s[0], [0.0, 0.0, -0.2], rtol=1e-5)
    np.testing.assert_allclose(t.imu.accel_m_s2[0], [0.0, 0.0, 9.8], rtol=1e-5)


def test_a_ulog_without_gnss_is_one_line(tmp_path):
    p = write_ulog(tmp_path / "nogps.ulg", {"sensor_combined": (IMU_FIELDS, _imu_rows(5))})
    with pytest.raises(InputError) as exc:
        read_telemetry(p)
    msg = str(exc.value)
    assert msg.startswith(str(p)) and "no GNSS topic" in msg and "\n" not in msg


def test_a_ulog_whose_fixes_are_all_2d_and_a_broken_file_are_one_line(tmp_path):
    p = write_ulog(tmp_path / "2d.ulg", {"vehicle_gps_position": (GPS_FIELDS, _gps_rows(3, 2))})
    with pytest.raises(InputError, match="no usable 3D fix"):
        read_telemetry(p)
    bad = tmp_path / "bad.ulg"
    bad.write_bytes(b"ULog\x01\x12\x35" + bytes(3))
    with pytest.raises(InputError) as exc:
        read_telemetry(bad)
    assert str(exc.value).startswith(str(bad)) and "\n" not in str(exc.value)


def test_an_msl_altitude_only_gets_a_large_vertical_sigma(tmp_path):
    fields = [f for f in GPS_FIELDS if f[1] != "alt_ellipsoid"]
    rows = [r[:5] + r[6:] for r in _gps_rows(4)]  # without alt_ellipsoid
    t = read_ulog(write_ulog(tmp_path / "msl.ulg", {"vehicle_gps_position": (fields, rows)}))
    np.testing.assert_allclose(t.gnss.height_m, 490.0)  # MSL, as logged
    np.testing.assert_allclose(t.gnss.sigma_v_m, 30.0)  # the geoid is tens of metres away
    np.testing.assert_allclose(t.gnss.sigma_h_m, 0.8, rtol=1e-6)
