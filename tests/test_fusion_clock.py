"""The fusion's clock policy (issue 17): a GNSS-only scan does not crash, an SRT is on the
video's clock, a guessed clock is refused with one note instead of a silent fused result."""

from __future__ import annotations

import argparse
import math
from dataclasses import replace

import numpy as np
import pytest
from signpose.estimator.camera import pinhole_camera
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.fusion import (
    FusionSettings,
    body_T_cam_from_mounting,
    burst_fixes,
    clock_shift_limit_s,
    estimate_clock_offset,
    fuse_trajectory,
    on_smoother,
    vision_solve,
)
from signpose.estimator.smoother import SmootherSettings
from signpose.estimator.telemetry import GnssFixes, Telemetry
from signpose.maps.geodesy import GeoOrigin, geodetic_from_enu
from signpose.maps.loader import bundled_map_path, load_map

from signpose.cli import main
from signpose.cli.run import fusion_settings
from signpose.io.telemetry import TelemetryRequest
from signpose.io.telemetry_srt import read_srt
from signpose.sim.observations import synthesize_observations
from signpose.sim.telemetry import (
    TelemetrySimSettings,
    away_and_back,
    default_body_T_cam,
    simulate_telemetry,
)

ORIGIN = GeoOrigin(47.0, 8.0, 500.0)


def _line_flight(n: int, fps: float, speed: float, turn: bool):
    """(N, 4, 4) poses along x at ``speed`` [m/s] (with ``turn``: a sideways swing)."""
    t = np.arange(n) / fps
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = speed * t
    if turn:
        T[:, 1, 3] = 6.0 * np.sin(2 * np.pi * t / 4.0)
    return t, T


def _gnss(t_tel: np.ndarray, enu: np.ndarray, sigma: float, rng) -> Telemetry:
    noisy = enu + rng.normal(0.0, sigma, enu.shape)
    lat, lon, h = geodetic_from_enu(ORIGIN, noisy)
    n = len(t_tel)
    fixes = GnssFixes(t_tel, lat, lon, h, np.full(n, sigma), np.full(n, 2 * sigma))
    return Telemetry(source="gnss.csv", gnss=fixes)


@pytest.fixture(scope="module")
def sign_map():
    return replace(load_map(bundled_map_path()), origin=ORIGIN)


def test_gnss_only_scan_whose_fixes_leave_the_overlap_does_not_crash(sign_map):
    """Regression: the Gauss-Newton step compared residuals of 13 and 12 fixes (ValueError)."""
    t, T = _line_flight(90, 30.0, 3.0, turn=False)  # 3 s of video, fixes at 10 Hz
    tg = np.arange(0.037, 3.0, 0.1)
    enu = np.stack([np.interp(tg, t, T[:, 0, 3]), 0 * tg, 0 * tg], 1)
    tel = _gnss(tg + 0.25, enu, 1.5, np.random.default_rng(0))
    s = FusionSettings(use_imu=False)
    c = estimate_clock_offset(T, t, np.ones(len(t), bool), tel, sign_map, s)
    assert c.source == "gnss" and math.isfinite(c.offset_s)
    # A straight line at constant speed: a time shift is a position offset, which the
    # GNSS error absorbs; the scan must not claim to know the clock.
    limit = clock_shift_limit_s(T, t, np.ones(len(t), bool), 1.5, s)
    assert not c.sigma_s <= limit


def test_gnss_only_clock_with_turns_is_found_within_its_sigma(sign_map):
    t, T = _line_flight(200, 10.0, 3.0, turn=True)
    tg = np.arange(0.05, 20.0, 0.1)
    enu = np.stack([np.interp(tg, t, T[:, k, 3]) for k in range(3)], 1)
    tel = _gnss(tg + 0.4, enu, 0.5, np.random.default_rng(1))
    c = estimate_clock_offset(
        T, t, np.ones(len(t), bool), tel, sign_map, FusionSettings(use_imu=False)
    )
    assert c.source == "gnss" and 0 < c.sigma_s < 0.05
    assert abs(c.offset_s - 0.4) < 3 * c.sigma_s


