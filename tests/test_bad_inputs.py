"""Bad inputs at the readers (issue 15): one InputError naming the file, or a reported skip.

Each case is a user's file: it either raises ``InputError`` with one line that
names the file (the CLI prints it and exits 2), or the source reads on and says
in ``problems`` what it skipped. Nothing else escapes; fuzzers with a fixed seed
and budget keep it so.
"""

from __future__ import annotations

import base64
import json
import random
from pathlib import Path

import cv2
import numpy as np
import pytest
from mcap.writer import Writer as McapWriter
from signpose.estimator.camera import pinhole_camera

from signpose.cli import main as cli_main
from signpose.core.errors import InputError, OutputError
from signpose.io import mcap as mcap_io
from signpose.io.camera_file import load_camera, write_camera_info
from signpose.io.frames_csv import FrameStamp, write_frames_csv
from signpose.io.observations import read_observations
from signpose.io.sources import open_source
from signpose.io.tum import read_tum

GOOD_LINE = (
    '{"frame": 0, "stamp_ns": 0, "image_size": [1920, 1080], "signs": [{"code": "0101", '
    '"keypoints_px": {"center": [1.0, 2.0]}, "bbox_px": [1, 2, 3, 4], "sigma_px": 0.4, '
    '"score": 1.0}]}'
)


def _line(sign: dict | None = None, **fields) -> str:
    d = json.loads(GOOD_LINE)
    d.update(fields)
    d["signs"][0].update(sign or {})
    return json.dumps(d)


def _assert_one_line_naming(exc: pytest.ExceptionInfo, path: Path, *parts: str) -> None:
    text = str(exc.value)
    assert text.startswith(str(path)) and "\n" not in text
    for part in parts:
        assert part in text


# --------------------------------------------------------------------------- observations


@pytest.mark.parametrize(
    "second, expect",
    [
        (_line(frame=1, stamp_ns=10).encode() + b"\xff", "line 2: malformed observation (byte"),
        (b'{"frame": 1, "stamp_ns": Infinity, "image_size": [1, 1], "signs": []}', "stamp_ns"),
        (
            b'{"frame": 1, "stamp_ns": 5, "image_size": [1920, -Infinity], "signs": []}',
            "image_size",
        ),
        (b'{"frame": 1, "stamp_ns": 1e300, "image_size": [1, 1], "signs": []}', "stamp_ns"),
        (b"[" * 100_000 + b"]" * 100_000, "line 2: malformed observation"),
        (_line({"score": "high"}, frame=1, stamp_ns=10).encode(), "score must be a number"),
        (_line({"bbox_px": [1, 2, 3, float("nan")]}, frame=1, stamp_ns=10).encode(), "bbox_px"),
        (_line(frame=1, stamp_ns=0).encode(), "stamp_ns 0 repeats line 1's 0"),
        (_line(frame=1, stamp_ns=-5).encode(), "stamp_ns"),
        (_line(frame=True, stamp_ns=10).encode(), "frame must be a whole number"),
    ],
)
def test_bad_observation_lines_are_one_error_naming_the_line(tmp_path, second, expect):
    path = tmp_path / "observations.jsonl"
    path.write_bytes(GOOD_LINE.encode() + b"\n" + second + b"\n")
    with pytest.raises(InputError) as exc:
        read_observations(path)
    _assert_one_line_naming(exc, path, "line 2", expect)


def test_observations_out_of_time_order_name_both_lines(tmp_path):
    path = tmp_path / "observations.jsonl"
    lines = [_line(frame=i, stamp_ns=t) for i, t in enumerate([0, 100, 200, 150])]
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError) as exc:
        read_observations(path)
    _assert_one_line_naming(exc, path, "line 4: stamp_ns 150 is before line 3's 200")


