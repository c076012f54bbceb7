"""A focal length the video cannot check: its stated sigma in the pose sigmas.

From one pylon face a focal length ``e`` off scales the camera-to-signs vector
by about ``1 + e`` and leaves the residuals as they are
(``estimator.intrinsics_share``): without ``focal_sigma_rel`` those poses are
``ok`` and far outside their sigmas; with it their sigmas cover the error.
"""

from dataclasses import replace

import numpy as np
import pytest
from conftest import estimator_scene
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.intrinsics_share import scene_to_camera_m, with_focal_share
from signpose.estimator.status import PoseStatus

FOCAL_OFF = 0.03


@pytest.fixture(scope="module")
def flight():
    sign_map, camera, frames, gt, _ = estimator_scene(n_frames=30, sigma_px=0.2, seed=5)
    K = camera.K.copy()
    K[0, 0] *= 1 + FOCAL_OFF
    K[1, 1] *= 1 + FOCAL_OFF
    wrong = replace(camera, K=K)
    s = replace(EstimatorSettings(), methods=("pnp", "smoothed"))
    s = replace(s, smoother=replace(s.smoother, landmarks="fixed"))
    silent = estimate_trajectories(frames, sign_map, wrong, s, False)
    told = estimate_trajectories(
        frames, sign_map, wrong, replace(s, focal_sigma_rel=FOCAL_OFF), False
    )
    return frames, sign_map, gt, silent, told


def _normalised_errors(method, gt):
    """|error| / sigma per axis of the ok and weak poses, and which those are."""
    ok = np.array([st in (PoseStatus.OK, PoseStatus.WEAK) for st in method.status])
    err = method.world_T_cam[:, :3, 3] - gt.world_t_cam
    return np.abs(err[ok]) / method.sigma_xyz[ok], ok


@pytest.mark.parametrize("name", ["pnp", "smoothed"])
def test_a_focal_length_off_is_silent_without_its_sigma(flight, name):
    _, _, gt, silent, _ = flight
    z, ok = _normalised_errors(silent.methods[name], gt)
    statuses = silent.methods[name].status
    assert np.mean([st is PoseStatus.OK for st in statuses]) > 0.8  # the poses look fine
    assert np.mean(np.max(z, axis=1) > 3) > 0.5


@pytest.mark.parametrize("name", ["pnp", "smoothed"])
def test_the_stated_focal_sigma_covers_the_error(flight, name):
    _, _, gt, silent, told = flight
    z, ok = _normalised_errors(told.methods[name], gt)
    assert ok.mean() > 0.8
    # the focal length is off by its stated sigma: a 1-sigma error on the line of sight
    assert np.median(np.max(z, axis=1)) < 2.0
    assert np.mean(np.max(z, axis=1) > 3) <= 0.1
    # 3 % of a 20-30 m range is beyond the weak limit: no pose is left ok
    assert not any(st is PoseStatus.OK for st in told.methods[name].status)
    # only the sigmas change, not the poses
    np.testing.assert_array_equal(told.methods[name].world_T_cam, silent.methods[name].world_T_cam)
    assert np.all(told.methods[name].sigma_xyz[ok] >= silent.methods[name].sigma_xyz[ok])


def test_the_share_is_the_focal_sigma_times_the_range(flight):
    frames, sign_map, _, silent, _ = flight
    m = silent.methods["pnp"]
    d = scene_to_camera_m(frames, sign_map, m.world_T_cam)
    shared = with_focal_share(m, frames, sign_map, 0.01, weak_sigma_m=np.inf)
    ok = np.isfinite(m.sigma_xyz).all(axis=1)
    np.testing.assert_allclose(
        shared.sigma_xyz[ok] ** 2 - m.sigma_xyz[ok] ** 2, (0.01 * d[ok]) ** 2, rtol=1e-9
    )
    assert shared.status == m.status
    # a sigma above the weak limit makes an ok pose weak, never the other way
    tight = with_focal_share(m, frames, sign_map, 0.01, weak_sigma_m=0.0)
    for before, after in zip(m.status, tight.status, strict=True):
        assert after is (PoseStatus.WEAK if before is PoseStatus.OK else before)
    assert with_focal_share(m, frames, sign_map, 0.0, weak_sigma_m=0.0) is m
