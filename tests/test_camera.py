"""Camera files in three formats, projection and undistortion."""

import cv2
import numpy as np
import pytest
import yaml
from signpose.estimator.camera import (
    EQUIDISTANT,
    PLUMB_BOB,
    CameraModel,
    check_image_size,
    pinhole_camera,
    pixel_from_cam_point,
    pixel_from_world_point,
    undistort_px,
)

from signpose.core.errors import InputError
from signpose.io.camera_file import load_camera, write_camera_info

K = np.array([[1210.5, 0.0, 955.25], [0.0, 1208.75, 541.5], [0.0, 0.0, 1.0]])
CAMERAS = {
    PLUMB_BOB: CameraModel(1920, 1080, K, np.array([-0.12, 0.035, 8e-4, -5e-4, -0.004]), PLUMB_BOB),
    EQUIDISTANT: CameraModel(1920, 1080, K, np.array([0.04, -0.012, 0.003, -0.0007]), EQUIDISTANT),
}


def _assert_same(a: CameraModel, b: CameraModel, n_dist: int | None = None):
    assert (a.width, a.height, a.model) == (b.width, b.height, b.model)
    np.testing.assert_allclose(a.K, b.K, rtol=0, atol=1e-9)
    n = n_dist or len(a.dist)
    np.testing.assert_allclose(a.dist[:n], b.dist[:n], rtol=0, atol=1e-12)
    assert np.all(b.dist[n:] == 0)


@pytest.mark.parametrize("model", [PLUMB_BOB, EQUIDISTANT])
def test_ros_camera_info_round_trip(tmp_path, model):
    cam = CAMERAS[model]
    write_camera_info(tmp_path / "cam.yaml", cam)
    _assert_same(cam, load_camera(tmp_path / "cam.yaml"))
    assert yaml.safe_load((tmp_path / "cam.yaml").read_text())["distortion_model"] == model


@pytest.mark.parametrize("model", [PLUMB_BOB, EQUIDISTANT])
@pytest.mark.parametrize("fisheye_flag", [False, True])
def test_opencv_filestorage_round_trip(tmp_path, model, fisheye_flag):
    cam = CAMERAS[model]
    path = tmp_path / "opencv.yaml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", cam.width)
    fs.write("image_height", cam.height)
    fs.write("camera_matrix", cam.K)
    fs.write("distortion_coefficients", cam.dist.reshape(1, -1))
    if fisheye_flag:
        fs.write("fisheye", int(model == EQUIDISTANT))
    else:
        fs.write("distortion_model", model)
    fs.release()
    assert path.read_text().startswith("%YAML")
    _assert_same(cam, load_camera(path))


@pytest.mark.parametrize("model", [PLUMB_BOB, EQUIDISTANT])
def test_kalibr_camchain_round_trip(tmp_path, model):
    cam = CAMERAS[model]
    n = 4  # Kalibr radtan and equidistant both carry 4 coefficients
    chain = {
        "cam0": {
            "camera_model": "pinhole",
            "intrinsics": [cam.fx, cam.fy, cam.cx, cam.cy],
            "distortion_model": "radtan" if model == PLUMB_BOB else "equidistant",
            "distortion_coeffs": [float(x) for x in cam.dist[:n]],
            "resolution": [cam.width, cam.height],
            "rostopic": "/cam0/image_raw",
        }
    }
    path = tmp_path / "camchain.yaml"
    path.write_text(yaml.safe_dump(chain))
    _assert_same(cam, load_camera(path), n_dist=n)


@pytest.mark.parametrize("model", [PLUMB_BOB, EQUIDISTANT])
def test_undistort_inverts_projection(model):
    rng = np.random.default_rng(3)
    cam = CAMERAS[model]
    # Points spread over the whole image, corners included.
    xy = rng.uniform([-0.8, -0.45], [0.8, 0.45], size=(400, 2))
    z = rng.uniform(2.0, 60.0, size=(400, 1))
    pts = np.hstack([xy * z, z])
    raw = pixel_from_cam_point(cam, pts)
    ideal = (pts[:, :2] / pts[:, 2:]) @ cam.K[:2, :2].T + cam.K[:2, 2]
    assert np.abs(raw - ideal).max() > 5.0  # the distortion is real
    np.testing.assert_array_less(np.linalg.norm(undistort_px(cam, raw) - ideal, axis=1), 1e-3)


def test_pixel_from_world_point_depth_and_behind():
    cam = pinhole_camera(640, 480, 60.0)
    world_T_cam = np.eye(4)
    world_T_cam[:3, 3] = [1.0, 2.0, 3.0]
    pts = np.array([[1.0, 2.0, 13.0], [1.0, 2.0, -7.0]])
    px, depth = pixel_from_world_point(cam, world_T_cam, pts)
    np.testing.assert_allclose(px[0], [cam.cx, cam.cy])
    np.testing.assert_allclose(depth, [10.0, -10.0])
    assert np.all(np.isnan(px[1]))


def test_pinhole_camera_field_of_view():
    cam = pinhole_camera(1920, 1080, 60.0)
    assert 2 * np.degrees(np.arctan((cam.width / 2) / cam.fx)) == pytest.approx(60.0)
    assert not cam.has_distortion
    np.testing.assert_allclose(undistort_px(cam, [[3.0, 4.0]]), [[3.0, 4.0]])


@pytest.mark.parametrize(
    "text,expect",
    [
        ("image_width: 10\n", "unknown camera format"),
        ("cam0: {intrinsics: [1, 1, 1, 1]}\n", "resolution"),
        (
            "image_width: 640\nimage_height: 480\ncamera_matrix: {data: [1, 0, 1]}\n",
            "camera_matrix",
        ),
        (
            "image_width: 640\nimage_height: 480\ncamera_matrix: {data: [1,0,1,0,1,1,0,0,1]}\n"
            "distortion_model: tangential_magic\n",
            "distortion model",
        ),
        ("[unclosed\n", "YAML"),
    ],
)
def test_bad_camera_files_name_the_file(tmp_path, text, expect):
    path = tmp_path / "cam.yaml"
    path.write_text(text)
    with pytest.raises(InputError, match=expect) as info:
        load_camera(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_check_image_size():
    cam = pinhole_camera(640, 480)
    check_image_size(cam, 640, 480, "video.mp4")
    with pytest.raises(InputError, match="video.mp4"):
        check_image_size(cam, 1920, 1080, "video.mp4")
