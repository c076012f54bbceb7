"""Camera files in three formats, projection and undistortion."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
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

from signpose.cli import main as cli_main
from signpose.core.errors import InputError
from signpose.io.camera_file import (
    MAX_CAMERA_FILE_BYTES,
    load_camera,
    read_camera_file,
    write_camera_info,
    write_kalibr,
    write_opencv,
)

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


# --------------------------------------------------------------------------- real files (issue 13)

REFERENCE = Path(__file__).resolve().parents[2] / "shared" / "reference" / "camera-files"
needs_reference = pytest.mark.skipif(
    not REFERENCE.is_dir(), reason="../shared/reference/camera-files is absent"
)

# Values as SOURCES.md gives them for each file (and the file itself shows).
REFERENCE_FILES = {
    "ros_cim_test_calibration.yaml": (
        "camera_info",
        PLUMB_BOB,
        (640, 480),
        (1168.68, 1169.01, 295.015, 252.247, 0.0),
        [-1.04482, 1.59252, -0.0196308, 0.0287906, 0.0],
    ),
    "ros_usb_cam_camera_info.yaml": (
        "camera_info",
        PLUMB_BOB,
        (640, 480),
        (438.783367, 437.302876, 305.593336, 243.738352, 0.0),
        [-0.361976, 0.110510, 0.001014, 0.000505, 0.0],
    ),
    "ros_depthai_left_stereo.yaml": (
        "camera_info",
        PLUMB_BOB,
        (1280, 720),
        (800.40414, 799.68286, 638.37063, 360.37479, 0.0),
        [0.107416, -0.285425, -0.005807, -0.001530, 0.0],
    ),
    "ros_equidistant_ost.yaml": (
        "camera_info",
        EQUIDISTANT,
        (1280, 720),
        (638.0064, 638.9817, 633.75963, 369.88374, 1.0591),
        [-0.019592, -0.056248, 0.075002, -0.043589],
    ),
    "kalibr_camchain_equi.yaml": (
        "kalibr",
        EQUIDISTANT,
        (640, 480),
        (277.95596230891084, 278.4167467580337, 315.5269754313737, 244.46893770533453, 0.0),
        [-0.005908650672531068, 0.01587953759563821, -0.024196671184075886, 0.015501252412920248],
    ),
    "opencv_left_intrinsics.yml": (
        "opencv",
        PLUMB_BOB,
        (640, 480),
        (535.91573396163199, 535.91573396163199, 342.28315473308373, 235.57082909788173, 0.0),
        [
            -0.26637260909660682,
            -0.038588898922304653,
            0.0017831947042852964,
            -0.00028122100441115472,
            0.23839153080878486,
        ],
    ),
}


def _assert_reads_as(found, source_format, model, size, fx_fy_cx_cy_skew, dist):
    cam = found.camera
    assert (found.source_format, cam.model, cam.image_size) == (source_format, model, size)
    np.testing.assert_allclose(
        [cam.fx, cam.fy, cam.cx, cam.cy, cam.K[0, 1]], fx_fy_cx_cy_skew, rtol=0, atol=1e-12
    )
    np.testing.assert_allclose(cam.dist, dist, rtol=0, atol=1e-15)


@needs_reference
@pytest.mark.parametrize("name", sorted(REFERENCE_FILES))
def test_real_calibration_files_load_with_their_model(name):
    _assert_reads_as(read_camera_file(REFERENCE / name), *REFERENCE_FILES[name])


@needs_reference
def test_a_kalibr_chain_with_an_omni_camera_is_refused_naming_it():
    with pytest.raises(InputError, match=r"cam1: camera_model 'omni' is not supported"):
        load_camera(REFERENCE / "kalibr_wiki_camchain_omni.yaml")


def _calibration_sample(path: Path, camera: CameraModel, *, old_keys=False, fisheye=False):
    """What OpenCV's camera_calibration tutorial sample saves (XML by default)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    keys = ("image_Width", "image_Height", "Camera_Matrix", "Distortion_Coefficients")
    if not old_keys:
        keys = ("image_width", "image_height", "camera_matrix", "distortion_coefficients")
    fs.write("calibration_time", "Tue Dec  1 20:00:00 2026")
    fs.write("nr_of_frames", 25)
    fs.write(keys[0], camera.width)
    fs.write(keys[1], camera.height)
    fs.write("board_width", 9)
    fs.write("board_height", 6)
    fs.write("square_size", 50.0)
    fs.write("flags", 0)
    if not old_keys:
        fs.write("fisheye_model", int(fisheye))
    fs.write(keys[2], camera.K)
    fs.write(keys[3], camera.dist.reshape(-1, 1))
    fs.write("avg_reprojection_error", 0.31)
    fs.release()


