"""The flight's a posteriori pixel noise scale (estimator/noise_scale.py)."""

from dataclasses import replace

import numpy as np
import pytest
from conftest import estimator_scene
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.noise_scale import (
    exact_map_pose,
    inflated_pose,
    pixel_noise_scale,
    pose_noise_scale,
    residual_noise_scale,
    scaled_frames,
    scaled_pose,
)
from signpose.estimator.perframe import FramePose
from signpose.estimator.status import PoseStatus


def _poses(rng, n, scale, keypoints=20):
    """Poses on an exact map: the chi-square with the survey noise is the pixel one."""
    dof = 2 * keypoints - 6
    chi2 = scale**2 * rng.chisquare(dof, n)
    return [
        FramePose(
            i,
            i,
            np.eye(4),
            keypoints_used=keypoints,
            chi2=float(c),
            cov6=np.eye(6),
            chi2_map=float(c),
        )
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
    wild = [replace(p, chi2=p.chi2 * 400, chi2_map=p.chi2 * 400) for p in poses[:30]]
    assert pixel_noise_scale(wild + poses[30:]) == pytest.approx(1.5, rel=0.12)


def test_survey_errors_are_not_taken_as_pixel_noise():
    # A surveyed map's own error inflates the pixel-only chi-square tenfold;
    # whitened with the survey noise too, the residuals are as claimed.
    rng = np.random.default_rng(4)
    poses = [replace(p, chi2=100 * p.chi2) for p in _poses(rng, 300, 1.0)]
    assert pixel_noise_scale(poses) == pytest.approx(1.0, abs=0.05)
    assert pixel_noise_scale([exact_map_pose(p) for p in poses]) == pytest.approx(10.0, rel=0.05)


def test_only_the_pixel_share_of_a_covariance_scales():
    pixel, survey = np.diag([1.0, 1, 1, 2, 2, 2]), np.diag([0.0, 0, 0, 5, 5, 5])
    p = FramePose(
        0, 0, np.eye(4), keypoints_used=10, chi2=8.0, chi2_map=6.0,
        cov6=pixel + survey, cov6_pixel=pixel,
    )  # fmt: skip
    q = scaled_pose(p, 2.0)
    assert np.allclose(q.cov6_pixel, 4 * pixel) and np.allclose(q.cov6, 4 * pixel + survey)
    assert q.chi2 == 2.0 and q.chi2_map == 1.5
    e = exact_map_pose(p)
    assert np.allclose(e.cov6, pixel) and e.chi2_map == 8.0


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


def _pose_pairs(rng, n, k):
    """PnP poses scattering k times their claimed share about a smoothed trajectory."""
    c_pnp, c_sm = np.diag([4e-4, 1e-4, 9e-4]), np.diag([1e-4, 2e-5, 1e-4])
    cov_pnp, cov_sm = np.zeros((6, 6)), np.zeros((n, 6, 6))
    cov_pnp[3:, 3:] = c_pnp
    cov_sm[:, 3:, 3:] = c_sm
    smoothed = np.tile(np.eye(4), (n, 1, 1))
    d = rng.multivariate_normal(np.zeros(3), k**2 * (c_pnp - c_sm), n)
    poses = []
    for i in range(n):
        T = np.eye(4)
        T[:3, 3] = d[i]
        poses.append(FramePose(i, i, T, keypoints_used=20, cov6=cov_pnp, cov6_pixel=cov_pnp))
    return poses, smoothed, cov_sm


@pytest.mark.parametrize("k", [1.0, 1.4, 2.0])
def test_pose_scale_from_pnp_scatter_about_the_smoothed_poses(k):
    rng = np.random.default_rng(5)
    poses, smoothed, cov_sm = _pose_pairs(rng, 400, k)
    assert pose_noise_scale(poses, smoothed, cov_sm) == pytest.approx(k, rel=0.08)
    assert pose_noise_scale(poses, smoothed, None) == 1.0
    assert pose_noise_scale(poses[:9], smoothed, cov_sm) == 1.0
    q = inflated_pose(replace(poses[0], chi2=5.0, chi2_map=4.0), 2.0)
    assert np.allclose(q.cov6, 4 * poses[0].cov6) and np.allclose(q.cov6_pixel, q.cov6)
    assert (q.chi2, q.chi2_map) == (5.0, 4.0)  # the residuals' tests are not relaxed


def test_pose_scale_never_below_one_and_skips_frames_the_smoother_does_not_improve():
    rng = np.random.default_rng(6)
    poses, smoothed, cov_sm = _pose_pairs(rng, 200, 0.5)
    assert pose_noise_scale(poses, smoothed, cov_sm) == 1.0
    poses, smoothed, _ = _pose_pairs(rng, 200, 3.0)
    same = np.repeat(poses[0].cov6[None], 200, axis=0)  # no better than PnP: no test
    assert pose_noise_scale(poses, smoothed, same) == 1.0


def test_an_honest_flight_on_an_exact_map_keeps_its_pose_sigmas():
    sign_map, camera, frames, _, _ = estimator_scene(n_frames=60, sigma_px=0.4, seed=4)
    s = replace(EstimatorSettings(), methods=("pnp", "smoothed"))
    s = replace(s, smoother=replace(s.smoother, landmarks="fixed"))
    r = estimate_trajectories(frames, sign_map, camera, s, False)
    assert 1.0 <= r.pose_noise_scale < 1.2


@pytest.mark.parametrize("scale", [1.0, 1.3, 2.0])
def test_residual_scale_of_chi_square_frames(scale):
    # 300 frames of 10-20 keypoints, each keypoint's whitened chi2 (2 dof) scaled
    rng = np.random.default_rng(7)
    k = rng.integers(10, 21, 300)
    frame = np.repeat(np.arange(300), k)
    # a frame's residuals keep 2k - 6 dof: draw its total and share it out
    total = scale**2 * rng.chisquare(2 * k - 6)
    chi2 = np.repeat(total / k, k)
    got = residual_noise_scale(chi2, frame, 300)
    assert got == pytest.approx(scale, rel=0.05) if scale > 1 else 1.0 <= got < 1.05
    assert residual_noise_scale(chi2[:50], frame[:50], 300) == 1.0  # too few frames


def test_residual_scale_sees_a_heavy_tail_the_median_passes():
    rng = np.random.default_rng(8)
    k = np.full(400, 15)
    frame = np.repeat(np.arange(400), k)
    # 40 % of the frames scatter twice their sigmas: the median frame is fine
    s = np.where(rng.random(400) < 0.4, 2.0, 1.0)
    total = s**2 * rng.chisquare(2 * k - 6)
    assert residual_noise_scale(np.repeat(total / k, k), frame, 400) > 1.3
