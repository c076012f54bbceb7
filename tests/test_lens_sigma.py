"""Keypoint sigmas carried through the lens: raw-pixel sigmas become undistorted ones.

The decoder's sigmas are in raw (distorted) pixels; the estimator works on
undistorted pixels, where a barrel lens or a fisheye stretches the image
toward its edges. A keypoint's sigma there is ``J sigma_raw`` with J the
undistortion's Jacobian (``camera.undistort_px_jacobian``).
"""

import logging
from dataclasses import replace
from types import SimpleNamespace

import gtsam
import numpy as np
import pytest
import signpose.estimator.perframe as perframe
import signpose.estimator.smoother as smoother
from signpose.estimator.camera import (
    EQUIDISTANT,
    CameraModel,
    pinhole_camera,
    undistort_px,
    undistort_px_jacobian,
    undistorted_sigmas,
)
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.noise_scale import exact_map_pose, pixel_noise_scale
from signpose.estimator.smoother import collect_measurements, whitened_chi2
from signpose.estimator.status import PoseStatus
from signpose.frontend.observations import FrameObservations, SignObservation
from signpose.maps.loader import bundled_map_path, load_map

from signpose.sim.observations import SyntheticSettings, paper_like_frames

W, H = 1280, 720


def _camera(model: str, dist) -> CameraModel:
    cam = pinhole_camera(W, H, 90.0)
    K = np.array(cam.K)
    K[0, 1] = 0.8  # a little skew: the Jacobian must carry it too
    return replace(cam, K=K, dist=np.asarray(dist, float), model=model)


BARREL = _camera("plumb_bob", [-0.3, 0.08, 0.0004, -0.0003, 0.0])
FISHEYE = _camera(EQUIDISTANT, [0.05, -0.02, 0.004, -0.001])


def _grid(n: int = 9) -> np.ndarray:
    u, v = np.meshgrid(np.linspace(5, W - 6, n), np.linspace(5, H - 6, n))
    return np.column_stack([u.ravel(), v.ravel()])


@pytest.mark.parametrize("camera", [BARREL, FISHEYE], ids=["plumb_bob", "equidistant"])
def test_the_jacobian_is_the_undistortions_derivative(camera):
    px = _grid()
    und, J, valid = undistort_px_jacobian(camera, px)
    assert np.array_equal(und, undistort_px(camera, px)) and np.all(valid)
    h = 0.05
    num = np.empty_like(J)
    for a, step in enumerate(([h, 0.0], [0.0, h])):
        num[:, :, a] = (undistort_px(camera, px + step) - undistort_px(camera, px - step)) / (2 * h)
    assert np.max(np.abs(J - num)) < 1e-5
    # the edges are stretched: the edge's Jacobian is far from the identity
    assert np.max(np.abs(J - np.eye(2))) > 0.2


def test_no_distortion_carries_nothing():
    cam = pinhole_camera(W, H, 90.0)
    px = _grid()
    und, J, valid = undistort_px_jacobian(cam, px)
    assert J is None and valid is None and np.array_equal(und, px)
    s = np.full((len(px), 2), 0.3)
    assert undistorted_sigmas(None, s) is not None and np.array_equal(undistorted_sigmas(J, s), s)


