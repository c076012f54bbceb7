"""A skewed camera (K[0, 1] != 0): projection and undistortion use the same lens model.

The model, for both plumb_bob and equidistant: raw u = fx * x_d + s * y_d + cx,
v = fy * y_d + cy, with (x_d, y_d) the distorted normalised coordinates. The
expected pixels are computed here from the formulas, not through OpenCV.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from signpose.estimator.camera import (
    EQUIDISTANT,
    PLUMB_BOB,
    CameraModel,
    pixel_from_cam_point,
    undistort_px,
)
from signpose.estimator.perframe import solve_frame_pnp
from signpose.maps.loader import bundled_map_path, load_map

from signpose.io.camera_file import load_camera
from signpose.sim.observations import SyntheticSettings, paper_like_frames

REAL_SKEWED = (
    Path(__file__).resolve().parents[2] / "shared/reference/camera-files/ros_equidistant_ost.yaml"
)

# ros_equidistant_ost.yaml's intrinsics (skew 1.0591 px).
K_SKEWED = np.array([[638.0064, 1.0591, 633.75963], [0.0, 638.9817, 369.88374], [0.0, 0.0, 1.0]])
DIST = {
    EQUIDISTANT: np.array([-0.019592, -0.056248, 0.075002, -0.043589]),
    PLUMB_BOB: np.array([-0.12, 0.03, 0.0007, -0.0004, -0.002]),
}


def _distorted(model: str, dist: np.ndarray, xy: np.ndarray) -> np.ndarray:
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    if model == EQUIDISTANT:
        r = np.sqrt(r2)
        theta = np.arctan(r)
        k1, k2, k3, k4 = dist
        theta_d = theta * (1 + k1 * theta**2 + k2 * theta**4 + k3 * theta**6 + k4 * theta**8)
        scale = np.where(r > 0, theta_d / np.where(r > 0, r, 1.0), 1.0)
        return xy * scale[:, None]
    k1, k2, p1, p2, k3 = dist
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def _cam_points(rng: np.random.Generator, n: int = 200) -> np.ndarray:
    # Up to ~0.55 rad off-axis: within the image of the 1280x720 camera.
    xy = rng.uniform(-0.55, 0.55, size=(n, 2)) * np.array([1.0, 0.55])
    depth = rng.uniform(2.0, 40.0, size=n)
    return np.column_stack([xy * depth[:, None], depth])


@pytest.mark.parametrize("model", [PLUMB_BOB, EQUIDISTANT])
def test_projection_of_a_skewed_camera_follows_the_lens_model(model):
    rng = np.random.default_rng(15)
    camera = CameraModel(1280, 720, K_SKEWED, DIST[model], model)
    cam_pts = _cam_points(rng)
    d = _distorted(model, DIST[model], cam_pts[:, :2] / cam_pts[:, 2:])
    expect = np.column_stack(
        [
            K_SKEWED[0, 0] * d[:, 0] + K_SKEWED[0, 1] * d[:, 1] + K_SKEWED[0, 2],
            K_SKEWED[1, 1] * d[:, 1] + K_SKEWED[1, 2],
        ]
    )
    assert np.max(np.abs(pixel_from_cam_point(camera, cam_pts) - expect)) < 1e-6


@pytest.mark.parametrize("model", [PLUMB_BOB, EQUIDISTANT])
def test_project_then_undistort_is_the_ideal_pinhole_of_the_full_k(model):
    rng = np.random.default_rng(16)
    camera = CameraModel(1280, 720, K_SKEWED, DIST[model], model)
    cam_pts = _cam_points(rng)
    ideal = (cam_pts / cam_pts[:, 2:]) @ K_SKEWED.T
    back = undistort_px(camera, pixel_from_cam_point(camera, cam_pts))
    # Below 1e-3 px everywhere (the skew term alone is ~0.33 px at 200 px off-centre).
    assert np.max(np.abs(back - ideal[:, :2])) < 1e-3


@pytest.mark.skipif(not REAL_SKEWED.exists(), reason="../shared reference files absent")
def test_the_real_skewed_equidistant_file_round_trips():
    camera = load_camera(REAL_SKEWED)
    assert camera.K[0, 1] == pytest.approx(1.0591)
    rng = np.random.default_rng(17)
    cam_pts = _cam_points(rng)
    ideal = (cam_pts / cam_pts[:, 2:]) @ camera.K.T
    back = undistort_px(camera, pixel_from_cam_point(camera, cam_pts))
    assert np.max(np.abs(back - ideal[:, :2])) < 1e-3


@pytest.mark.parametrize("model", [PLUMB_BOB, EQUIDISTANT])
def test_per_frame_pnp_of_a_skewed_camera_is_exact_without_noise(model):
    # A 1.06 px skew (the real file's) moved every PnP pose by 3.6 cm at 27 m before.
    sign_map = load_map(bundled_map_path())
    K = np.array([[1662.0, 1.06, 959.5], [0.0, 1664.0, 539.5], [0.0, 0.0, 1.0]])
    camera = CameraModel(1920, 1080, K, DIST[model], model)
    rng = np.random.default_rng(18)
    frames, gt, _ = paper_like_frames(sign_map, camera, 6, rng, SyntheticSettings(sigma_px=0.0))
    for frame, world_t_cam in zip(frames, gt.world_t_cam, strict=True):
        pose = solve_frame_pnp(frame, sign_map, camera)
        assert pose.world_T_cam is not None
        assert np.linalg.norm(pose.world_T_cam[:3, 3] - world_t_cam) < 1e-6
