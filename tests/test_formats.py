"""Every file format signpose writes reads back to what was written (round trips).

One test group per format module of ``signpose.io``: camera files, TUM,
observations JSONL, MCAP (Foxglove JSON). Property tests use hypothesis where a
parser has free-form input; the rest draw from a seeded ``default_rng``.
"""

from __future__ import annotations

import base64

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from signpose.estimator.camera import EQUIDISTANT, PLUMB_BOB, CameraModel
from signpose.estimator.trajectory import Trajectory, quat_xyzw_from_rotation
from signpose.frontend.observations import FrameObservations, SignObservation
from signpose.frontend.sign import ALL_CODES, KEYPOINT_NAMES

from signpose.core.errors import InputError
from signpose.io import mcap as mcap_io
from signpose.io.camera_file import load_camera, write_camera_info
from signpose.io.groundtruth import read_ground_truth
from signpose.io.messages import camera_from_message, image_from_message, message_stamp_ns
from signpose.io.observations import read_observations, write_observations
from signpose.io.tum import read_tum, write_tum

# Decimals each writer keeps (the readers parse what they print exactly).
OBS_DECIMALS = 4
TUM_POSITION_ATOL_M = 5e-7  # 6 decimals
TUM_STAMP_ATOL_S = 5e-10  # 9 decimals
TUM_QUAT_ATOL = 5e-9  # 9 decimals, then renormalised on reading

FILES = settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)

# --------------------------------------------------------------------------- camera files

_finite = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)


@st.composite
def cameras(draw) -> CameraModel:
    model = draw(st.sampled_from([PLUMB_BOB, EQUIDISTANT]))
    n_dist = 4 if model == EQUIDISTANT else draw(st.sampled_from([4, 5, 8]))
    width = draw(st.integers(1, 8192))
    height = draw(st.integers(1, 8192))
    fx = draw(st.floats(1.0, 1e5))
    fy = draw(st.floats(1.0, 1e5))
    skew = draw(st.sampled_from([0.0, 1.0591]))
    K = np.array(
        [
            [fx, skew, draw(st.floats(0.0, float(width)))],
            [0.0, fy, draw(st.floats(0.0, float(height)))],
            [0.0, 0.0, 1.0],
        ]
    )
    dist = np.array([draw(_finite) for _ in range(n_dist)])
    return CameraModel(width, height, K, dist, model, draw(st.sampled_from(["cam", "left"])))


@FILES
@given(camera=cameras())
def test_camera_info_round_trip(tmp_path, camera):
    path = tmp_path / "camera.yaml"
    write_camera_info(path, camera)
    back = load_camera(path)
    assert (back.width, back.height, back.model, back.name) == (
        camera.width,
        camera.height,
        camera.model,
        camera.name,
    )
    np.testing.assert_array_equal(back.K, camera.K)  # YAML floats keep every digit
    np.testing.assert_array_equal(back.dist, camera.dist)


# --------------------------------------------------------------------------- TUM


def _random_trajectory(rng: np.random.Generator, n: int) -> Trajectory:
    stamps_s = np.sort(rng.uniform(0.0, 1e5, n))
    world_t_cam = rng.uniform(-1e3, 1e3, (n, 3))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Trajectory(stamps_s, world_t_cam, q)


@pytest.mark.parametrize("seed", range(5))
def test_tum_round_trip(tmp_path, seed):
    traj = _random_trajectory(np.random.default_rng(seed), n=1 + 7 * seed)
    write_tum(tmp_path / "t.tum", traj)
    back = read_tum(tmp_path / "t.tum")
    np.testing.assert_allclose(back.stamps_s, traj.stamps_s, rtol=0, atol=TUM_STAMP_ATOL_S * 1e5)
    np.testing.assert_allclose(back.world_t_cam, traj.world_t_cam, rtol=0, atol=TUM_POSITION_ATOL_M)
    np.testing.assert_allclose(back.quat_xyzw, traj.quat_xyzw, rtol=0, atol=4 * TUM_QUAT_ATOL)


