"""What each iSAM2 update re-eliminates and relinearises (the per-frame cost of smooth_isam2)."""

from dataclasses import replace

import numpy as np
import pytest
from conftest import estimator_scene
from signpose.estimator import smoother as sm
from signpose.estimator.perframe import run_per_frame


@pytest.fixture(scope="module")
def flight():
    sign_map, camera, frames, _, _ = estimator_scene(
        n_frames=60, sigma_px=0.4, seed=1, flat=False, duration_s=7.0
    )
    meas = sm.collect_measurements(frames, sign_map, camera)
    stamps = np.array([f.stamp_ns for f in frames], float) * 1e-9
    init = [p.world_T_cam for p in run_per_frame(frames, sign_map, camera, "pnp")]
    return meas, stamps, init, camera, sm.default_pose(sign_map)


def _updates(flight, s: sm.SmootherSettings) -> list:
    meas, stamps, init, camera, default = flight
    run = sm._Isam2Run(sm._GraphBuilder(meas, stamps, camera, s), default)
    out = []
    for i in range(meas.n_frames):
        run.add_frame(i, init[i])
        res = run.last_update
        out.append((res.getVariablesReeliminated(), res.getVariablesRelinearized()))
    return out


def test_updates_in_a_first_segment_stay_at_the_top_of_the_tree(flight):
    # One segment, no window: 60 frames on the same landmark variables. Each
    # update re-eliminates the landmarks and the newest frames only; with the
    # previous frame left anywhere by a batch reordering, every update of the
    # segment re-eliminated the whole tree (40 -> 120 variables by frame 40).
    s = sm.SmootherSettings(
        landmarks=sm.KEYPOINTS,
        isam_segment_frames=0,
        isam_window_frames=0,
        isam_relinearize_skip=1000,
    )
    reelim = [r for r, _ in _updates(flight, s)]
    assert max(reelim[25:]) <= reelim[25] + 4
    assert reelim[-1] < 0.6 * (2 * 60 + 40)  # fewer than the variables held


def test_old_velocities_and_a_coarser_velocity_threshold_relinearise_fewer(flight):
    base = sm.SmootherSettings(landmarks=sm.KEYPOINTS, isam_window_frames=0)
    every = replace(base, isam_relinearize_recent_frames=0)
    n_every = sum(r for _, r in _updates(flight, every))
    n_recent = sum(r for _, r in _updates(flight, replace(every, isam_relinearize_recent_frames=5)))
    coarse = replace(every, isam_relinearize_velocity_mps=1.0)
    n_coarse = sum(r for _, r in _updates(flight, coarse))
    assert n_recent < n_every and n_coarse < n_every


def test_the_causal_estimate_keeps_relinearising_recent_frames(flight):
    meas, stamps, init, camera, default = flight
    s = sm.SmootherSettings(landmarks=sm.KEYPOINTS, isam_segment_frames=7, isam_window_frames=20)
    a = sm.smooth_isam2(meas, stamps, init, camera, s, default)
    b = sm.smooth_isam2(
        meas, stamps, init, camera, replace(s, isam_relinearize_recent_frames=0), default
    )
    # The final estimate does not depend on it (the sweeps converge); the
    # causal one only through old velocities' linearisation points.
    assert np.abs(a.world_T_cam[:, :3, 3] - b.world_T_cam[:, :3, 3]).max() < 1e-4
    assert np.abs(a.causal_world_T_cam[:, :3, 3] - b.causal_world_T_cam[:, :3, 3]).max() < 0.02