def test_an_srt_sidecar_is_on_the_video_clock_unless_an_offset_is_given(sign_map, tmp_path):
    srt = tmp_path / "clip.SRT"
    srt.write_text(
        "1\n00:00:00,000 --> 00:00:00,033\n[latitude: 47.0] [longitude: 8.0] [abs_alt: 500.0]\n\n"
        "2\n00:00:00,033 --> 00:00:00,066\n[latitude: 47.0] [longitude: 8.00001] [abs_alt: 500]\n"
    )
    tel = read_srt(srt, video_start_s=10.0)
    assert tel.clock_is_video
    t, T = _line_flight(3, 30.0, 1.0, turn=False)
    args = (T, t + 10.0, np.ones(3, bool), tel, sign_map)
    c = estimate_clock_offset(*args, FusionSettings())
    assert (c.offset_s, c.sigma_s, c.source) == (0.0, 0.0, "video")
    c = estimate_clock_offset(*args, FusionSettings(clock_offset_s=0.2))
    assert (c.offset_s, c.source) == (0.2, "fixed")
    assert not Telemetry(source="x.csv").clock_is_video  # other readers: estimated


@pytest.fixture(scope="module")
def flight(sign_map):
    """A 30 s flight at 2 fps (GNSS 10 Hz, no IMU), telemetry 0.3 s late."""
    camera = pinhole_camera(1920, 1080, 60.0)
    truth = away_and_back(sign_map, seed=1)
    gt = truth.trajectory(2.0)
    frames, _ = synthesize_observations(sign_map, camera, gt, np.random.default_rng(5))
    sim = TelemetrySimSettings(clock_offset_s=0.3)
    tel, _ = simulate_telemetry(truth, sign_map, np.random.default_rng(6), sim)
    settings = FusionSettings(
        use_imu=False,
        cam_t_antenna_m=sim.cam_t_antenna_m,
        body_T_cam=tuple(map(tuple, default_body_T_cam())),
    )
    vision = vision_solve(frames, sign_map, camera, gt.stamps_s, settings.smoother)
    tel = replace(tel, imu=None)
    given = fuse_trajectory(
        frames, sign_map, camera, gt.stamps_s, tel, replace(settings, clock_offset_s=0.3), vision
    )
    return dict(camera=camera, gt=gt, frames=frames, tel=tel, s=settings, v=vision, given=given)


def test_a_guessed_clock_refuses_the_fusion_with_one_note(flight, sign_map):
    f = flight
    r = fuse_trajectory(
        f["frames"], sign_map, f["camera"], f["gt"].stamps_s, f["tel"], f["s"], f["v"]
    )
    assert r.refused and r.counts["refused"] == 1
    assert (r.clock.offset_s, r.clock.source) == (0.0, "none")  # the guess is not used
    assert np.array_equal(r.world_T_cam, f["v"].world_T_cam)  # the vision poses, as they were
    (note,) = r.notes
    assert "not determined from GNSS alone" in note and "give --telemetry-offset" in note
    assert str(f["tel"].source) in note
    given = f["given"]
    assert not given.refused and given.notes == () and given.counts["gnss_used"] > 100


def test_without_imu_gnss_does_not_pull_the_poses_where_signs_are_seen(flight):
    """No IMU, clock given: where signs are seen the fused pose is within the vision pose's
    noise; where none is, the pose is a bridge with a GNSS-sized sigma, never 'ok'."""
    f = flight
    r, v, truth = f["given"], f["v"], f["gt"].world_t_cam
    seen = v.observed
    assert 10 < seen.sum() < len(seen) - 10  # both kinds of frames
    moved = np.linalg.norm(r.world_T_cam[seen, :3, 3] - v.world_T_cam[seen, :3, 3], axis=1)
    sigma_v = np.linalg.norm(v.sigma_xyz[seen], axis=1)
    assert np.all(moved <= 3 * sigma_v)
    err_f = np.linalg.norm(r.world_T_cam[seen, :3, 3] - truth[seen], axis=1)
    err_v = np.linalg.norm(v.world_T_cam[seen, :3, 3] - truth[seen], axis=1)
    assert np.sqrt(np.mean(err_f**2)) <= 1.05 * np.sqrt(np.mean(err_v**2))
    gap = ~seen
    assert all(r.status[i].value in ("weak", "bridged") for i in np.nonzero(gap)[0])
    sig = np.linalg.norm(r.sigma_xyz[gap], axis=1)
    assert np.all(np.isfinite(sig)) and np.median(sig) > 0.5  # GNSS-sized, not the signs'


def test_the_fused_graph_takes_the_runs_smoother_settings():
    run = SmootherSettings(landmarks="fixed", cv_sigma_acc=32.0, kernel="huber", tukey_k=9.0)
    s = on_smoother(FusionSettings(clock_offset_s=0.1), run)
    assert s.clock_offset_s == 0.1
    assert (s.smoother.landmarks, s.smoother.cv_sigma_acc) == ("fixed", 32.0)
    assert (s.smoother.kernel, s.smoother.tukey_k) == (FusionSettings().smoother.kernel, 4.685)


