"""MCAP logs: writing with our schemas, reading images/camera back, bad logs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from signpose.estimator.camera import pinhole_camera
from signpose.estimator.trajectory import Trajectory
from signpose.frontend.observations import FrameObservations, SignObservation
from signpose.maps.loader import bundled_map_path, load_map

from signpose.core.errors import InputError
from signpose.io import mcap as mcap_io
from signpose.io.sources import McapSource, open_source

REFERENCE = Path(__file__).resolve().parents[2] / "shared" / "reference" / "foxglove-jsonschema"


def _validate(name: str, message: dict) -> None:
    """Validate against our own schema always, and Foxglove's reference when present."""
    import jsonschema

    jsonschema.validate(message, mcap_io.schema(name))
    ref = REFERENCE / f"{name}.json"
    if ref.is_file():
        jsonschema.validate(message, json.loads(ref.read_text()))


def _images(rng: np.random.Generator, n: int, w: int = 64, h: int = 48) -> list[np.ndarray]:
    return [rng.integers(0, 255, (h, w, 3), dtype=np.uint8) for _ in range(n)]


def _poses(n: int) -> np.ndarray:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = np.arange(n) * 0.5
    T[:, 1, 3] = 20.0
    return T


def _write_flight(path: Path, rng: np.random.Generator, n: int = 5) -> tuple:
    camera = pinhole_camera(64, 48, 60.0)
    stamps = [1_000_000_000 + i * 100_000_000 for i in range(n)]
    with mcap_io.McapFrameWriter(path, camera, "demo_pylon", _poses(n)) as writer:
        for i, (t, img) in enumerate(zip(stamps, _images(rng, n), strict=True)):
            writer.write(i, t, img)
    return camera, stamps


def test_frame_writer_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    path = tmp_path / "flight.mcap"
    camera, stamps = _write_flight(path, rng)
    source = open_source(path)
    assert isinstance(source, McapSource)
    assert source.topic == mcap_io.IMAGE_TOPIC
    assert source.length == 5
    assert source.camera is not None
    assert source.camera.image_size == (64, 48)
    np.testing.assert_allclose(source.camera.K, camera.K)
    frames = list(source)
    assert [f.stamp_ns for f in frames] == stamps
    assert frames[0].image.shape == (48, 64, 3)
    assert source.problems == []
    gt = mcap_io.read_json_messages(path, mcap_io.GROUNDTRUTH_TOPIC)
    assert len(gt) == 5
    assert gt[2]["pose"]["position"]["x"] == pytest.approx(1.0)
    assert gt[2]["timestamp"] == {"sec": 1, "nsec": 200_000_000}


def test_every_written_message_matches_the_schemas(tmp_path):
    rng = np.random.default_rng(1)
    sign_map = load_map(bundled_map_path())
    n = 4
    stamps_ns = [i * 50_000_000 for i in range(n)]
    frames = [
        FrameObservations(
            i,
            t,
            (64, 48),
            (SignObservation("0101", {"center": (10.0 + i, 20.0)}, (5.0, 15.0, 10.0, 10.0)),),
        )
        for i, t in enumerate(stamps_ns)
    ]
    traj = Trajectory.from_matrices(np.array(stamps_ns) / 1e9, _poses(n))
    bad = _poses(n)
    bad[1, :3, 3] = np.nan  # a frame without an estimate
    baseline = Trajectory.from_matrices(np.array(stamps_ns) / 1e9, bad)
    path = tmp_path / "result.mcap"
    images = list(zip(stamps_ns, _images(rng, n), strict=True))
    mcap_io.write_result_mcap(
        path,
        sign_map,
        frames,
        {"baseline": baseline, "smoothed": traj},
        camera=pinhole_camera(64, 48),
        images=images,
    )
    log = mcap_io.McapLog(path)
    topics = {c.topic: c for c in log.channels}
    expected = {
        "/signpose/baseline/pose": ("PoseInFrame", n - 1),
        "/signpose/smoothed/pose": ("PoseInFrame", n),
        mcap_io.TF_TOPIC: ("FrameTransforms", n),
        mcap_io.SCENE_TOPIC: ("SceneUpdate", 1),
        mcap_io.ANNOTATIONS_TOPIC: ("ImageAnnotations", n),
        mcap_io.IMAGE_TOPIC: ("CompressedImage", n),
        mcap_io.CALIBRATION_TOPIC: ("CameraCalibration", 1),
    }
    for topic, (name, count) in expected.items():
        assert topics[topic].schema_name == f"foxglove.{name}"
        assert topics[topic].message_encoding == "json"
        assert topics[topic].message_count == count, topic
    seen = 0
    for msg in log.messages(list(expected)):
        _validate(msg.schema_name.removeprefix("foxglove."), msg.decoded)
        seen += 1
    assert seen == sum(c for _, c in expected.values())
    scene = mcap_io.read_json_messages(path, mcap_io.SCENE_TOPIC)[0]
    ids = {e["id"] for e in scene["entities"]}
    assert {f"sign/{c}" for c in sign_map.codes} <= ids
    assert {"trajectory/baseline", "trajectory/smoothed"} <= ids
    texts = [t["text"] for e in scene["entities"] for t in e["texts"]]
    assert sorted(texts) == sorted(sign_map.codes)
    ann = mcap_io.read_json_messages(path, mcap_io.ANNOTATIONS_TOPIC)[3]
    assert ann["texts"][0]["text"] == "0101"
    assert ann["circles"][0]["position"] == {"x": 13.0, "y": 20.0}


