"""rosbag2 bags in: folders and files, MCAP and sqlite3 storage, every compression mode.

The bags are written here with the ``rosbags`` writer (what rosbags-based
recorders produce; the layout is ``ros2 bag record``'s), never downloaded.
Images are PNG, so a bag's frames are compared byte for byte with the same
PNGs read as a folder.
"""

from __future__ import annotations

import os
import random
import re
import shutil
import sqlite3
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from mcap.stream_reader import StreamReader
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Reader, StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore
from signpose.estimator.camera import CameraModel
from signpose.estimator.trajectory import Trajectory, rotation_from_quat_xyzw
from signpose.frontend.observations import FrameObservations
from signpose.maps.loader import bundled_map_path, load_map

from signpose import pipeline
from signpose.cli import main as cli_main
from signpose.core.errors import InputError, OutputError
from signpose.io import mcap as mcap_io
from signpose.io import rosbag_write
from signpose.io.camera_file import write_camera_info
from signpose.io.frames_csv import FrameStamp, read_frames_csv, write_frames_csv
from signpose.io.rosbag import read_bag_info
from signpose.io.rosbag_write import ResultBag, write_result_bag
from signpose.io.sources import BagSource, FolderSource, open_source
from signpose.io.tum import read_tum
from signpose.sim.flight import SimSettings, simulate

STORE = get_typestore(Stores.ROS2_HUMBLE)
IMAGE_TOPIC = "/camera/image_raw/compressed"
RAW_TOPIC = "/camera/image_raw"
INFO_TOPIC = "/camera/camera_info"
FRAME_ID = "camera_optical_frame"
EPOCH_S = 1_700_000_000  # bags are stamped in epoch time
PERIOD_NS = 50_000_000
LARGE = (240, 320, 3)  # ~230 kB of PNG: 20 frames fill several 1 MiB MCAP chunks
STORAGES = {"mcap": StoragePlugin.MCAP, "sqlite3": StoragePlugin.SQLITE3}
COMPRESSIONS = {"none": None, "file": CompressionMode.FILE, "message": CompressionMode.MESSAGE}


def _msg(name: str):
    return STORE.types[name]


def _header(stamp_ns: int):
    Header, Time = _msg("std_msgs/msg/Header"), _msg("builtin_interfaces/msg/Time")
    return Header(stamp=Time(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9), frame_id=FRAME_ID)


def _camera_info(stamp_ns: int):
    roi = _msg("sensor_msgs/msg/RegionOfInterest")(
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    return _msg("sensor_msgs/msg/CameraInfo")(
        header=_header(stamp_ns),
        height=48,
        width=64,
        distortion_model="plumb_bob",
        d=np.array([0.01, -0.002, 0.0, 0.0, 0.0]),
        k=np.array([60.0, 0.0, 31.5, 0.0, 61.0, 23.5, 0.0, 0.0, 1.0]),
        r=np.eye(3).reshape(-1),
        p=np.array([60.0, 0.0, 31.5, 0.0, 0.0, 61.0, 23.5, 0.0, 0.0, 0.0, 1.0, 0.0]),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )


def _images(n: int, seed: int = 0, shape: tuple[int, ...] = (48, 64, 3)) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 255, shape, dtype=np.uint8) for _ in range(n)]


def _stamps(n: int) -> list[int]:
    return [EPOCH_S * 10**9 + i * PERIOD_NS for i in range(n)]


