"""NavSatFix and Imu topics of rosbag2 bags (MCAP and sqlite3 storage) as telemetry.

The bags are written with the ``rosbags`` writer and the ROS 2 Humble types.
"""

from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from signpose.core.errors import InputError
from signpose.io.telemetry import read_telemetry

STORE = get_typestore(Stores.ROS2_HUMBLE)
EPOCH_S = 1_700_000_000
FIX, IMU = "sensor_msgs/msg/NavSatFix", "sensor_msgs/msg/Imu"


def _header(stamp_ns: int, frame_id: str = "gps"):
    Header, Time = STORE.types["std_msgs/msg/Header"], STORE.types["builtin_interfaces/msg/Time"]
    return Header(stamp=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=frame_id)


def _fix(stamp_ns: int, lat: float, lon: float, alt: float, status: int = 0, var: float = 0.25):
    Status = STORE.types["sensor_msgs/msg/NavSatStatus"]
    return STORE.types[FIX](
        header=_header(stamp_ns),
        status=Status(status=status, service=1),
        latitude=lat,
        longitude=lon,
        altitude=alt,
        position_covariance=np.array([var, 0, 0, 0, var, 0, 0, 0, 4 * var]),
        position_covariance_type=2,
    )


def _imu(stamp_ns: int, gyro_z: float, gyro_cov0: float = 0.0):
    V3, Q = STORE.types["geometry_msgs/msg/Vector3"], STORE.types["geometry_msgs/msg/Quaternion"]
    return STORE.types[IMU](
        header=_header(stamp_ns, "imu"),
        orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.array([-1.0] + [0.0] * 8),
        angular_velocity=V3(x=0.0, y=0.0, z=gyro_z),
        angular_velocity_covariance=np.array([gyro_cov0] + [0.0] * 8),
        linear_acceleration=V3(x=0.0, y=0.0, z=9.81),
        linear_acceleration_covariance=np.zeros(9),
    )


def write_telemetry_bag(path: Path, storage, fix_topics=("/fix",)) -> Path:
    with Writer(path, version=8, storage_plugin=storage) as w:
        fixes = [w.add_connection(t, FIX, typestore=STORE) for t in fix_topics]
        imu = w.add_connection("/imu", IMU, typestore=STORE)
        for i in range(50):
            stamp = EPOCH_S * 10**9 + i * 5_000_000
            cov0 = -1.0 if i == 7 else 0.0  # a sample without a gyro
            w.write(imu, stamp + 1000, STORE.serialize_cdr(_imu(stamp, 0.01 * i, cov0), IMU))
            if i % 10 == 0:
                status = -1 if i == 20 else 0  # no fix
                msg = _fix(stamp, 47.0 + i * 1e-6, 8.0, 500.0 + i, status)
                for c in fixes:
                    w.write(c, stamp + 2000, STORE.serialize_cdr(msg, FIX))
    return path


@pytest.mark.parametrize("storage", [StoragePlugin.MCAP, StoragePlugin.SQLITE3])
def test_navsatfix_and_imu_from_a_bag(tmp_path, storage):
    bag = write_telemetry_bag(tmp_path / "bag", storage)
    t = read_telemetry(bag)
    np.testing.assert_allclose(t.gnss.t_s - EPOCH_S, [0.0, 0.05, 0.15, 0.2], atol=1e-6)
    np.testing.assert_allclose(t.gnss.height_m, [500.0, 510.0, 530.0, 540.0])
    np.testing.assert_allclose(t.gnss.sigma_h_m, 0.5)  # sqrt of the covariance
    np.testing.assert_allclose(t.gnss.sigma_v_m, 1.0)
    assert len(t.imu) == 49 and t.skipped == {"no_fix": 1, "no_gyro": 1}
    assert t.imu.gyro_rad_s[1, 2] == pytest.approx(0.01)
    np.testing.assert_allclose(t.imu.accel_m_s2[:, 2], 9.81)


def test_several_fix_topics_need_one_named(tmp_path):
    bag = write_telemetry_bag(tmp_path / "bag", StoragePlugin.MCAP, ("/fix", "/rtk/fix"))
    with pytest.raises(InputError) as exc:
        read_telemetry(bag)
    msg = str(exc.value)
    assert msg.startswith(str(bag)) and "2 GNSS topics" in msg and "--telemetry-topic" in msg
    t = read_telemetry(bag, topic="/rtk/fix,/imu")
    assert len(t.gnss) == 4 and len(t.imu) == 49
    only_fix = read_telemetry(bag, topic="/rtk/fix")
    assert only_fix.imu is None
    with pytest.raises(InputError, match="--telemetry-topic /nope: not a NavSatFix"):
        read_telemetry(bag, topic="/nope")