def test_simulator_messages_match_the_schemas(tmp_path):
    rng = np.random.default_rng(2)
    path = tmp_path / "sim.mcap"
    _write_flight(path, rng, n=2)
    log = mcap_io.McapLog(path)
    names = set()
    for msg in log.messages([c.topic for c in log.channels]):
        _validate(msg.schema_name.removeprefix("foxglove."), msg.decoded)
        names.add(msg.schema_name)
    assert names == {
        "foxglove.CameraCalibration",
        "foxglove.CompressedImage",
        "foxglove.PoseInFrame",
        "foxglove.FrameTransforms",
    }


def test_raw_image_json_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    img = rng.integers(0, 255, (6, 8, 3), dtype=np.uint8)
    msg = {
        "timestamp": mcap_io.stamp_dict(5),
        "frame_id": "cam",
        "width": 8,
        "height": 6,
        "encoding": "rgb8",
        "step": 8 * 3,
        "data": __import__("base64").b64encode(img[:, :, ::-1].tobytes()).decode(),
    }
    _validate("RawImage", msg)
    path = tmp_path / "raw.mcap"
    with mcap_io.McapJsonWriter(path) as w:
        w.write("/cam/raw", "RawImage", msg, 5)
    frames = list(open_source(path))
    assert len(frames) == 1
    np.testing.assert_array_equal(frames[0].image, img)
    assert frames[0].stamp_ns == 5


# The message definitions every ROS 2 schema below ends with (Header and its Time).
_HEADER_MSGDEFS = """\
================================================================================
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
================================================================================
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
"""

_IMAGE_MSGDEF = (
    """std_msgs/Header header
uint32 height
uint32 width
string encoding
uint8 is_bigendian
uint32 step
uint8[] data
"""
    + _HEADER_MSGDEFS
)

_COMPRESSED_MSGDEF = (
    """std_msgs/Header header
string format
uint8[] data
"""
    + _HEADER_MSGDEFS
)

_CAMERA_INFO_MSGDEF = (
    """std_msgs/Header header
uint32 height
uint32 width
string distortion_model
float64[] d
float64[9] k
float64[9] r
float64[12] p
"""
    + _HEADER_MSGDEFS
)


def test_ros2_image_and_camera_info(tmp_path):
    from mcap_ros2.writer import Writer

    rng = np.random.default_rng(4)
    path = tmp_path / "ros2.mcap"
    grays = [rng.integers(0, 255, (6, 8), dtype=np.uint8) for _ in range(3)]
    with open(path, "wb") as f:
        w = Writer(f)
        img_schema = w.register_msgdef("sensor_msgs/msg/Image", _IMAGE_MSGDEF)
        info_schema = w.register_msgdef("sensor_msgs/msg/CameraInfo", _CAMERA_INFO_MSGDEF)
        header = {"stamp": {"sec": 3, "nanosec": 0}, "frame_id": "cam"}
        w.write_message(
            "/cam/info",
            info_schema,
            {
                "header": header,
                "height": 6,
                "width": 8,
                "distortion_model": "plumb_bob",
                "d": [0.0] * 5,
                "k": [10.0, 0, 3.5, 0, 10.0, 2.5, 0, 0, 1],
                "r": [1.0, 0, 0, 0, 1, 0, 0, 0, 1],
                "p": [10.0, 0, 3.5, 0, 0, 10.0, 2.5, 0, 0, 0, 1, 0],
            },
            log_time=1,
        )
        for i, g in enumerate(grays):
            msg = {
                "header": {"stamp": {"sec": 3, "nanosec": i * 1000}, "frame_id": "cam"},
                "height": 6,
                "width": 8,
                "encoding": "mono8",
                "is_bigendian": 0,
                "step": 8,
                "data": g.tobytes(),
            }
            w.write_message("/cam/image", img_schema, msg, log_time=10 + i)
        w.finish()
    source = open_source(path)
    assert source.topic == "/cam/image"
    assert source.camera is not None and source.camera.fx == 10.0
    frames = list(source)
    assert [f.stamp_ns for f in frames] == [3_000_000_000, 3_000_001_000, 3_000_002_000]
    np.testing.assert_array_equal(frames[1].image, grays[1])