def test_an_edge_keypoints_sigma_grows_by_the_lens_stretch():
    sign_map = load_map(bundled_map_path())
    code = sign_map.signs[0].code
    edge, centre = (8.0, BARREL.cy), (BARREL.cx, BARREL.cy)  # the left edge
    kp = {"center": centre, "direction": edge}
    kps = {"center": (0.2, 0.3), "direction": (0.2, 0.3)}
    obs = SignObservation(code, kp, None, 0.1, 1.0, (), kps)
    frames = [FrameObservations(0, 0, (W, H), (obs,))]
    if "direction" not in sign_map.signs[0].keypoints_world():
        pytest.fail("the bundled map's signs have no keypoint s1")
    meas = collect_measurements(frames, sign_map, BARREL)
    sig = meas.axis_sigmas()
    names = [meas.landmark_name[j] for j in meas.landmark]
    at_edge, at_centre = sig[names.index("direction")], sig[names.index("center")]
    _, J, _ = undistort_px_jacobian(BARREL, np.array([edge]))
    want = np.sqrt(J[0] ** 2 @ np.array([0.2, 0.3]) ** 2)
    assert np.allclose(at_edge, want, rtol=1e-12)
    assert np.all(at_edge > 1.3 * np.array([0.2, 0.3]))  # ~1.38x at this edge
    assert np.allclose(at_centre, [0.2, 0.3], rtol=1e-3)  # the centre is not stretched
    m = names.index("direction")
    assert meas.sigma_px[m] == pytest.approx(np.sqrt(at_edge[0] * at_edge[1]))
    # the floor at the sign's sigma_px applies in raw pixels, before the lens
    low = SignObservation(code, kp, None, 0.25, 1.0, (), {"direction": (0.1, 0.1)})
    m2 = collect_measurements([FrameObservations(0, 0, (W, H), (low,))], sign_map, BARREL)
    j = [m2.landmark_name[i] for i in m2.landmark].index("direction")
    assert np.allclose(m2.axis_sigmas()[j], np.sqrt(J[0] ** 2 @ np.array([0.25, 0.25]) ** 2))


def _pnp_chi2_per_dof(camera: CameraModel) -> tuple[float, float]:
    """(median chi2 / dof, pixel_noise_scale) of PnP on a close flight, the map exact."""
    sign_map = load_map(bundled_map_path())
    rng = np.random.default_rng(1)
    s = SyntheticSettings(sigma_px=0.3)  # raw-pixel noise, as the decoder reports it
    frames, _, _ = paper_like_frames(sign_map, camera, 60, rng, s, fps=60 / 7, distance_m=8.0)
    poses = perframe.run_per_frame(frames, sign_map, camera, "pnp")
    r = [p.chi2 / (2 * p.keypoints_used - 6) for p in poses if p.world_T_cam is not None]
    assert len(r) >= 55
    return float(np.median(r)), pixel_noise_scale([exact_map_pose(p) for p in poses])


@pytest.mark.parametrize("camera", [BARREL, FISHEYE], ids=["plumb_bob", "equidistant"])
def test_pnp_chi2_is_about_one_through_a_strong_lens(camera, monkeypatch):
    median, scale = _pnp_chi2_per_dof(camera)
    assert 0.9 < median < 1.1 and scale < 1.05
    # the same keypoints with their raw-pixel sigmas taken as undistorted ones: biased
    real = perframe.undistort_px_jacobian
    monkeypatch.setattr(perframe, "undistort_px_jacobian", lambda c, p: (real(c, p)[0], None, None))
    raw_median, raw_scale = _pnp_chi2_per_dof(camera)
    assert raw_median > 1.12 and raw_scale > 1.05


# A fisheye whose corners see rays beyond 90 deg (no pinhole image holds them),
# and a polynomial that folds beyond its calibrated radius.
WIDE_FISHEYE = replace(FISHEYE, K=np.array([[400.0, 0.0, 639.5], [0.0, 400.0, 359.5], [0, 0, 1]]))
FOLDED = _camera("plumb_bob", [-0.5, 0.1, 0.0, 0.0, 0.0])