def test_estimate_cli_exits_2_with_one_line(tmp_path, capsys):
    path = tmp_path / "observations.jsonl"
    path.write_bytes(GOOD_LINE.encode() + b"\n\xfe\xff\n")
    camera = tmp_path / "camera.yaml"
    write_camera_info(camera, pinhole_camera(1920, 1080))
    map_path = Path(__file__).resolve().parents[1] / "maps" / "demo_pylon.yaml"
    argv = ["estimate", str(path), "--map", str(map_path), "--camera", str(camera)]
    code = cli_main([*argv, "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.count("\n") == 0 and str(path) in err and "line 2" in err


# --------------------------------------------------------------------------- fuzzing


def _opencv_yaml() -> bytes:
    """An OpenCV FileStorage camera file as cv2 writes it (the fuzzers' seed)."""
    fs = cv2.FileStorage(".yml", cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_MEMORY)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    fs.write("camera_matrix", np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.array([[0.1, -0.02, 0.0, 0.0, 0.01]]))
    fs.write("fisheye_model", 0)
    return fs.releaseAndGetString().encode()


_SEEDS = {
    "observations": (read_observations, GOOD_LINE.encode() + b"\n"),
    "tum": (read_tum, b"0.0 1 2 3 0 0 0 1\n1.0 1 2 3 0 0 0 1\n"),
    "opencv_camera": (load_camera, _opencv_yaml()),
}
_TOKENS = [b"[", b"]", b"{", b"}", b"Infinity", b"-Infinity", b"NaN", b"1e308", b"1e999", b"\xff"]
_TOKENS += [b"\x00", b'"', b":", b",", b"\n", b"-1", b"99999999999999999999999", b"true"]
FUZZ_CASES = 600


def _mutated(rng: random.Random, seed: bytes) -> bytes:
    s = bytearray(seed)
    for _ in range(rng.randint(1, 6)):
        i = rng.randrange(len(s) + 1)
        op = rng.random()
        if op < 0.35:
            s[i:i] = rng.choice(_TOKENS)
        elif op < 0.55:
            del s[i : i + rng.randint(1, 20)]
        elif op < 0.75 and s:
            s[min(i, len(s) - 1)] = rng.randrange(256)
        elif op < 0.85:
            s[i:i] = rng.choice(_TOKENS) * rng.randint(10, 3000)
        else:
            s[i:i] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 5)))
    return bytes(s)


@pytest.mark.parametrize("reader", sorted(_SEEDS))
def test_reader_fuzz_raises_only_input_error(tmp_path, reader):
    read, seed = _SEEDS[reader]
    rng = random.Random(15)
    path = tmp_path / "input"
    escaped = []
    for _ in range(FUZZ_CASES):
        data = _mutated(rng, seed)
        path.write_bytes(data)
        try:
            read(path)
        except InputError as exc:
            assert str(path) in str(exc)
        except Exception as exc:  # noqa: BLE001 - what the test looks for
            escaped.append((type(exc).__name__, data[:80]))
    assert not escaped, escaped[:3]


# --------------------------------------------------------------------------- MCAP messages