def write_bag(
    path: Path,
    images: list[np.ndarray],
    *,
    storage: str = "mcap",
    compression: str = "none",
    camera_info: bool = True,
    raw: bool = False,
    first: int = 0,
) -> Path:
    """A bag with PNG CompressedImage (or raw bgr8 Image) frames and one CameraInfo.

    Frame i of the bag is stamped as frame ``first + i`` of a flight.
    """
    writer = Writer(path, version=8, storage_plugin=STORAGES[storage])
    if COMPRESSIONS[compression] is not None:
        writer.set_compression(COMPRESSIONS[compression], CompressionFormat.ZSTD)
    kind = "sensor_msgs/msg/Image" if raw else "sensor_msgs/msg/CompressedImage"
    with writer:
        images_conn = writer.add_connection(
            RAW_TOPIC if raw else IMAGE_TOPIC, kind, typestore=STORE
        )
        info_conn = None
        if camera_info:
            info_conn = writer.add_connection(
                INFO_TOPIC, "sensor_msgs/msg/CameraInfo", typestore=STORE
            )
        stamps = _stamps(first + len(images))[first:]
        for i, (stamp_ns, image) in enumerate(zip(stamps, images, strict=True)):
            log_ns = stamp_ns + 7_000_000  # received a little after capture
            if info_conn is not None and i == 0:
                data = STORE.serialize_cdr(_camera_info(stamp_ns), "sensor_msgs/msg/CameraInfo")
                writer.write(info_conn, log_ns, data)
            if raw:
                msg = _msg(kind)(
                    header=_header(stamp_ns),
                    height=image.shape[0],
                    width=image.shape[1],
                    encoding="bgr8",
                    is_bigendian=0,
                    step=image.shape[1] * 3,
                    data=image.reshape(-1),
                )
            else:
                ok, png = cv2.imencode(".png", image)
                assert ok
                msg = _msg(kind)(header=_header(stamp_ns), format="png", data=png.reshape(-1))
            writer.write(images_conn, log_ns, STORE.serialize_cdr(msg, kind))
    return path


def _folder_frames(tmp_path: Path, images: list[np.ndarray]):
    folder = tmp_path / "pngs"
    folder.mkdir()
    rows = []
    for i, (stamp_ns, image) in enumerate(zip(_stamps(len(images)), images, strict=True)):
        cv2.imwrite(str(folder / f"{i:04d}.png"), image)
        rows.append(FrameStamp(f"{i:04d}.png", stamp_ns))
    write_frames_csv(folder / "frames.csv", rows)
    return list(FolderSource(folder))


