"""The simulated telemetry: IMU consistent with the trajectory, GNSS errors as specified,
the CSV read back by the reader, a long stretch with no sign in view."""

from __future__ import annotations

from dataclasses import replace

import gtsam
import numpy as np
import pytest
from signpose.estimator.camera import pinhole_camera
from signpose.estimator.fusion import (
    FusionSettings,
    _imu_params,
    _preintegrate,
    gimbal_from_world_R_cam,
)
from signpose.maps.geodesy import GeoOrigin, enu_from_geodetic
from signpose.maps.loader import bundled_map_path, load_map

from signpose.io.telemetry_csv import read_telemetry_csv
from signpose.sim.observations import synthesize_observations
from signpose.sim.telemetry import (
    TelemetrySimSettings,
    away_and_back,
    default_body_T_cam,
    simulate_telemetry,
    write_telemetry_csv,
)

ORIGIN = GeoOrigin(47.0, 8.0, 500.0)
NOISELESS = TelemetrySimSettings(
    gyro_noise=0.0,
    accel_noise=0.0,
    gyro_bias_rw=0.0,
    accel_bias_rw=0.0,
    gyro_bias0=0.0,
    accel_bias0=0.0,
    clock_offset_s=0.3,
)


@pytest.fixture(scope="module")
def site():
    sign_map = replace(load_map(bundled_map_path()), origin=ORIGIN)
    return sign_map, away_and_back(sign_map, seed=1)


def test_noiseless_imu_integrates_to_the_trajectory(site):
    """Preintegrated noise-free samples carry the true pose 1 s on within 2 mm / 0.1 mrad."""
    sign_map, flight = site
    tel, _ = simulate_telemetry(flight, sign_map, np.random.default_rng(0), NOISELESS)
    body_T_cam = default_body_T_cam()
    s = FusionSettings(body_T_cam=tuple(map(tuple, body_T_cam)))
    for ta in (3.0, 9.5, 15.0):  # looking at the signs, turning away, away
        tb = ta + 1.0
        pim = gtsam.PreintegratedCombinedMeasurements(_imu_params(s))
        off = NOISELESS.clock_offset_s
        assert _preintegrate(pim, tel.imu, ta + off, tb + off, 0.05)
        T = flight.poses(np.array([ta - 1e-3, ta, ta + 1e-3, tb]))
        v = (T[2, :3, 3] - T[0, :3, 3]) / 2e-3
        state = pim.predict(gtsam.NavState(gtsam.Pose3(T[1]), v), gtsam.imuBias.ConstantBias())
        assert np.linalg.norm(state.pose().translation() - T[3, :3, 3]) < 2e-3
        dR = state.pose().rotation().matrix().T @ T[3, :3, :3]
        assert np.linalg.norm(gtsam.Rot3.Logmap(gtsam.Rot3(dR))) < 1e-4


def test_gnss_errors_bursts_and_same_noise_without_them(site):
    sign_map, flight = site
    s = TelemetrySimSettings()
    tel, truth = simulate_telemetry(flight, sign_map, np.random.default_rng(5), s)
    clean, clean_truth = simulate_telemetry(
        flight, sign_map, np.random.default_rng(5), replace(s, multipath=False)
    )
    assert 9.5 <= 1.0 / np.median(np.diff(tel.gnss.t_s)) <= 10.5
    # Fixes are where the truth says, through the geodesy (WGS84 -> ENU).
    z = enu_from_geodetic(ORIGIN, tel.gnss.lat_deg, tel.gnss.lon_deg, tel.gnss.height_m)
    assert np.abs(z - truth.antenna_world_m - truth.gnss_error_m).max() < 1e-3
    assert truth.burst.any() and not clean_truth.burst.any()
    extra = truth.gnss_error_m - clean_truth.gnss_error_m  # only the bursts differ
    assert np.abs(extra[~truth.burst]).max() == 0.0
    mag = np.linalg.norm(extra[truth.burst], axis=1)
    assert mag.min() >= 5.0 - 1e-9 and mag.max() <= 20.0 + 1e-9
    # Without bursts: white 1.2 / 1.8 m plus drift, so 1-2.5 m per axis.
    sd = clean_truth.gnss_error_m.std(axis=0)
    assert np.all(sd[:2] > 0.8) and np.all(sd < 2.5)
    assert np.allclose(tel.imu.gyro_rad_s, clean.imu.gyro_rad_s)
    span = tel.span_s()
    assert span[0] <= 0.0 + s.clock_offset_s - 1.0 and span[1] >= flight.duration_s + 1.0


def test_csv_round_trip_through_the_reader(site, tmp_path):
    sign_map, flight = site
    sim = TelemetrySimSettings(gimbal_rate_hz=5.0)
    tel, _ = simulate_telemetry(flight, sign_map, np.random.default_rng(2), sim)
    path = tmp_path / "telemetry.csv"
    write_telemetry_csv(path, tel)
    back = read_telemetry_csv(path)
    assert len(back.gnss) == len(tel.gnss) and len(back.imu) == len(tel.imu)
    assert np.allclose(back.gnss.t_s, tel.gnss.t_s, atol=1e-6)
    assert np.allclose(back.gnss.lat_deg, tel.gnss.lat_deg, atol=1e-9)
    assert np.allclose(back.gnss.height_m, tel.gnss.height_m, atol=1e-4)
    assert np.allclose(back.gnss.sigma_h_m, tel.gnss.sigma_h_m)
    assert np.allclose(back.imu.gyro_rad_s, tel.imu.gyro_rad_s, atol=1e-8)
    assert np.allclose(back.imu.accel_m_s2, tel.imu.accel_m_s2, atol=1e-7)
    assert len(back.gimbal) == len(tel.gimbal) and not back.skipped
    assert np.allclose(back.gimbal.yaw_deg, tel.gimbal.yaw_deg, atol=1e-4)
    # The angles describe the camera: yaw within a few sigma of the truth.
    R = flight.rotations(tel.gimbal.t_s - sim.clock_offset_s)
    yaw_true = np.array([gimbal_from_world_R_cam(r)[0] for r in R])
    d = (tel.gimbal.yaw_deg - yaw_true + 180.0) % 360.0 - 180.0
    assert 1.0 < np.std(d) < 3.0 and abs(np.mean(d)) < 1.0


def test_flight_has_ten_seconds_without_signs(site):
    sign_map, flight = site
    gt = flight.trajectory(5.0)
    frames, _ = synthesize_observations(
        sign_map, pinhole_camera(1920, 1080, 60.0), gt, np.random.default_rng(0)
    )
    seen = np.array([len(f.signs) > 0 for f in frames])
    runs, run = [], 0
    for s in seen:
        run = 0 if s else run + 1
        runs.append(run)
    assert max(runs) / 5.0 >= 10.0
    assert seen[:20].all() and seen[-20:].all()  # signs at both ends