def test_mcap_bad_messages_are_skipped_and_reported(tmp_path):
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 255, (24, 32, 3), dtype=np.uint8) for _ in range(5)]
    path = tmp_path / "log.mcap"
    with open(path, "wb") as f:
        writer = McapWriter(f)
        writer.start(profile="", library="test")
        schema = writer.register_schema(
            "foxglove.CompressedImage",
            "jsonschema",
            mcap_io.schema_text("CompressedImage").encode(),
        )
        channel = writer.register_channel("/cam", "json", schema)
        for i, image in enumerate(images):
            msg = mcap_io.compressed_image(1_000 + i, image)
            if i == 1:
                msg["timestamp"]["sec"] = "abc"
            if i == 2:
                jpeg = base64.b64decode(msg["data"])
                msg["data"] = base64.b64encode(jpeg[: len(jpeg) // 2]).decode()
            data = b'{"timestamp": ' if i == 3 else json.dumps(msg).encode()
            writer.add_message(channel, 1_000 + i, data, 1_000 + i)
        writer.finish()
    source = open_source(path)
    frames = list(source)
    assert [f.stamp_ns for f in frames] == [1_000, 1_004]
    text = "\n".join(source.problems)
    assert len(source.problems) == 3
    assert "message 1: bad header stamp" in text
    assert "message 2: JPEG data ends without its end-of-image marker" in text
    assert "message 3: cannot decode" in text


# --------------------------------------------------------------------------- folders and videos


def _folder(tmp_path: Path, sizes: list[tuple[int, int]], stamps: list[int] | None = None):
    rng = np.random.default_rng(1)
    folder = tmp_path / "frames"
    folder.mkdir()
    rows = []
    for i, (w, h) in enumerate(sizes):
        cv2.imwrite(str(folder / f"{i:03d}.png"), rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
        rows.append(FrameStamp(f"{i:03d}.png", (stamps or list(range(len(sizes))))[i] * 1000))
    write_frames_csv(folder / "frames.csv", rows)
    return folder


def test_a_frame_of_another_size_is_skipped_and_counted(tmp_path):
    folder = _folder(tmp_path, [(96, 54), (96, 54), (64, 36), (96, 54)])
    source = open_source(folder)
    frames = list(source)
    assert [f.index for f in frames] == [0, 1, 2]
    assert [f.stamp_ns for f in frames] == [0, 1000, 3000]
    assert source.problems == [
        f"{folder}: 1 frame(s) of another size than the first frame's 96x54 skipped "
        "(first: frame 2, 64x36)"
    ]


def test_frames_csv_with_a_stamp_or_a_name_twice_is_refused(tmp_path):
    folder = _folder(tmp_path, [(16, 16)] * 3)
    csv_path = folder / "frames.csv"
    csv_path.write_text("filename,stamp_ns\n000.png,0\n001.png,5\n002.png,5\n")
    with pytest.raises(InputError) as exc:
        open_source(folder)
    _assert_one_line_naming(exc, csv_path, "line 4: stamp_ns 5 repeats line 3's")
    csv_path.write_text("filename,stamp_ns\n000.png,0\n001.png,5\n000.png,9\n")
    with pytest.raises(InputError) as exc:
        open_source(folder)
    _assert_one_line_naming(exc, csv_path, "line 4: image '000.png' is listed again")


def test_images_frames_csv_leaves_out_are_reported(tmp_path):
    folder = _folder(tmp_path, [(16, 16)] * 3)
    (folder / "frames.csv").write_text("filename,stamp_ns\n000.png,0\n002.png,5\n")
    source = open_source(folder)
    assert len(list(source)) == 2
    assert source.problems == [
        f"{folder}: 1 image(s) not listed in frames.csv are left out (first: 001.png)"
    ]


def test_a_cut_jpeg_in_a_folder_is_skipped(tmp_path):
    folder = _folder(tmp_path, [(32, 24)] * 3)
    ok, buf = cv2.imencode(".jpg", np.full((24, 32, 3), 128, np.uint8))
    for name in ("000", "001", "002"):
        (folder / f"{name}.png").unlink()
        (folder / f"{name}.jpg").write_bytes(buf.tobytes())
    (folder / "001.jpg").write_bytes(buf.tobytes()[:-200])
    (folder / "frames.csv").write_text("filename,stamp_ns\n000.jpg,0\n001.jpg,5\n002.jpg,9\n")
    source = open_source(folder)
    assert [f.stamp_ns for f in source] == [0, 9]
    assert source.problems == [
        f"{folder}: 001.jpg: JPEG ends without its end-of-image marker (cut short); skipped"
    ]


def test_video_is_read_past_a_damaged_region(tmp_path):
    rng = np.random.default_rng(1)
    path = tmp_path / "flight.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (96, 64))
    for i in range(40):
        image = rng.integers(0, 60, (64, 96, 3), dtype=np.uint8)
        cv2.putText(image, str(i), (10, 40), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (255, 255, 255), 2)
        writer.write(image)
    writer.release()
    data = bytearray(path.read_bytes())
    start = int(len(data) * 0.45)
    data[start : start + 3000] = b"\x00" * 3000
    path.write_bytes(bytes(data))
    source = open_source(path)
    frames = list(source)
    assert 30 <= len(frames) < 40  # the decoder resynchronises after a few frames
    stamps = [f.stamp_ns for f in frames]
    assert stamps == sorted(set(stamps))
    assert any("unreadable frame(s) skipped in 1 damaged region(s)" in p for p in source.problems)


def test_a_full_disk_while_writing_mcap_names_the_file(tmp_path, monkeypatch):
    import errno

    from signpose.io import mcap_write

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    path = tmp_path / "result.mcap"
    with mcap_io.McapJsonWriter(path) as writer:
        monkeypatch.setattr(mcap_write.Writer, "add_message", full)
        with pytest.raises(OutputError) as exc:
            writer.write("/p", "PoseInFrame", mcap_io.pose_in_frame(0, "w", np.eye(4)), 0)
    _assert_one_line_naming(exc, path, "No space left on device")
    assert list(tmp_path.iterdir()) == []  # no partial file, no temporary