@pytest.mark.parametrize("compression", sorted(COMPRESSIONS))
@pytest.mark.parametrize("storage", sorted(STORAGES))
def test_bag_folder_reads_like_the_same_pngs(tmp_path, storage, compression):
    images = _images(6)
    bag = write_bag(tmp_path / "bag", images, storage=storage, compression=compression)
    source = open_source(bag)
    assert isinstance(source, BagSource)
    assert (source.topic, source.length) == (IMAGE_TOPIC, 6)
    frames = list(source)
    expected = _folder_frames(tmp_path, images)
    assert [f.stamp_ns for f in frames] == [f.stamp_ns for f in expected]  # header stamps
    for got, want in zip(frames, expected, strict=True):
        np.testing.assert_array_equal(got.image, want.image)
    assert source.problems == []
    assert source.frame_id == FRAME_ID
    cam = source.camera
    assert cam is not None and (cam.width, cam.height) == (64, 48)
    np.testing.assert_array_equal(cam.K, [[60.0, 0.0, 31.5], [0.0, 61.0, 23.5], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("storage", sorted(STORAGES))
def test_a_storage_file_of_a_bag_reads_with_the_bags_compression(tmp_path, storage):
    images = _images(3, seed=1)
    bag = write_bag(tmp_path / "bag", images, storage=storage, compression="message")
    (file,) = [p for p in bag.iterdir() if p.name != "metadata.yaml"]
    frames = list(open_source(file))
    np.testing.assert_array_equal(frames[2].image, images[2])


def test_raw_images_in_a_db3(tmp_path):
    images = _images(3, seed=2)
    bag = write_bag(tmp_path / "bag", images, storage="sqlite3", raw=True, camera_info=False)
    (db3,) = bag.glob("*.db3")
    os.remove(bag / "metadata.yaml")  # a lone .db3, as copied off a robot
    source = open_source(db3)
    assert source.topic == RAW_TOPIC and source.camera is None
    frames = list(source)
    for got, want in zip(frames, images, strict=True):
        np.testing.assert_array_equal(got.image, want)


def test_header_stamp_zero_falls_back_to_the_log_time(tmp_path):
    bag = tmp_path / "bag"
    writer = Writer(bag, version=8, storage_plugin=StoragePlugin.SQLITE3)
    kind = "sensor_msgs/msg/CompressedImage"
    ok, png = cv2.imencode(".png", _images(1)[0])
    with writer:
        conn = writer.add_connection(IMAGE_TOPIC, kind, typestore=STORE)
        for i in range(2):
            msg = _msg(kind)(header=_header(0), format="png", data=png.reshape(-1))
            writer.write(conn, 5_000 + i, STORE.serialize_cdr(msg, kind))
    assert [f.stamp_ns for f in open_source(bag)] == [5_000, 5_001]


def test_a_recording_killed_before_metadata_was_written(tmp_path):
    bag = write_bag(tmp_path / "bag", _images(4), storage="sqlite3")
    os.remove(bag / "metadata.yaml")
    source = open_source(bag)
    assert isinstance(source, BagSource)
    assert len(list(source)) == 4
    assert len(source.problems) == 1 and "no metadata.yaml" in source.problems[0]


def test_truncated_db3_reads_up_to_the_break(tmp_path):
    images = _images(40, seed=3)
    bag = write_bag(tmp_path / "bag", images, storage="sqlite3", camera_info=False)
    (db3,) = bag.glob("*.db3")
    before = db3.read_bytes()
    with open(db3, "r+b") as f:
        f.truncate(int(len(before) * 0.6))
    cut = db3.read_bytes()
    frames = list(source := open_source(bag))
    assert 10 < len(frames) < 40
    for got, want in zip(frames, images, strict=False):
        np.testing.assert_array_equal(got.image, want)
    assert len(source.problems) == 1
    assert f"bag.db3: log stopped after {len(frames)} messages" in source.problems[0]
    assert db3.read_bytes() == cut  # read through a repaired copy, never written


def test_truncated_mcap_in_a_bag_reads_up_to_the_break(tmp_path):
    images = _images(20, seed=4, shape=LARGE)  # several MCAP chunks
    bag = write_bag(tmp_path / "bag", images, storage="mcap", camera_info=False)
    (mcap,) = bag.glob("*.mcap")
    data = mcap.read_bytes()
    mcap.write_bytes(data[: int(len(data) * 0.7)])
    frames = list(source := open_source(bag))
    assert 5 < len(frames) < 20
    assert len(source.problems) == 1 and "truncated or corrupt" in source.problems[0]


def test_truncated_zstd_file_reads_what_decompresses(tmp_path):
    images = _images(20, seed=5, shape=LARGE)
    bag = write_bag(tmp_path / "bag", images, storage="mcap", compression="file")
    (packed,) = bag.glob("*.zstd")
    data = packed.read_bytes()
    packed.write_bytes(data[: int(len(data) * 0.7)])
    frames = list(source := open_source(bag))
    assert 0 < len(frames) < 20
    assert any("compressed file ends inside a frame" in p for p in source.problems)


def _metadata(bag: Path) -> dict:
    return yaml.safe_load((bag / "metadata.yaml").read_text())


@pytest.mark.parametrize(
    "damage, expect",
    [
        (lambda d: "rosbag2_bagfile_information: [\n", "not readable YAML"),
        (lambda d: yaml.safe_dump({"other": 1}), "no 'rosbag2_bagfile_information'"),
        (
            lambda d: yaml.safe_dump(
                {"rosbag2_bagfile_information": {**d, "storage_identifier": "hdf5"}}
            ),
            "storage 'hdf5' is not supported",
        ),
        (
            lambda d: yaml.safe_dump(
                {"rosbag2_bagfile_information": {**d, "relative_file_paths": ["gone.db3"]}}
            ),
            "not in the folder: gone.db3",
        ),
        (
            lambda d: yaml.safe_dump(
                {"rosbag2_bagfile_information": {**d, "compression_format": "lz4"}}
            ),
            "compression format 'lz4' is not supported",
        ),
        (lambda d: "\udcff", "not readable YAML"),
        (lambda d: "a: " + "[" * 5000, "nested deeper than 64"),
    ],
)
def test_corrupt_metadata_is_one_line_naming_the_file(tmp_path, damage, expect):
    bag = write_bag(tmp_path / "bag", _images(2), storage="sqlite3", compression="message")
    info = _metadata(bag)["rosbag2_bagfile_information"]
    text = damage(info)
    (bag / "metadata.yaml").write_bytes(text.encode("utf-8", "surrogateescape"))
    with pytest.raises(InputError) as err:
        open_source(bag)
    message = str(err.value)
    assert message.startswith(str(bag / "metadata.yaml")) and expect in message
    assert "\n" not in message


def test_bag_without_an_image_topic_lists_its_topics(tmp_path):
    bag = tmp_path / "bag"
    with Writer(bag, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection(INFO_TOPIC, "sensor_msgs/msg/CameraInfo", typestore=STORE)
        writer.write(conn, 1, STORE.serialize_cdr(_camera_info(1), "sensor_msgs/msg/CameraInfo"))
    with pytest.raises(InputError, match="no image topic.*/camera/camera_info"):
        open_source(bag)


def test_wrong_topic_in_a_bag_lists_the_image_topics(tmp_path):
    bag = write_bag(tmp_path / "bag", _images(2), storage="sqlite3")
    with pytest.raises(InputError, match=f"no topic '/nope'.*{IMAGE_TOPIC}"):
        open_source(bag, topic="/nope")
    with pytest.raises(InputError, match="holds sensor_msgs/msg/CameraInfo, not images"):
        open_source(bag, topic=INFO_TOPIC)


def test_a_db3_that_is_not_sqlite(tmp_path):
    path = tmp_path / "flight.db3"
    path.write_bytes(b"\x00" * 4096)
    with pytest.raises(InputError, match="flight.db3: not an SQLite database"):
        open_source(path)


def test_a_db3_without_bag_tables(tmp_path):
    path = tmp_path / "other.db3"
    with sqlite3.connect(path) as con:
        con.execute("CREATE TABLE t (x INTEGER)")
    with pytest.raises(InputError, match="other.db3: not a readable rosbag2 sqlite3 file"):
        open_source(path)


def test_a_corrupt_message_is_skipped_and_reported(tmp_path):
    images = _images(3, seed=6)
    bag = write_bag(tmp_path / "bag", images, storage="sqlite3", camera_info=False)
    (db3,) = bag.glob("*.db3")
    with sqlite3.connect(db3) as con:
        con.execute("UPDATE messages SET data = x'0001' WHERE id = 2")
    frames = list(source := open_source(bag))
    assert len(frames) == 2
    np.testing.assert_array_equal(frames[1].image, images[2])
    assert len(source.problems) == 1 and "message 1: cannot decode" in source.problems[0]


def test_split_bag_reads_every_file_in_order(tmp_path):
    images = _images(6, seed=7)
    first = write_bag(tmp_path / "a", images[:3], storage="sqlite3", camera_info=False)
    second = write_bag(tmp_path / "b", images[3:], storage="sqlite3", camera_info=False, first=3)
    bag = tmp_path / "bag"
    bag.mkdir()
    shutil.move(next(first.glob("*.db3")), bag / "bag_0.db3")
    shutil.move(next(second.glob("*.db3")), bag / "bag_1.db3")
    meta = _metadata(first)
    info = meta["rosbag2_bagfile_information"]
    info["relative_file_paths"] = ["bag_0.db3", "bag_1.db3"]
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
    assert [p.name for p in read_bag_info(bag).files] == ["bag_0.db3", "bag_1.db3"]
    source = open_source(bag)
    assert source.length == 6
    frames = list(source)
    assert [f.stamp_ns for f in frames] == _stamps(6)
    for got, want in zip(frames, images, strict=True):
        np.testing.assert_array_equal(got.image, want)


# --------------------------------------------------------------------------- ROS 2 out


def _result_inputs(n: int = 4):
    sign_map = load_map(bundled_map_path())
    stamps_ns = _stamps(n)
    frames = tuple(FrameObservations(i, t, (64, 48), ()) for i, t in enumerate(stamps_ns))
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = np.arange(n) * 0.5
    T[:, 1, 3] = 20.0
    T[:, :3, :3] = rotation_from_quat_xyzw(np.array([[0.1, -0.2, 0.3, 0.9]]))[0]
    bad = T.copy()
    bad[1, :3, 3] = np.nan  # a frame without an estimate
    stamps_s = np.array(stamps_ns) / 1e9
    trajectories = {
        "baseline": Trajectory.from_matrices(stamps_s, bad),
        "smoothed": Trajectory.from_matrices(stamps_s, T),
    }
    camera = CameraModel(64, 48, np.array([[60.0, 0, 31.5], [0, 61.0, 23.5], [0, 0, 1]]),
                         np.array([0.01, -0.002, 0.0, 0.0, 0.0]))  # fmt: skip
    return ResultBag(sign_map, frames, trajectories, camera, FRAME_ID), T, stamps_ns


def _assert_pose(pose, T):
    p, q = pose.position, pose.orientation
    np.testing.assert_allclose([p.x, p.y, p.z], T[:3, 3], rtol=0, atol=1e-12)
    R = rotation_from_quat_xyzw(np.array([[q.x, q.y, q.z, q.w]]))[0]
    np.testing.assert_allclose(R, T[:3, :3], rtol=0, atol=1e-12)


def test_result_bag_reads_back_with_rosbags(tmp_path):
    bag, T, stamps_ns = _result_inputs()
    path = write_result_bag(tmp_path / "result_bag", bag)
    meta = _metadata(path)["rosbag2_bagfile_information"]
    assert meta["storage_identifier"] == "mcap"
    by_topic: dict[str, list] = {}
    with Reader(path) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        for conn, log_ns, raw in reader.messages():
            msg = STORE.deserialize_cdr(raw, conn.msgtype)
            by_topic.setdefault(conn.topic, []).append((log_ns, msg))
    assert types == {
        "/signpose/baseline/pose": "geometry_msgs/msg/PoseStamped",
        "/signpose/smoothed/pose": "geometry_msgs/msg/PoseStamped",
        "/signpose/baseline/path": "nav_msgs/msg/Path",
        "/signpose/smoothed/path": "nav_msgs/msg/Path",
        "/tf": "tf2_msgs/msg/TFMessage",
        "/signpose/signs": "visualization_msgs/msg/MarkerArray",
        "/camera/camera_info": "sensor_msgs/msg/CameraInfo",
    }
    world = bag.sign_map.frame
    smoothed = by_topic["/signpose/smoothed/pose"]
    assert [t for t, _ in smoothed] == stamps_ns  # epoch stamps, not 1970
    for (t, msg), want in zip(smoothed, T, strict=True):
        assert (msg.header.frame_id, msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec) == (
            world,
            t,
        )
        _assert_pose(msg.pose, want)
    baseline = by_topic["/signpose/baseline/pose"]
    assert [t for t, _ in baseline] == [stamps_ns[0], *stamps_ns[2:]]  # NaN frame left out
    ((_, path_msg),) = by_topic["/signpose/smoothed/path"]
    assert len(path_msg.poses) == 4 and path_msg.header.frame_id == world
    _assert_pose(path_msg.poses[3].pose, T[3])
    tfs = by_topic["/tf"]
    assert len(tfs) == 4
    for (_, msg), want in zip(tfs, T, strict=True):
        (tf,) = msg.transforms
        assert (tf.header.frame_id, tf.child_frame_id) == (world, FRAME_ID)
        tr = tf.transform.translation
        np.testing.assert_allclose([tr.x, tr.y, tr.z], want[:3, 3], rtol=0, atol=1e-12)
    ((_, markers),) = by_topic["/signpose/signs"]
    texts = sorted(m.text for m in markers.markers if m.text)
    assert texts == sorted(bag.sign_map.codes)
    assert len(markers.markers) == 2 * len(bag.sign_map.signs)
    ((_, info),) = by_topic["/camera/camera_info"]
    assert (info.width, info.height, info.header.frame_id) == (64, 48, FRAME_ID)
    np.testing.assert_array_equal(info.k.reshape(3, 3), bag.camera.K)
    np.testing.assert_array_equal(info.d, bag.camera.dist)


def test_result_bag_mcap_has_the_ros2_profile(tmp_path):
    bag, _, _ = _result_inputs(2)
    path = write_result_bag(tmp_path / "result_bag", bag)
    (mcap_file,) = path.glob("*.mcap")
    with open(mcap_file, "rb") as f:
        header = next(r for r in StreamReader(f).records if type(r).__name__ == "Header")
    assert header.profile == "ros2"


def test_result_bag_replaces_an_older_one_whole(tmp_path):
    bag, _, _ = _result_inputs(3)
    target = tmp_path / "result_bag"
    write_result_bag(target, bag)
    (target / "stale.txt").write_text("from an older run")
    write_result_bag(target, bag)
    assert sorted(p.name for p in target.iterdir()) == ["metadata.yaml", "result_bag.mcap"]
    assert [p.name for p in tmp_path.iterdir()] == ["result_bag"]  # no temporary left


def test_result_bag_in_a_folder_that_cannot_be_written(tmp_path):
    bag, _, _ = _result_inputs(2)
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(OutputError, match=str(blocker / "result_bag")):
        write_result_bag(blocker / "result_bag", bag)


# --------------------------------------------------------------------------- end to end


@pytest.fixture(scope="module")
def jpeg_flight(tmp_path_factory):
    """A simulated 960x540 flight as a folder of JPEGs, run once by the pipeline."""
    root = tmp_path_factory.mktemp("jpeg_flight")
    sign_map = load_map(bundled_map_path())
    settings = SimSettings(frames=8, width=960, height=540, format="png")
    sim = simulate(sign_map, root / "sim", settings, progress=False)
    folder = root / "jpegs"
    folder.mkdir()
    rows, jpegs = [], []
    for row in read_frames_csv(sim.frames_path / "frames.csv"):
        image = cv2.imread(str(sim.frames_path / row.filename))
        ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 92])
        assert ok
        name = Path(row.filename).with_suffix(".jpg").name
        (folder / name).write_bytes(buf.tobytes())
        rows.append(FrameStamp(name, row.stamp_ns))
        jpegs.append((row.stamp_ns, buf.reshape(-1)))
    write_frames_csv(folder / "frames.csv", rows)
    run_settings = pipeline.RunSettings(plots=False, mcap=False)
    pipeline.run(folder, sign_map, root / "run", camera=sim.camera, settings=run_settings,
                 progress=False)  # fmt: skip
    return sim, jpegs, root / "run", run_settings


def _jpeg_bag(path: Path, jpegs, storage: str, compression: str) -> Path:
    writer = Writer(path, version=8, storage_plugin=STORAGES[storage])
    if COMPRESSIONS[compression] is not None:
        writer.set_compression(COMPRESSIONS[compression], CompressionFormat.ZSTD)
    kind = "sensor_msgs/msg/CompressedImage"
    with writer:
        conn = writer.add_connection(IMAGE_TOPIC, kind, typestore=STORE)
        for stamp_ns, data in jpegs:
            msg = _msg(kind)(header=_header(stamp_ns), format="jpeg", data=data)
            writer.write(conn, stamp_ns, STORE.serialize_cdr(msg, kind))  # frame 0 is at t = 0
    return path


@pytest.mark.parametrize("compression", sorted(COMPRESSIONS))
@pytest.mark.parametrize("storage", sorted(STORAGES))
def test_a_bag_runs_end_to_end_like_the_jpeg_folder(jpeg_flight, tmp_path, storage, compression):
    sim, jpegs, folder_run, run_settings = jpeg_flight
    bag = _jpeg_bag(tmp_path / "bag", jpegs, storage, compression)
    out = tmp_path / "run"
    result = pipeline.run(bag, load_map(bundled_map_path()), out, camera=sim.camera,
                          settings=run_settings, progress=False)  # fmt: skip
    assert result.n_frames == 8
    observed = (out / "observations.jsonl").read_bytes()
    assert observed == (folder_run / "observations.jsonl").read_bytes()
    for method in ("baseline", "pnp", "smoothed"):
        got, want = read_tum(out / f"{method}.tum"), read_tum(folder_run / f"{method}.tum")
        np.testing.assert_array_equal(got.stamps_s, want.stamps_s)
        np.testing.assert_allclose(got.world_t_cam, want.world_t_cam, rtol=0, atol=1e-6)


def test_a_bag_keeps_its_own_clock(tmp_path):
    bag = write_bag(tmp_path / "bag", _images(2), storage="sqlite3")
    with pytest.raises(InputError, match="a log has its own times"):
        open_source(bag, start_ns=10**18)
    assert open_source(bag).clock == "log"


BAG_FUZZ_CASES = 60


def test_damaged_bags_raise_only_input_error(tmp_path):
    """Bytes cut, flipped or overwritten in a bag's files: InputError or reported problems."""
    rng = random.Random(13)
    sources = [
        write_bag(tmp_path / f"{s}_{c}", _images(4), storage=s, compression=c)
        for s in sorted(STORAGES)
        for c in sorted(COMPRESSIONS)
    ]
    escaped = []
    for case in range(BAG_FUZZ_CASES):
        bag = shutil.copytree(rng.choice(sources), tmp_path / f"case{case}")
        target = rng.choice(sorted(bag.iterdir()))
        data = bytearray(target.read_bytes())
        if rng.random() < 0.3:
            del data[rng.randrange(len(data)) :]
        else:
            for _ in range(rng.randint(1, 20)):
                data[rng.randrange(len(data))] = rng.randrange(256)
        target.write_bytes(bytes(data))
        try:
            list(open_source(bag))
        except InputError:
            pass
        except Exception as exc:  # noqa: BLE001 - what the test looks for
            escaped.append(f"{target.name}: {type(exc).__name__}: {exc}")
        shutil.rmtree(bag)
    assert not escaped, escaped[:3]


def test_images_stamped_backwards_are_skipped_not_restamped(tmp_path):
    images = _images(3, seed=8)
    first = write_bag(tmp_path / "a", images, storage="sqlite3", camera_info=False)
    (db3,) = first.glob("*.db3")
    with sqlite3.connect(db3) as con:  # message 2 republishes message 1's stamp
        (data,) = con.execute("SELECT data FROM messages WHERE id = 2").fetchone()
        con.execute("UPDATE messages SET data = ? WHERE id = 3", (data,))
    source = open_source(first)
    assert [f.stamp_ns for f in source] == _stamps(2)
    assert source.problems == [
        f"{first}: {IMAGE_TOPIC}: 1 image(s) stamped at or before the previous image skipped "
        "(first: message 2); frame times must increase"
    ]


def test_run_writes_a_ros2_bag_with_the_inputs_frame_id(jpeg_flight, tmp_path, capsys):
    sim, jpegs, _, _ = jpeg_flight
    bag = _jpeg_bag(tmp_path / "bag", jpegs, "sqlite3", "none")
    camera = tmp_path / "camera.yaml"
    write_camera_info(camera, sim.camera)
    out = tmp_path / "run"
    argv = ["run", str(bag), "--map", str(bundled_map_path()), "--camera", str(camera)]
    assert cli_main([*argv, "--out", str(out), "--ros2-bag", "--no-plots", "-q"]) == 0
    capsys.readouterr()
    with Reader(out / "result_bag") as reader:
        tf = [
            STORE.deserialize_cdr(raw, conn.msgtype)
            for conn, _, raw in reader.messages()
            if conn.topic == "/tf"
        ]
    assert len(tf) == 8
    assert {m.transforms[0].child_frame_id for m in tf} == {FRAME_ID}
    transforms = mcap_io.read_json_messages(out / "result.mcap", mcap_io.TF_TOPIC)
    assert {t["transforms"][0]["child_frame_id"] for t in transforms} == {FRAME_ID}


def test_result_bag_over_a_file_is_refused(tmp_path):
    bag, _, _ = _result_inputs(2)
    target = tmp_path / "result_bag"
    target.write_text("not a bag")
    with pytest.raises(OutputError, match="exists and is not a folder"):
        write_result_bag(target, bag)
    assert target.read_text() == "not a bag"


def test_result_bag_staging_folder_carries_the_pid_and_a_killed_ones_is_removed(
    tmp_path, monkeypatch
):
    bag, _, _ = _result_inputs(2)
    target = tmp_path / "result_bag"
    dead = subprocess.Popen(["true"])
    dead.wait()  # its pid no longer runs: like a writer killed before its rename
    killed = tmp_path / f".result_bag.{dead.pid}.abcd1234.tmp"
    (killed / "result_bag").mkdir(parents=True)
    live = tmp_path / f".result_bag.{os.getppid()}.abcd1234.tmp"  # a live writer's
    live.mkdir()
    staging = []
    real_swap_in = rosbag_write._swap_in

    def swap_in(staged, to):
        staging.append(staged.parent.name)
        real_swap_in(staged, to)

    monkeypatch.setattr(rosbag_write, "_swap_in", swap_in)
    write_result_bag(target, bag)
    assert re.fullmatch(rf"\.result_bag\.{os.getpid()}\.[a-z0-9_]{{8}}\.tmp", staging[0])
    assert sorted(p.name for p in tmp_path.iterdir()) == [live.name, "result_bag"]