@pytest.mark.parametrize("suffix", [".xml", ".yml"])
@pytest.mark.parametrize("model", [PLUMB_BOB, EQUIDISTANT])
def test_opencv_calibration_sample_output(tmp_path, suffix, model):
    cam = CAMERAS[model]
    path = tmp_path / f"out_camera_data{suffix}"
    _calibration_sample(path, cam, fisheye=model == EQUIDISTANT)
    found = read_camera_file(path)
    assert found.source_format == ("opencv_xml" if suffix == ".xml" else "opencv")
    _assert_same(cam, found.camera)  # fisheye_model: 1 is equidistant, never plumb_bob


@pytest.mark.parametrize("suffix", [".xml", ".yml"])
def test_opencv_calibration_sample_old_key_names(tmp_path, suffix):
    cam = CAMERAS[PLUMB_BOB]
    path = tmp_path / f"out_camera_data{suffix}"
    _calibration_sample(path, cam, old_keys=True)
    _assert_same(cam, load_camera(path))


def test_kalibr_camchain_with_a_yaml_directive(tmp_path):
    cam = CAMERAS[EQUIDISTANT]
    chain = {
        "cam0": {
            "camera_model": "pinhole",
            "intrinsics": [cam.fx, cam.fy, cam.cx, cam.cy],
            "distortion_model": "equidistant",
            "distortion_coeffs": [float(x) for x in cam.dist],
            "resolution": [cam.width, cam.height],
        }
    }
    path = tmp_path / "camchain.yaml"
    path.write_text("%YAML:1.0\n---\n" + yaml.safe_dump(chain))
    found = read_camera_file(path)
    assert found.source_format == "kalibr"
    _assert_same(cam, found.camera)


@pytest.mark.parametrize("writer", [write_camera_info, write_opencv, write_kalibr])
@pytest.mark.parametrize("model", [PLUMB_BOB, EQUIDISTANT])
def test_every_writer_reads_back(tmp_path, writer, model):
    cam = CAMERAS[model]
    if writer is write_kalibr and model == PLUMB_BOB:  # radtan: k1, k2, p1, p2 and no k3
        cam = CameraModel(cam.width, cam.height, cam.K, np.append(cam.dist[:4], 0.0), model)
    path = tmp_path / "camera.yaml"
    writer(path, cam)
    _assert_same(cam, load_camera(path))


def test_kalibr_cannot_state_a_k3(tmp_path):
    with pytest.raises(InputError, match=r"camchain.yaml: Kalibr radtan takes k1, k2, p1, p2"):
        write_kalibr(tmp_path / "camchain.yaml", CAMERAS[PLUMB_BOB])


_ROS = "image_width: 640\nimage_height: 480\ncamera_matrix: {data: [500,0,320,0,500,240,0,0,1]}\n"