@pytest.mark.parametrize("camera", [WIDE_FISHEYE, FOLDED], ids=["beyond_90_deg", "folded"])
def test_pixels_the_lens_model_cannot_undistort_are_dropped(camera, caplog):
    px = _grid(17)
    und, _, valid = undistort_px_jacobian(camera, px)
    assert 0 < np.sum(~valid) < len(px) // 2 and valid[len(px) // 2]  # the centre holds
    sign_map = load_map(bundled_map_path())
    code = sign_map.signs[0].code
    bad = px[np.nonzero(~valid)[0][0]]
    kp = {"center": (camera.cx, camera.cy), "direction": tuple(bad)}
    obs = SignObservation(code, kp, None, 0.1, 1.0)
    with caplog.at_level(logging.WARNING):
        meas = collect_measurements([FrameObservations(0, 0, (W, H), (obs,))], sign_map, camera)
    assert "1 of 2 keypoints" in caplog.text and "lens model" in caplog.text
    assert [meas.landmark_name[j] for j in meas.landmark] == ["center"]
    assert np.allclose(meas.px[0], (camera.cx, camera.cy))
    c = perframe._correspondences(
        FrameObservations(0, 0, (W, H), (obs,)), sign_map, camera, all_keypoints=True
    )
    assert c.names == ["center"] and len(c.px) == len(c.sigma_px) == len(c.world) == 1


def _lens_flight(camera: CameraModel, n: int = 30):
    sign_map = load_map(bundled_map_path())
    rng = np.random.default_rng(2)
    s = SyntheticSettings(sigma_px=0.3)
    frames, gt, _ = paper_like_frames(sign_map, camera, n, rng, s, fps=n / 7, distance_m=6.0)
    return sign_map, frames, gt


@pytest.mark.parametrize("camera", [BARREL, FISHEYE], ids=["plumb_bob", "equidistant"])
def test_the_smoothers_measurements_whiten_to_chi_square_2_at_the_truth(camera, monkeypatch):
    sign_map, frames, gt = _lens_flight(camera, 90)
    truth = SimpleNamespace(
        world_T_cam=np.asarray(gt.world_T_cam()),
        landmarks_world=np.array([p for s in sign_map.signs for p in s.keypoints_world().values()]),
    )
    meas = collect_measurements(frames, sign_map, camera)
    assert meas.cov_uv_px is not None and len(meas.frame) > 1000
    mean = float(np.mean(whitened_chi2(meas, truth, camera)))
    assert 1.9 < mean < 2.1  # chi-square with 2 dof: 2 +- 0.06 at 2 sigma here
    # every consumer whitens alike: the gtsam factors' own whitening is the same
    m = 7
    noise = gtsam.noiseModel.Gaussian.Covariance(meas.cov_uv_px[m])
    r = np.array([0.3, -0.2])
    assert np.allclose(noise.whiten(r) @ noise.whiten(r), np.sum(meas.whitened(r[None], [m]) ** 2))
    assert np.isclose(
        np.sum(meas.whitened(r[None], [m]) ** 2), r @ np.linalg.solve(meas.cov_uv_px[m], r)
    )
    # the raw-pixel sigmas taken as undistorted ones: too small, chi-square too large
    real = smoother.undistort_px_jacobian
    monkeypatch.setattr(smoother, "undistort_px_jacobian", lambda c, p: (real(c, p)[0], None, None))
    raw = collect_measurements(frames, sign_map, camera)
    assert float(np.mean(whitened_chi2(raw, truth, camera))) > 2.2


def test_a_flight_through_a_strong_lens_is_smoothed_with_honest_statuses():
    sign_map, frames, gt = _lens_flight(BARREL, 24)
    s = replace(EstimatorSettings(), methods=("pnp", "smoothed"))
    s = replace(s, smoother=replace(s.smoother, landmarks="fixed"))
    r = estimate_trajectories(frames, sign_map, BARREL, s, False)
    assert r.warnings == () and r.pixel_noise_scale < 1.1
    sm = r.methods["smoothed"]
    assert sum(st is PoseStatus.OK for st in sm.status) >= 20
    err = np.linalg.norm(sm.world_T_cam[:, :3, 3] - np.asarray(gt.world_T_cam())[:, :3, 3], axis=1)
    assert np.max(err / np.linalg.norm(sm.sigma_xyz, axis=1)) < 4.0  # sigmas that hold
