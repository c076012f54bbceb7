"""The causal (iSAM2 filter) method carries sigmas and its own statuses.

Before, its sigma columns were empty and every observed frame was ``ok``: a
pose no user could weigh. Now its sigmas are the filter's marginal of each
newest pose, and its statuses the residual test at the filter's poses.
"""

from dataclasses import replace

import numpy as np
import pytest
from conftest import estimator_scene
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.status import PoseStatus


@pytest.fixture(scope="module")
def run():
    sign_map, camera, frames, gt, _ = estimator_scene(n_frames=40, sigma_px=0.3, seed=1)
    s = replace(EstimatorSettings(), methods=("pnp", "smoothed"), solver="isam2")
    return estimate_trajectories(frames, sign_map, camera, s, False), gt, frames


def test_causal_poses_have_sigmas_that_hold(run):
    result, gt, _ = run
    m = result.methods["causal"]
    assert np.all(np.isfinite(m.sigma_xyz[m.valid]))
    z = (m.world_T_cam[:, :3, 3] - gt.world_t_cam)[m.valid] / m.sigma_xyz[m.valid]
    rms = np.sqrt(np.mean(z**2, axis=0))
    assert np.all((rms > 0.3) & (rms < 1.5)), rms
    assert np.mean(np.max(np.abs(z), axis=1) > 3) < 0.05


def test_the_filter_is_less_certain_than_the_smoother_at_the_start(run):
    """The first frames: the filter has seen only them, the smoother the whole flight."""
    result, _, _ = run
    causal, smoothed = result.methods["causal"], result.methods["smoothed"]
    assert np.all(
        np.linalg.norm(causal.sigma_xyz[:3], axis=1)
        > np.linalg.norm(smoothed.sigma_xyz[:3], axis=1)
    )


def test_a_filter_pose_off_its_keypoints_is_suspect(monkeypatch):
    """The filter's pose of frame 20 moved 0.5 m (as an outlier the filter took before
    the innovation test would): ``suspect``, not ``ok`` (was: ``ok`` when observed)."""
    from signpose.estimator import estimate as est

    real = est.smooth_isam2

    def shifted(*args, **kwargs):
        r = real(*args, **kwargs)
        T = r.causal_world_T_cam.copy()
        T[20, :3, 3] += 0.5
        return replace(r, causal_world_T_cam=T)

    monkeypatch.setattr(est, "smooth_isam2", shifted)
    sign_map, camera, frames, _, _ = estimator_scene(n_frames=40, sigma_px=0.3, seed=1)
    s = replace(EstimatorSettings(), methods=("pnp", "smoothed"), solver="isam2")
    status = estimate_trajectories(frames, sign_map, camera, s, False).methods["causal"].status
    assert status[20] is PoseStatus.SUSPECT
    assert sum(st is PoseStatus.OK for st in status) == len(status) - 1