def test_no_image_topic_lists_topics(tmp_path):
    path = tmp_path / "noimg.mcap"
    with mcap_io.McapJsonWriter(path) as w:
        w.write("/pose", "PoseInFrame", mcap_io.pose_in_frame(0, "w", np.eye(4)), 0)
    with pytest.raises(InputError, match=r"no image topic.*/pose \(foxglove.PoseInFrame\)"):
        open_source(path)


def _two_image_topics(path: Path, rng: np.random.Generator) -> None:
    with mcap_io.McapJsonWriter(path) as w:
        for topic in ("/left/image", "/right/image"):
            img = rng.integers(0, 255, (8, 8), dtype=np.uint8)
            w.write(topic, "CompressedImage", mcap_io.compressed_image(1, img), 1)


def test_several_image_topics_need_topic(tmp_path):
    path = tmp_path / "two.mcap"
    _two_image_topics(path, np.random.default_rng(5))
    with pytest.raises(InputError, match=r"several image topics.*/left/image.*--topic"):
        open_source(path)
    assert open_source(path, topic="/right/image").topic == "/right/image"


def test_wrong_topic_lists_available(tmp_path):
    path = tmp_path / "two.mcap"
    _two_image_topics(path, np.random.default_rng(6))
    with pytest.raises(InputError, match=r"no topic '/cam'.*/left/image, /right/image"):
        open_source(path, topic="/cam")


def test_truncated_mcap_reads_what_is_there(tmp_path):
    rng = np.random.default_rng(7)
    path = tmp_path / "flight.mcap"
    n = 40
    camera = pinhole_camera(64, 48)
    # Small chunks, so that a cut keeps most frames.
    with mcap_io.McapFrameWriter(path, camera, chunk_size=4096) as writer:
        for i, img in enumerate(_images(rng, n)):
            writer.write(i, i * 1000, img)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) * 2 // 3])
    source = open_source(cut)
    assert source.length is None  # no summary section any more
    frames = list(source)
    assert 0 < len(frames) < n
    assert [f.stamp_ns for f in frames] == [i * 1000 for i in range(len(frames))]
    assert len(source.problems) == 1
    assert "stopped after" in source.problems[0]
    assert "truncated or corrupt" in source.problems[0]
    assert f"read {len(frames)} images" in source.problems[0]


def test_garbage_mcap_is_input_error(tmp_path):
    path = tmp_path / "bad.mcap"
    path.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 4)
    with pytest.raises(InputError, match="bad.mcap"):
        open_source(path)


def test_writer_abort_leaves_no_file(tmp_path):
    path = tmp_path / "out.mcap"
    with pytest.raises(KeyboardInterrupt), mcap_io.McapJsonWriter(path) as w:
        w.write("/p", "PoseInFrame", mcap_io.pose_in_frame(0, "w", np.eye(4)), 0)
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_ros2_compressed_image(tmp_path):
    import cv2
    from mcap_ros2.writer import Writer

    rng = np.random.default_rng(8)
    img = rng.integers(0, 255, (12, 16, 3), dtype=np.uint8)
    ok, png = cv2.imencode(".png", img)
    assert ok
    path = tmp_path / "ros2c.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        schema = w.register_msgdef("sensor_msgs/msg/CompressedImage", _COMPRESSED_MSGDEF)
        for i in range(2):
            msg = {
                "header": {"stamp": {"sec": 7, "nanosec": i}, "frame_id": "cam"},
                "format": "png",
                "data": png.tobytes(),
            }
            w.write_message("/cam/compressed", schema, msg, log_time=i + 1)
        w.finish()
    source = open_source(path)
    assert source.camera is None
    frames = list(source)
    assert [f.stamp_ns for f in frames] == [7_000_000_000, 7_000_000_001]
    np.testing.assert_array_equal(frames[0].image, img)  # PNG is lossless