@pytest.mark.parametrize(
    "text,expect",
    [
        (_ROS + "distortion_model: double_sphere\n", "'double_sphere' is not supported"),
        (
            _ROS + "distortion_model: plumb_bob\ndistortion_coefficients: {data: [0,0,0,0,0,0]}\n",
            "6 coefficients is not supported",
        ),
        (
            _ROS + "distortion_model: equidistant\ndistortion_coefficients: {data: [0,0,0,0,0]}\n",
            "takes 4 coefficients k1..k4, has 5",
        ),
        (
            "cam0: {camera_model: ds, intrinsics: [0.5, 0.6, 300, 300, 320, 240], "
            "resolution: [640, 480]}\n",
            "camera_model 'ds' is not supported",
        ),
        (
            "cam0: {camera_model: pinhole, intrinsics: [300, 300, 320, 240], "
            "distortion_model: fov, distortion_coeffs: [0.9], resolution: [640, 480]}\n",
            "'fov' is not supported",
        ),
        ("cam1: {camera_model: pinhole}\n", "has no 'cam0'"),
        ("%YAML", "not a readable OpenCV FileStorage YAML"),
        ("%YAML:1.0\n---\n" + "[" * 5000 + "]" * 5000 + "\n", "nested deeper than 64"),
        ("a: " + "[" * 5000 + "]" * 5000 + "\n", "nested deeper than 64"),
        ("<?xml version='1.0'?>\n<opencv_storage><a>", "OpenCV FileStorage XML"),
        (_ROS.replace("500,0,320", "1e308,0,320"), "focal lengths"),
        (_ROS.replace("image_width: 640", "image_width: -640"), "image_width"),
        (_ROS.replace("image_width: 640", "image_width: .inf"), "image_width"),
        (_ROS.replace("0,0,1]", "0,0,2]"), "0 0 1"),
        (_ROS.replace("320", "1e9"), "principal point"),
    ],
)
def test_unusable_camera_files_are_refused_naming_why(tmp_path, text, expect):
    path = tmp_path / "cam.yaml"
    path.write_text(text)
    with pytest.raises(InputError, match=expect) as info:
        load_camera(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_camera_file_bytes_that_are_not_utf8_or_too_many(tmp_path):
    path = tmp_path / "cam.yaml"
    path.write_bytes(b"image_width: 640\n\xff\n")
    with pytest.raises(InputError, match="not UTF-8"):
        load_camera(path)
    path.write_bytes(b"#" * (MAX_CAMERA_FILE_BYTES + 1))
    with pytest.raises(InputError, match="not a camera file"):
        load_camera(path)
    with pytest.raises(InputError, match="is a folder"):
        load_camera(tmp_path)


@settings(max_examples=300, deadline=None, derandomize=True)
@given(
    head=st.sampled_from(["", "%YAML:1.0\n---\n", "<?xml version='1.0'?>\n", "cam0:\n  ", "%YAML"]),
    body=st.text(max_size=200),
)
def test_camera_reader_fuzz_raises_only_input_error(tmp_path_factory, head, body):
    path = tmp_path_factory.mktemp("fuzz") / "cam.yaml"
    path.write_text(head + body, encoding="utf-8", errors="surrogatepass")
    try:
        load_camera(path)
    except InputError as exc:
        assert str(path) in str(exc)


def test_camera_command_prints_what_it_read_and_converts(tmp_path, capsys):
    cam = CAMERAS[EQUIDISTANT]
    src = tmp_path / "ost.yaml"
    write_camera_info(src, cam)
    assert cli_main(["camera", str(src)]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == {
        "model": "equidistant",
        "width": 1920,
        "height": 1080,
        "fx": 1210.5,
        "fy": 1208.75,
        "cx": 955.25,
        "cy": 541.5,
        "skew": 0.0,
        "distortion": [0.04, -0.012, 0.003, -0.0007],
        "source_format": "camera_info",
    }
    out = tmp_path / "camchain.yaml"
    assert cli_main(["camera", str(src), "--to", "kalibr", "--out", str(out)]) == 0
    assert json.loads(capsys.readouterr().out)["source_format"] == "camera_info"
    assert read_camera_file(out).source_format == "kalibr"
    _assert_same(cam, load_camera(out))
    assert cli_main(["camera", str(src), "--to", "opencv"]) == 2
    assert "--to and --out go together" in capsys.readouterr().err
    assert cli_main(["camera", str(src), "--to", "opencv", "--out", str(tmp_path)]) == 2
    assert f"{tmp_path}: is a folder" in capsys.readouterr().err


def test_ros_rational_polynomial_with_8_coefficients(tmp_path):
    dist = [-0.2, 0.05, 1e-4, -2e-4, 0.01, 0.3, -0.02, 0.004]
    text = _ROS + "distortion_model: rational_polynomial\ndistortion_coefficients: {rows: 1, "
    text += f"cols: 8, data: {dist}}}\n"
    path = tmp_path / "ost.yaml"
    path.write_text(text)
    cam = load_camera(path)
    assert cam.model == PLUMB_BOB  # OpenCV's rational model: undistortPoints takes 8
    np.testing.assert_array_equal(cam.dist, dist)
    write_camera_info(tmp_path / "back.yaml", cam)
    assert yaml.safe_load((tmp_path / "back.yaml").read_text())["distortion_model"] == (
        "rational_polynomial"
    )
    np.testing.assert_array_equal(load_camera(tmp_path / "back.yaml").dist, dist)


def test_opencv_file_whose_model_and_fisheye_flag_disagree(tmp_path):
    path = tmp_path / "cam.yml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.zeros((4, 1)))
    fs.write("distortion_model", "plumb_bob")
    fs.write("fisheye_model", 1)
    fs.release()
    with pytest.raises(InputError, match="says plumb_bob but fisheye_model says equidistant"):
        load_camera(path)
