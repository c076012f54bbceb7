"""The flight's a posteriori pixel noise scale (estimator/noise_scale.py)."""

from dataclasses import replace

import numpy as np
import pytest
from conftest import estimator_scene
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.noise_scale import pixel_noise_scale, scaled_frames, scaled_pose
from signpose.estimator.perframe import FramePose
from signpose.estimator.status import PoseStatus


def _poses(rng, n, scale, keypoints=20):
    dof = 2 * keypoints - 6
    chi2 = scale**2 * rng.chisquare(dof, n)
    return [
        FramePose(i, i, np.eye(4), keypoints_used=keypoints, chi2=float(c), cov6=np.eye(6))
        for i, c in enumerate(chi2)
    ]


@pytest.mark.parametrize("scale", [1.5, 2.0, 3.0])
def test_the_scale_of_chi_square_residuals_is_recovered(scale):
    rng = np.random.default_rng(1)
    assert pixel_noise_scale(_poses(rng, 300, scale)) == pytest.approx(scale, rel=0.04)


def test_never_below_one_and_none_from_few_frames():
    rng = np.random.default_rng(2)
    assert pixel_noise_scale(_poses(rng, 300, 0.5)) == 1.0
    assert pixel_noise_scale(_poses(rng, 9, 3.0)) == 1.0
    assert pixel_noise_scale(_poses(rng, 10, 3.0)) > 2.0
    # frames without a pose or without residual freedom say nothing
    unposed = [FramePose(i, i, None) for i in range(50)]
    three = [replace(p, keypoints_used=3) for p in _poses(rng, 50, 3.0)]
    assert pixel_noise_scale(unposed + three) == 1.0


def test_a_tenth_of_wild_frames_barely_moves_it():
    rng = np.random.default_rng(3)
    poses = _poses(rng, 300, 1.5)
    wild = [replace(p, chi2=p.chi2 * 400) for p in poses[:30]]
    assert pixel_noise_scale(wild + poses[30:]) == pytest.approx(1.5, rel=0.12)


def test_scaling_a_pose_and_frames():
    p = FramePose(0, 0, np.eye(4), keypoints_used=10, chi2=8.0, cov6=np.eye(6))
    q = scaled_pose(p, 2.0)
    assert q.chi2 == 2.0 and np.allclose(q.cov6, 4 * np.eye(6))
    assert scaled_pose(p, 1.0) is p
    _, _, frames, _, _ = estimator_scene(n_frames=3, sigma_px=0.2)
    # the synthetic signs carry no per-keypoint sigmas: give them some
    frames = [
        replace(
            f,
            signs=tuple(
                replace(o, keypoint_sigma_px={k: (0.1, 0.2) for k in o.keypoints_px})
                for o in f.signs
            ),
        )
        for f in frames
    ]
    assert any(o.keypoint_sigma_px for f in frames for o in f.signs)
    out = scaled_frames(frames, 3.0)
    assert scaled_frames(frames, 1.0) is frames
    for f, g in zip(frames, out, strict=True):
        for a, b in zip(f.signs, g.signs, strict=True):
            assert b.sigma_px == pytest.approx(3 * a.sigma_px)
            assert b.keypoints_px == a.keypoints_px
            for k, (su, sv) in a.keypoint_sigma_px.items():
                assert b.keypoint_sigma_px[k] == pytest.approx((3 * su, 3 * sv))


def _claiming(frames, sigma_px):
    return [replace(f, signs=tuple(replace(o, sigma_px=sigma_px) for o in f.signs)) for f in frames]


@pytest.fixture(scope="module")
def optimistic():
    """A flight whose keypoints scatter 0.4 px while they claim 0.2 px."""
    sign_map, camera, frames, gt, _ = estimator_scene(n_frames=60, sigma_px=0.4, seed=4)
    methods = ("pnp", "smoothed")
    runs = {}
    for on in (False, True):
        s = replace(EstimatorSettings(), methods=methods, scale_pixel_noise=on)
        runs[on] = estimate_trajectories(_claiming(frames, 0.2), sign_map, camera, s, False)
    honest = estimate_trajectories(
        frames, sign_map, camera, replace(EstimatorSettings(), methods=methods), False
    )
    return runs, honest


def test_optimistic_sigmas_are_found_and_scaled(optimistic):
    runs, honest = optimistic
    assert runs[False].pixel_noise_scale == 1.0
    assert runs[True].pixel_noise_scale == pytest.approx(2.0, rel=0.12)
    # sigmas that were right are left alone
    assert 1.0 <= honest.pixel_noise_scale < 1.15


def test_scaled_run_flags_as_the_honest_one_does(optimistic):
    runs, honest = optimistic

    def suspect(r, m):
        return np.mean([s is PoseStatus.SUSPECT for s in r.methods[m].status])

    # 2x optimistic sigmas fail the chi-square test on most frames...
    assert suspect(runs[False], "pnp") > 0.5
    # ...the scaled run flags like the run whose sigmas were right
    assert suspect(runs[True], "pnp") <= suspect(honest, "pnp") + 0.05
    assert suspect(runs[True], "smoothed") <= suspect(honest, "smoothed") + 0.05
    # and its pose sigmas grew to the honest run's (the survey's share does not scale)
    a = np.nanmedian(runs[False].methods["smoothed"].sigma_xyz, axis=0)
    b = np.nanmedian(runs[True].methods["smoothed"].sigma_xyz, axis=0)
    c = np.nanmedian(honest.methods["smoothed"].sigma_xyz, axis=0)
    assert np.all(b > a) and np.max(b / a) > 1.2
    assert np.allclose(b, c, rtol=0.1)
