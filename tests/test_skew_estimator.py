"""A skewed camera in the estimator's pixel math: PnP sigmas, the gate and residuals.

The camera is an ideal pinhole with ros_equidistant_ost.yaml's skew (1.06 px),
built here, so the test needs nothing from ../shared. Its undistorted pixels
keep the skew (``undistort_px``), so every model of them must use the full K.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from signpose.estimator.camera import CameraModel, pinhole_camera, pixel_from_world_point
from signpose.estimator.estimate import gate_measurements
from signpose.estimator.projection import pixels_and_pose_jacobian, pose_covariance
from signpose.estimator.smoother import collect_measurements, project
from signpose.maps.loader import bundled_map_path, load_map

from signpose.sim.observations import SyntheticSettings, paper_like_frames

SKEW_PX = 1.0591


def _skewed(camera: CameraModel, skew: float = SKEW_PX) -> CameraModel:
    K = camera.K.copy()
    K[0, 1] = skew
    return replace(camera, K=K)


def _scene(rng: np.random.Generator):
    """A camera 25 m from a spread of points filling the image."""
    world_T_cam = np.eye(4)
    world_T_cam[:3, 3] = [0.3, -0.2, -25.0]
    cam_xy = rng.uniform(-0.5, 0.5, size=(12, 2)) * [1.0, 0.56]
    depth = rng.uniform(22.0, 28.0, size=12)
    world_p = np.column_stack([cam_xy * depth[:, None], depth]) + world_T_cam[:3, 3]
    return world_T_cam, world_p


def test_projection_and_jacobian_use_the_skew():
    rng = np.random.default_rng(0)
    camera = _skewed(pinhole_camera(1280, 720, 90.0))
    world_T_cam, world_p = _scene(rng)
    uv, J, _ = pixels_and_pose_jacobian(camera, world_T_cam, world_p)
    expected, _ = pixel_from_world_point(camera, world_T_cam, world_p)
    assert np.max(np.abs(uv - expected)) < 1e-9
    T = np.repeat(world_T_cam[None], len(world_p), axis=0)
    assert np.max(np.abs(project(camera, T, world_p) - expected)) < 1e-9
    # The Jacobian against central differences of the skewed projection.
    eps = 1e-6
    for k in range(6):
        xi = np.zeros(6)
        xi[k] = eps
        num = []
        for sgn in (1.0, -1.0):
            d = np.eye(4)
            w = sgn * xi[:3]
            th = np.linalg.norm(w)
            W = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
            d[:3, :3] = np.eye(3) + W + (W @ W) / 2 if th else np.eye(3)
            d[:3, 3] = sgn * xi[3:]
            num.append(pixel_from_world_point(camera, world_T_cam @ d, world_p)[0])
        assert np.max(np.abs((num[0] - num[1]) / (2 * eps) - J[:, :, k])) < 1e-3


def test_pose_sigma_matches_the_unskewed_camera():
    rng = np.random.default_rng(1)
    plain = pinhole_camera(1280, 720, 90.0)
    camera = _skewed(plain)
    world_T_cam, world_p = _scene(rng)
    n = len(world_p)
    args = (world_T_cam, world_p, np.full(n, 0.3), np.full(n, 0.01))
    sigma = np.sqrt(np.diag(pose_covariance(camera, *args)))
    sigma_plain = np.sqrt(np.diag(pose_covariance(plain, *args)))
    # A 1 px skew is a 0.17 % shear of the image: the sigmas move by less than 1 %.
    assert np.max(np.abs(sigma / sigma_plain - 1.0)) < 0.01


def test_gate_keeps_exact_pixels_of_a_skewed_camera():
    sign_map = load_map(bundled_map_path())
    plain = pinhole_camera(1280, 720, 90.0)
    rng = np.random.default_rng(2)
    out = {}
    for name, camera in (("plain", plain), ("skewed", _skewed(plain, 20.0))):
        frames, gt, _ = paper_like_frames(
            sign_map, camera, 8, rng, SyntheticSettings(sigma_px=0.0), fps=2.0, seed=2
        )
        meas = collect_measurements(frames, sign_map, camera)
        poses = list(gt.world_T_cam())
        _, gated = gate_measurements(meas, poses, camera, gate_px=0.05)
        out[name] = (len(gated), int(gated.sum()))
    # Without noise at the true poses nothing is off by 0.05 px, skew or not (a
    # 20 px skew ignored puts points 300 px off-centre about 5 px off).
    assert out["skewed"][0] > 0 and out["skewed"][1] == 0 == out["plain"][1]
