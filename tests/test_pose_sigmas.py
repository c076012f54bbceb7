"""Pose sigmas a user can bet on: per-keypoint, per-axis pixel sigmas in PnP and the
smoother, PnP's pixel and survey shares, the baseline's refusal (issue 11, item 3)."""

from dataclasses import replace

import numpy as np
import pytest
from conftest import estimator_scene
from signpose.estimator.camera import pinhole_camera
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.fusion import FusionSettings, _inliers, vision_solve
from signpose.estimator.perframe import solve_frame_pnp
from signpose.estimator.projection import pixels_and_pose_jacobian, pose_fit
from signpose.estimator.smoother import (
    SmootherSettings,
    collect_measurements,
    default_pose,
    whitened_chi2,
)
from signpose.estimator.status import PoseStatus
from signpose.estimator.tuning import _held_out_score


def _scene(rng, n_signs=6, per_sign=4):
    """(camera, (4, 4) pose, (K, 3) world points, (K,) sign of each) of a frame of signs."""
    camera = pinhole_camera(1280, 720, 60.0)
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, -25.0]
    centres = np.column_stack([rng.uniform(-4, 4, n_signs), rng.uniform(-3, 3, n_signs),
                               rng.uniform(-1.5, 1.5, n_signs)])  # fmt: skip
    offsets = rng.uniform(-0.3, 0.3, (n_signs, per_sign, 3)) * [1, 1, 0]
    world = (centres[:, None, :] + offsets).reshape(-1, 3)
    sign_id = np.repeat(np.arange(n_signs), per_sign)
    return camera, T, world, sign_id


def _weighted_fit(camera, T0, world, px, sigma):
    """Gauss-Newton with per-axis weights: the estimator pose_fit describes."""
    T = T0.copy()
    w = 1.0 / sigma.reshape(-1) ** 2
    for _ in range(5):
        uv, J, _ = pixels_and_pose_jacobian(camera, T, world)
        Jf = J.reshape(-1, 6)
        xi = np.linalg.solve(Jf.T @ (w[:, None] * Jf), Jf.T @ (w * (px - uv).reshape(-1)))
        Rx = np.eye(3) + np.array(
            [[0, -xi[2], xi[1]], [xi[2], 0, -xi[0]], [-xi[1], xi[0], 0]]
        )  # small steps: first order is enough
        U, _, Vt = np.linalg.svd(T[:3, :3] @ Rx)
        T = T.copy()
        T[:3, 3] = T[:3, 3] + T[:3, :3] @ xi[3:]
        T[:3, :3] = U @ Vt
    return T


def test_pose_fit_shares_match_monte_carlo():
    # Pixel noise per keypoint and axis plus a survey shift per sign: the
    # pose errors of the pixel-weighted fit have the covariance pose_fit gives
    # (pixel share + survey share), and chi2_map has the pose's 2K - 6 dof.
    rng = np.random.default_rng(11)
    camera, T, world, sign_id = _scene(rng)
    k = len(world)
    sigma = rng.uniform(0.05, 0.4, (k, 2))
    sigma_m = np.full(k, 0.003)
    uv0, _, _ = pixels_and_pose_jacobian(camera, T, world)
    errors, chi2_map, chi2_pixel = [], [], []
    for _ in range(400):
        shift = rng.normal(0, 0.003, (sign_id.max() + 1, 3))[sign_id]
        px = uv0 + rng.normal(0, 1, (k, 2)) * sigma
        Te = _weighted_fit(camera, T, world - shift, px, sigma)  # the map is off by -shift
        errors.append(np.concatenate([np.zeros(3), T[:3, :3].T @ (Te[:3, 3] - T[:3, 3])]))
        uv, _, _ = pixels_and_pose_jacobian(camera, Te, world - shift)
        f = pose_fit(camera, Te, world - shift, px - uv, sigma, sigma_m, sign_id)
        chi2_map.append(f.chi2_map)
        chi2_pixel.append(f.chi2_pixel)
    f = pose_fit(camera, T, world, np.zeros((k, 2)), sigma, sigma_m, sign_id)
    emp = np.cov(np.array(errors)[:, 3:].T)
    model = f.cov6[3:, 3:]
    ratio = np.diag(emp) / np.diag(model)
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio
    # the survey's share is most of it here (3 mm per sign against < 0.4 px)
    assert np.all(np.diag(f.cov6_survey)[3:] > np.diag(f.cov6_pixel)[3:])
    dof = 2 * k - 6
    assert np.mean(chi2_map) == pytest.approx(dof, rel=0.1)
    assert np.mean(chi2_pixel) > 1.3 * dof  # the survey error taken as pixel noise


def test_pose_fit_on_an_exact_map_is_the_inverse_information():
    rng = np.random.default_rng(12)
    camera, T, world, sign_id = _scene(rng)
    sigma = rng.uniform(0.05, 0.4, (len(world), 2))
    f = pose_fit(camera, T, world, np.zeros((len(world), 2)), sigma, np.zeros(len(world)), sign_id)
    _, J, _ = pixels_and_pose_jacobian(camera, T, world)
    Jf = J.reshape(-1, 6) / sigma.reshape(-1, 1)
    assert np.allclose(f.cov6, np.linalg.inv(Jf.T @ Jf), rtol=1e-9, atol=0)
    assert np.all(f.cov6_survey == 0)


