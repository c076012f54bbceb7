"""iSAM2 in a bounded window (SmootherSettings.isam_window_frames): bounded state, batch result."""

from dataclasses import replace

import numpy as np
import pytest
from conftest import estimator_scene
from signpose.estimator import smoother as sm
from signpose.estimator.perframe import run_per_frame


@pytest.fixture(scope="module")
def flight():
    sign_map, camera, frames, gt, _ = estimator_scene(
        n_frames=60, sigma_px=0.4, seed=1, flat=False, duration_s=7.0
    )
    meas = sm.collect_measurements(frames, sign_map, camera)
    stamps = np.array([f.stamp_ns for f in frames], float) * 1e-9
    init = [p.world_T_cam for p in run_per_frame(frames, sign_map, camera, "pnp")]
    return meas, stamps, init, camera, sm.default_pose(sign_map), gt


@pytest.mark.parametrize("motion", [sm.CONSTANT_VELOCITY, sm.RANDOM_WALK])
def test_windowed_isam2_final_and_sigmas_match_batch(flight, motion):
    meas, stamps, init, camera, default, gt = flight
    base = sm.SmootherSettings(motion=motion, landmarks=sm.KEYPOINTS, isam_segment_frames=7)
    batch = sm.smooth_batch(meas, stamps, init, camera, base, default)
    windowed = replace(base, isam_window_frames=20)
    r = sm.smooth_isam2(meas, stamps, init, camera, windowed, default)
    d = np.linalg.norm(r.world_T_cam[:, :3, 3] - batch.world_T_cam[:, :3, 3], axis=1)
    # Frames left iSAM2 linearised where the running estimate was then (cm from
    # the end result); the sweeps take it to the batch solution (0.08 / 0.10 mm).
    assert d.max() < 1e-3
    err = np.abs(gt.world_t_cam - r.world_T_cam[:, :3, 3]).mean()
    assert err < np.abs(gt.world_t_cam - batch.world_T_cam[:, :3, 3]).mean() + 0.005
    # The covariances from the last sweep's conditionals: batch's to 0.1 %.
    assert np.all(np.abs(r.sigma_xyz / batch.sigma_xyz - 1) < 1e-3)
    assert np.all(np.isfinite(r.causal_world_T_cam))
    # The causal estimate is iSAM2's right after each frame: not the smoothed one.
    assert np.abs(r.causal_world_T_cam - r.world_T_cam).max() > 1e-4


def test_window_bounds_the_running_state(flight):
    meas, stamps, init, camera, default, _ = flight
    s = sm.SmootherSettings(landmarks=sm.KEYPOINTS, isam_window_frames=10, isam_segment_frames=5)
    run = sm._Isam2Run(sm._GraphBuilder(meas, stamps, camera, s), default)
    sizes = []
    for i in range(meas.n_frames):
        run.add_frame(i, init[i])
        sizes.append(run.isam.getLinearizationPoint().size())
    # Variables held after the window first filled: never more than at its first
    # fill, whatever the flight's length; without a window, every frame's.
    assert max(sizes[11:]) <= max(sizes[:11])
    assert len(run.written) == (meas.n_frames - 1) // 10
    whole = sm._Isam2Run(
        sm._GraphBuilder(meas, stamps, camera, replace(s, isam_window_frames=0)), default
    )
    for i in range(meas.n_frames):
        whole.add_frame(i, init[i])
    held = whole.isam.getLinearizationPoint().size()
    assert held > 2 * meas.n_frames and held > 3 * sizes[-1]