def test_tum_round_trip_of_poses_from_matrices(tmp_path):
    rng = np.random.default_rng(11)
    T = np.tile(np.eye(4), (3, 1, 1))
    T[:, :3, 3] = rng.normal(size=(3, 3))
    traj = Trajectory.from_matrices(np.array([0.0, 0.1, 0.2]), T)
    write_tum(tmp_path / "t.tum", traj)
    back = read_tum(tmp_path / "t.tum")
    np.testing.assert_allclose(back.world_T_cam(), T, rtol=0, atol=1e-6)
    assert quat_xyzw_from_rotation(np.eye(3)).shape == (1, 4)


# --------------------------------------------------------------------------- observations JSONL

_px = st.floats(-1e4, 1e4, allow_nan=False, allow_infinity=False)


@st.composite
def sign_observations(draw) -> SignObservation:
    names = draw(st.sets(st.sampled_from([k for k in KEYPOINT_NAMES if k != "center"])))
    keypoints = {name: (draw(_px), draw(_px)) for name in ["center", *sorted(names)]}
    bbox = draw(st.none() | st.tuples(_px, _px, _px, _px))
    return SignObservation(
        code=draw(st.sampled_from(sorted(ALL_CODES))),
        keypoints_px=keypoints,
        bbox_px=bbox,
        sigma_px=draw(st.floats(1e-3, 100.0)),
        score=draw(st.floats(0.0, 1.0)),
    )


@st.composite
def frames(draw) -> list[FrameObservations]:
    n = draw(st.integers(1, 5))
    stamps = sorted(draw(st.lists(st.integers(0, 2**62), min_size=n, max_size=n, unique=True)))
    size = (draw(st.integers(1, 8192)), draw(st.integers(1, 8192)))
    return [
        FrameObservations(i, t, size, tuple(draw(st.lists(sign_observations(), max_size=3))))
        for i, t in enumerate(stamps)
    ]


def _rounded(x: float) -> float:
    return round(float(x), OBS_DECIMALS)


@FILES
@given(written=frames())
def test_observations_round_trip(tmp_path, written):
    path = tmp_path / "observations.jsonl"
    write_observations(path, written)
    back = read_observations(path)
    assert [(f.frame, f.stamp_ns, f.image_size) for f in back] == [
        (f.frame, f.stamp_ns, f.image_size) for f in written
    ]
    for got, want in zip(back, written, strict=True):
        assert len(got.signs) == len(want.signs)
        for g, w in zip(got.signs, want.signs, strict=True):
            assert g.code == w.code
            assert g.keypoints_px == {
                k: (_rounded(u), _rounded(v)) for k, (u, v) in w.keypoints_px.items()
            }
            assert g.bbox_px == (None if w.bbox_px is None else tuple(map(_rounded, w.bbox_px)))
            assert (g.sigma_px, g.score) == (_rounded(w.sigma_px), _rounded(w.score))
    # A second round trip changes nothing: what is written is what is read.
    write_observations(tmp_path / "again.jsonl", back)
    assert (tmp_path / "again.jsonl").read_bytes() == path.read_bytes()


# --------------------------------------------------------------------------- MCAP


@pytest.mark.parametrize("model", [PLUMB_BOB, EQUIDISTANT])
def test_foxglove_calibration_round_trip(model):
    K = np.array([[500.0, 0.0, 320.5], [0.0, 501.0, 240.25], [0.0, 0.0, 1.0]])
    dist = np.array([0.1, -0.02, 0.003, -0.0004] + ([0.0005] if model == PLUMB_BOB else []))
    camera = CameraModel(640, 480, K, dist, model, "camera")
    msg = mcap_io.camera_calibration(1_500_000_000, camera)
    back = camera_from_message("foxglove.CameraCalibration", msg, "test")
    assert (back.width, back.height, back.model) == (640, 480, model)
    np.testing.assert_array_equal(back.K, K)
    np.testing.assert_array_equal(back.dist, dist)
    assert message_stamp_ns("foxglove.CameraCalibration", msg) == 1_500_000_000