def test_estimate_trajectories_has_no_fused_method_on_a_guessed_clock(flight, sign_map):
    f = flight
    settings = EstimatorSettings(methods=("smoothed",), tune_motion=False)
    r = estimate_trajectories(
        f["frames"],
        sign_map,
        f["camera"],
        settings,
        progress=False,
        telemetry=f["tel"],
        fusion=f["s"],
    )
    assert "fused" not in r.methods and "smoothed" in r.methods
    assert r.fusion is not None and r.fusion.refused


def test_mounting_angles_turn_the_default_camera():
    # Written out, not derived: the camera looks along body x (FLU), image right = body -y,
    # image down = body -z (the simulator's default_body_T_cam is now this very function).
    looking_forward = [[0, 0, 1, 0], [-1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 0, 1]]
    assert np.allclose(body_T_cam_from_mounting(0, 0, 0), looking_forward)
    assert np.allclose(default_body_T_cam(), looking_forward)
    T = np.array(body_T_cam_from_mounting(0.0, 45.0, 0.0))
    h = math.sqrt(0.5)
    assert np.allclose(T[:3, 2], [h, 0, -h])  # optical axis 45 deg down (FLU)
    assert np.allclose(np.array(body_T_cam_from_mounting(0, 0, 90.0))[:3, 2], [0, 1, 0])  # left
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3))


def test_geometry_options_reach_the_fusion_and_bad_ones_exit_2(tmp_path, capsys):
    ns = argparse.Namespace(antenna_offset="0.1,-0.2,0.05", imu_to_camera="0,30,0")
    request = TelemetryRequest(tmp_path / "t.csv", None, 0.2)
    s = fusion_settings(ns, request)
    assert s.cam_t_antenna_m == (0.1, -0.2, 0.05) and s.clock_offset_s == 0.2
    assert np.allclose(s.body_T_cam, body_T_cam_from_mounting(0, 30, 0))
    base = ["run", str(tmp_path / "v.mp4"), "--map", str(bundled_map_path())]
    base += ["--out", str(tmp_path / "out")]
    tel = ["--telemetry", str(tmp_path / "t.csv")]
    for extra, message in (
        (["--antenna-offset", "0.1,0.2", *tel], "--antenna-offset 0.1,0.2: give X,Y,Z"),
        (["--imu-to-camera", "0,nan,0", *tel], "--imu-to-camera 0,nan,0: give roll,pitch"),
        (["--antenna-offset", "0,0,0.1"], "--antenna-offset needs --telemetry FILE"),
    ):
        assert main(base + extra) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0]


def test_bursts_told_from_the_gnss_track_alone():
    """A turning track at 10 Hz, 1.2 m noise, two bursts (6 m for 2 s, 15 m for 1 s)."""
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 40.0, 0.1)
    track = np.stack([4.0 * np.cos(t / 3), 4.0 * np.sin(t / 3) * 3, 0.2 * t], 1)  # 4 m/s turns
    burst = ((t >= 10) & (t < 12)) | ((t >= 25) & (t < 26))
    clean = track + rng.normal(0.0, 1.0, track.shape) * [1.2, 1.2, 1.8]
    z = clean.copy()
    z[(t >= 10) & (t < 12)] += [4.0, -4.0, 2.0]
    z[(t >= 25) & (t < 26)] += [0.0, 15.0, 0.0]
    sigma = np.tile([1.2, 1.2, 1.8], (len(t), 1))
    found = burst_fixes(t, z, sigma)
    assert (found & burst).sum() >= 0.9 * burst.sum()
    assert (found & ~burst).sum() <= 0.02 * (~burst).sum()
    assert burst_fixes(t, clean, sigma).sum() <= 0.02 * len(t)  # no burst: ~nothing flagged


def test_a_video_clock_is_fused_at_offset_0_and_said(flight, sign_map):
    f = flight
    srt_like = replace(f["tel"], clock_is_video=True, source="clip.SRT")
    r = fuse_trajectory(
        f["frames"], sign_map, f["camera"], f["gt"].stamps_s, srt_like, f["s"], f["v"]
    )
    assert not r.refused and (r.clock.offset_s, r.clock.source) == (0.0, "video")
    (note,) = r.notes
    assert note.startswith("clock: clip.SRT is on the video's own clock")
