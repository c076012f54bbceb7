"""Landmark models: rigid signs, keypoints, the fixed map."""

import numpy as np
import pytest
from conftest import estimator_scene
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.smoother import (
    SmootherSettings,
    collect_measurements,
    default_pose,
    smooth_batch,
)


def _offsets(meas, landmarks_world):
    """(L, 3) each keypoint landmark minus its sign's centre landmark."""
    centre = {
        c: landmarks_world[j]
        for j, (c, n) in enumerate(zip(meas.landmark_code, meas.landmark_name, strict=True))
        if n == "center"
    }
    return np.array([landmarks_world[j] - centre[c] for j, c in enumerate(meas.landmark_code)])


@pytest.mark.parametrize("model", ["rigid-exact", "rigid", "keypoints", "fixed"])
def test_landmark_models_keep_what_they_promise(model):
    sign_map, camera, frames, gt, _ = estimator_scene(n_frames=30, sigma_px=0.5, seed=5, flat=False)
    meas = collect_measurements(frames, sign_map, camera)
    s = SmootherSettings(landmarks=model.removesuffix("-exact"), compute_sigmas=False)
    if model == "rigid-exact":
        s = SmootherSettings(landmarks="rigid", rigid_tie_sigma_m=1e-5, compute_sigmas=False)
    r = smooth_batch(meas, gt.stamps_s, list(gt.world_T_cam()), camera, s, default_pose(sign_map))
    moved = np.abs(_offsets(meas, r.landmarks_world) - _offsets(meas, meas.landmark_world)).max()
    shift = np.abs(r.landmarks_world - meas.landmark_world).max()
    if model == "rigid-exact":  # a sign moves as one body
        assert moved < 1e-4 and shift > 1e-4
    elif model == "rigid":  # ... up to its printing and hanging tolerance
        assert moved < 3 * s.rigid_tie_sigma_m and shift > 1e-4
    elif model == "keypoints":  # each keypoint on its own
        assert moved > 1e-4
    else:  # the survey as exact
        assert shift < 1e-5


def test_map_fixed_through_the_estimator():
    sign_map, camera, frames, gt, _ = estimator_scene(n_frames=20, sigma_px=0.3, flat=False)
    s = EstimatorSettings(methods=("smoothed",), smoother=SmootherSettings(landmarks="fixed"))
    r = estimate_trajectories(frames, sign_map, camera, s, progress=False)
    err = np.abs(r.methods["smoothed"].world_T_cam[:, :3, 3] - gt.world_t_cam)
    assert err.max() < 0.3
    with pytest.raises(ValueError, match="landmark model"):
        bad = EstimatorSettings(methods=("smoothed",), smoother=SmootherSettings(landmarks="x"))
        estimate_trajectories(frames, sign_map, camera, bad, progress=False)