def _with_keypoint_sigmas(frames, sigma_of):
    return [
        replace(
            f,
            signs=tuple(
                replace(o, keypoint_sigma_px={n: sigma_of(o, n) for n in o.keypoints_px})
                for o in f.signs
            ),
        )
        for f in frames
    ]


def test_pnp_weighs_each_keypoint_axis_by_its_sigma():
    # One keypoint per frame is 3 px off along u and says so (sigma_u 5 px):
    # the weighted PnP follows the others; told 0.2 px like the rest, it is pulled.
    sign_map, camera, frames, gt, _ = estimator_scene(n_frames=6, sigma_px=0.0, seed=2, flat=False)
    f = frames[3]
    bad = f.signs[0]
    moved = replace(
        bad, keypoints_px={**bad.keypoints_px, "center": tuple(np.add(bad.center_px, (3.0, 0.0)))}
    )
    f = replace(f, signs=(moved, *f.signs[1:]))
    honest = _with_keypoint_sigmas(
        [f], lambda o, n: (5.0, 0.2) if o is moved and n == "center" else (0.2, 0.2)
    )[0]
    silent = _with_keypoint_sigmas([f], lambda o, n: (0.2, 0.2))[0]
    truth = gt.world_t_cam[3]
    p_honest = solve_frame_pnp(honest, sign_map, camera)
    p_silent = solve_frame_pnp(silent, sign_map, camera)
    e_honest = np.linalg.norm(p_honest.world_T_cam[:3, 3] - truth)
    e_silent = np.linalg.norm(p_silent.world_T_cam[:3, 3] - truth)
    assert e_honest < 0.2 * e_silent
    # its chi-square counts the offset keypoint at its own sigma
    assert p_honest.chi2 < 2.0 < p_silent.chi2


def test_smoother_takes_per_axis_sigmas_and_the_baseline_writes_none():
    sign_map, camera, frames, gt, _ = estimator_scene(n_frames=20, sigma_px=0.3, seed=5, flat=False)
    frames = _with_keypoint_sigmas(frames, lambda o, n: (0.3, 0.6) if n == "center" else (0.3, 0.3))
    meas = collect_measurements(frames, sign_map, camera)
    centre = np.array([meas.landmark_name[j] == "center" for j in meas.landmark])
    assert np.allclose(meas.axis_sigmas()[centre], [0.3, 0.6])
    assert np.allclose(meas.sigma_px[centre], np.sqrt(0.3 * 0.6))
    assert np.allclose(meas.subset(centre).axis_sigmas(), [0.3, 0.6])
    r = estimate_trajectories(frames, sign_map, camera, EstimatorSettings(), progress=False)
    assert np.all(np.isnan(r.methods["baseline"].sigma_xyz))
    # without a sigma to bet on, no baseline pose is ok
    assert r.methods["baseline"].valid.sum() > 10
    assert PoseStatus.OK not in r.methods["baseline"].status
    assert np.all(np.isfinite(r.methods["pnp"].sigma_xyz[r.methods["pnp"].valid]))
    s = r.methods["smoothed"].sigma_xyz
    assert np.all(np.isfinite(s)) and np.all(s > 0)


def _offset_along_u(frames, frame, offset_px, sigma_uv):
    """``frames`` with frame ``frame``'s first sign's centre ``offset_px`` off along u,
    claiming ``sigma_uv``; every other keypoint 0.2 px on both axes."""
    f = frames[frame]
    bad = f.signs[0]
    moved_px = tuple(np.add(bad.keypoints_px["center"], (offset_px, 0.0)))
    moved = replace(bad, keypoints_px={**bad.keypoints_px, "center": moved_px})
    out = list(frames)
    out[frame] = replace(f, signs=(moved, *f.signs[1:]))
    return _with_keypoint_sigmas(
        out, lambda o, n: sigma_uv if o is moved and n == "center" else (0.2, 0.2)
    )


def test_fusion_inliers_and_held_out_score_whiten_per_axis():
    # A centre 4 px off along u that says sigma_u = 2 px (sigma_v 0.2): 2 sigma per
    # axis, but 6.3 of its geometric-mean sigma (0.63 px), beyond Tukey's 4.685.
    sign_map, camera, frames, gt, _ = estimator_scene(n_frames=8, sigma_px=0.0, seed=2, flat=False)
    frames = _offset_along_u(frames, 4, 4.0, (2.0, 0.2))
    meas = collect_measurements(frames, sign_map, camera)
    moved = np.nonzero((meas.frame == 4) & (meas.sigma_uv_px[:, 0] == 2.0))[0]
    assert len(moved) == 1
    vision = vision_solve(frames, sign_map, camera, gt.stamps_s, SmootherSettings())
    assert whitened_chi2(meas, vision, camera)[moved[0]] < 4.685**2
    kept = _inliers(meas, vision, camera, FusionSettings())
    assert len(kept.frame) == len(meas.frame)
    # the held-out score of that centre alone, its frame posed by its other keypoints:
    # about 2^2 per axis (25, the cap, at its geometric-mean sigma)
    held = np.arange(len(meas.frame)) == moved[0]
    init = list(vision.world_T_cam)
    s = SmootherSettings()
    score = _held_out_score(meas, held, gt.stamps_s, init, camera, s, default_pose(sign_map), 25.0)
    assert 2.0 < score < 8.0