@pytest.mark.parametrize("shape", [(6, 8), (6, 8, 3)])
def test_mcap_json_log_round_trip(tmp_path, shape):
    rng = np.random.default_rng(3)
    path = tmp_path / "log.mcap"
    stamps_ns = [10**18 + i * 33_333_333 for i in range(4)]
    images = [rng.integers(0, 255, shape, dtype=np.uint8) for _ in stamps_ns]
    with mcap_io.McapJsonWriter(path) as writer:
        for t, img in zip(stamps_ns, images, strict=True):
            raw = {
                "timestamp": mcap_io.stamp_dict(t),
                "frame_id": "cam_optical",
                "width": shape[1],
                "height": shape[0],
                "encoding": "mono8" if len(shape) == 2 else "bgr8",
                "step": shape[1] * (1 if len(shape) == 2 else 3),
                "data": base64.b64encode(img.tobytes()).decode(),
            }
            writer.write("/raw", "RawImage", raw, t)
    log = mcap_io.McapLog(path)
    assert [(c.topic, c.schema_name, c.message_count) for c in log.channels] == [
        ("/raw", "foxglove.RawImage", 4)
    ]
    for msg, t, img in zip(log.messages(["/raw"]), stamps_ns, images, strict=True):
        assert msg.log_time_ns == t
        assert message_stamp_ns(msg.schema_name, msg.decoded) == t
        back, reason = image_from_message(msg.schema_name, msg.decoded)
        assert reason == ""
        np.testing.assert_array_equal(back, img)


def _raw(image: np.ndarray, encoding: str, step_pad: int = 0) -> dict:
    h, w = image.shape[:2]
    rows = image.reshape(h, -1)
    padded = np.hstack([rows, np.zeros((h, step_pad), np.uint8)])
    return {
        "width": w,
        "height": h,
        "encoding": encoding,
        "step": padded.shape[1],
        "data": padded.tobytes(),
    }


@pytest.mark.parametrize(
    "encoding, make",
    [
        ("rgb8", lambda bgr: cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)),
        ("bgra8", lambda bgr: cv2.cvtColor(bgr, cv2.COLOR_BGR2BGRA)),
        ("yuv422_yuy2", lambda bgr: cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_YUY2)),
        ("yuv422", lambda bgr: cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_UYVY)),
    ],
)
def test_raw_colour_encodings_decode_to_bgr(encoding, make):
    bgr = np.zeros((6, 8, 3), np.uint8)
    bgr[:] = (10, 100, 200)
    image, reason = image_from_message("sensor_msgs/msg/Image", _raw(make(bgr), encoding, 3))
    assert reason == ""
    np.testing.assert_allclose(image.astype(int), bgr.astype(int), atol=2)  # YUV rounds


@pytest.mark.parametrize("pattern", ["rggb", "bggr", "gbrg", "grbg"])
def test_bayer_mosaics_decode_to_their_colour(pattern):
    value = {"r": 200, "g": 100, "b": 10}
    mosaic = np.zeros((8, 8), np.uint8)
    for k, (dy, dx) in enumerate(((0, 0), (0, 1), (1, 0), (1, 1))):
        mosaic[dy::2, dx::2] = value[pattern[k]]
    image, reason = image_from_message("sensor_msgs/msg/Image", _raw(mosaic, f"bayer_{pattern}8"))
    assert reason == ""
    np.testing.assert_array_equal(image[3:5, 3:5], np.full((2, 2, 3), (10, 100, 200)))


@pytest.mark.parametrize(
    "change, reason",
    [
        ({"width": "abc"}, "malformed raw image"),
        ({"height": -3}, "not usable"),
        ({"encoding": "32fc1"}, "unsupported raw image encoding"),
        ({"data": b"\0" * 10}, "too short"),
    ],
)
def test_malformed_raw_images_are_reasons_not_exceptions(change, reason):
    msg = {**_raw(np.zeros((6, 8), np.uint8), "mono8"), **change}
    image, why = image_from_message("sensor_msgs/msg/Image", msg)
    assert image is None and reason in why


def test_a_ground_truth_time_given_twice_is_refused(tmp_path):
    p = tmp_path / "gt.tum"
    p.write_text("0.0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n0.1 2 0 0 0 0 0 1\n")
    with pytest.raises(
        InputError, match=r"gt.tum: 1 time\(s\) given twice \(first: 0.100000000 s\)"
    ):
        read_ground_truth(p)
    p.write_text("0.0 0 0 0 0 0 0 1\n0.1 1 0 0 0 0 0 1\n")
    assert len(read_ground_truth(p).stamps_s) == 2
