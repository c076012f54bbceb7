"""Frame sources: video, image folder, errors."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import simulate_tiny, truth_detector
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from signpose.estimator.camera import pinhole_camera
from signpose.maps.loader import bundled_map_path, load_map

from signpose import pipeline
from signpose.core.errors import InputError
from signpose.io.clock import QUICKTIME_EPOCH_OFFSET_S, mp4_creation_time_ns, parse_start_time
from signpose.io.observations import read_observations
from signpose.io.sources import FolderSource, VideoSource, check_source_camera, open_source


def _frames(rng: np.random.Generator, n: int, w: int = 96, h: int = 64) -> list[np.ndarray]:
    out = []
    for i in range(n):
        img = rng.integers(0, 60, (h, w, 3), dtype=np.uint8)
        cv2.putText(img, str(i), (10, 40), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (255, 255, 255), 2)
        out.append(img)
    return out


def _write_video(path: Path, frames: list[np.ndarray], fourcc: str, fps: float = 10.0) -> None:
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (w, h))
    assert writer.isOpened()
    for f in frames:
        writer.write(f)
    writer.release()


def test_video_stamps_from_container(tmp_path):
    path = tmp_path / "flight.mp4"
    _write_video(path, _frames(np.random.default_rng(0), 12), "mp4v", fps=10.0)
    source = open_source(path)
    assert isinstance(source, VideoSource)
    assert source.length == 12
    frames = list(source)
    assert len(frames) == 12
    assert [f.index for f in frames] == list(range(12))
    np.testing.assert_allclose([f.stamp_ns / 1e6 for f in frames], np.arange(12) * 100.0, atol=1)
    assert frames[0].image_size == (96, 64)
    assert frames[0].gray().shape == (64, 96)
    assert source.problems == []


def test_truncated_video_reads_what_is_there(tmp_path):
    full = tmp_path / "full.avi"
    _write_video(full, _frames(np.random.default_rng(1), 30), "MJPG")
    data = full.read_bytes()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(data[: len(data) // 2])
    source = open_source(cut)
    frames = list(source)
    assert 0 < len(frames) < 30
    assert len(source.problems) == 1
    assert f"stopped at frame {len(frames)} of 30" in source.problems[0]


def test_truncated_mp4_without_index_says_why(tmp_path):
    full = tmp_path / "full.mp4"
    _write_video(full, _frames(np.random.default_rng(2), 10), "mp4v")
    cut = tmp_path / "cut.mp4"
    cut.write_bytes(full.read_bytes()[:-2000])
    with pytest.raises(InputError, match=r"cut.mp4: .*'moov' atom\) is missing"):
        open_source(cut)


def test_corrupt_video_is_input_error(tmp_path):
    path = tmp_path / "noise.mp4"
    path.write_bytes(np.random.default_rng(3).integers(0, 255, 5000, dtype=np.uint8).tobytes())
    with pytest.raises(InputError, match="noise.mp4"):
        list(open_source(path))


def test_folder_with_times_csv(tmp_path):
    rng = np.random.default_rng(4)
    names = ["img_2.png", "img_10.png", "img_1.png"]
    for name, img in zip(names, _frames(rng, 3), strict=True):
        cv2.imwrite(str(tmp_path / name), img)
    (tmp_path / "frames.csv").write_text(
        "filename,stamp_ns\nimg_1.png,100\nimg_2.png,200\nimg_10.png,1000\n"
    )
    source = open_source(tmp_path)
    assert isinstance(source, FolderSource)
    assert [p.name for p, _ in source.items] == ["img_1.png", "img_2.png", "img_10.png"]
    frames = list(source)
    assert [f.stamp_ns for f in frames] == [100, 200, 1000]


def test_folder_with_fps_natural_order(tmp_path):
    rng = np.random.default_rng(5)
    for i, img in enumerate(_frames(rng, 3)):
        cv2.imwrite(str(tmp_path / f"f{[2, 10, 1][i]}.jpg"), img)
    frames = list(open_source(tmp_path, fps=4.0))
    assert [f.stamp_ns for f in frames] == [0, 250_000_000, 500_000_000]
    source = open_source(tmp_path, fps=4.0)
    assert [p.name for p, _ in source.items] == ["f1.jpg", "f2.jpg", "f10.jpg"]


def test_folder_without_times_asks_for_fps(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((4, 4), np.uint8))
    with pytest.raises(InputError, match="frames.csv.*--fps"):
        open_source(tmp_path)


def test_folder_csv_naming_a_missing_image(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((4, 4), np.uint8))
    (tmp_path / "times.csv").write_text("filename,stamp_ns\nb.png,5\n")
    with pytest.raises(InputError, match=r"times.csv: line 2: image 'b.png'"):
        open_source(tmp_path)


def test_folder_skips_an_unreadable_image(tmp_path):
    cv2.imwrite(str(tmp_path / "0.png"), np.zeros((4, 4), np.uint8))
    (tmp_path / "1.png").write_bytes(b"not a png")
    source = open_source(tmp_path, fps=1.0)
    frames = list(source)
    assert len(frames) == 1
    assert "1.png: cannot read image" in source.problems[0]


@pytest.mark.parametrize("kind", ["empty_folder", "empty_file", "missing"])
def test_empty_or_missing_input(tmp_path, kind):
    if kind == "empty_folder":
        path = tmp_path / "frames"
        path.mkdir()
    elif kind == "empty_file":
        path = tmp_path / "flight.mp4"
        path.write_bytes(b"")
    else:
        path = tmp_path / "nothing.mp4"
    with pytest.raises(InputError, match=str(path.name)):
        open_source(path)


def test_camera_size_mismatch():
    camera = pinhole_camera(640, 480)
    check_source_camera("flight.mp4", camera, (640, 480))
    with pytest.raises(InputError, match=r"flight.mp4: images are 96x64 .* 640x480"):
        check_source_camera("flight.mp4", camera, (96, 64))


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    stamps=st.lists(st.integers(-(2**62), 2**62), min_size=1, max_size=8, unique=True),
    junk=st.text(alphabet=st.characters(blacklist_categories=("Cs",)), max_size=20),
)
def test_times_csv_parser(tmp_path_factory, stamps, junk):
    """Valid CSVs come back sorted by time; a corrupted stamp is one InputError naming the line."""
    from signpose.io.sources import _read_times_csv

    folder = tmp_path_factory.mktemp("csv")
    files = {f"{i}.png": folder / f"{i}.png" for i in range(len(stamps))}
    rows = "".join(f"{i}.png,{t}\n" for i, t in enumerate(stamps))
    path = folder / "frames.csv"
    path.write_text("filename,stamp_ns\n" + rows)
    items = _read_times_csv(path, files)
    assert [t for _, t in items] == sorted(stamps)
    bad = "".join(c for c in junk if c not in ',"\r\n\x0b\x0c\x1c\x1d\x1e\x85\u2028\u2029').strip()
    try:
        int(bad)
        return  # still a valid integer
    except ValueError:
        pass
    path.write_text("filename,stamp_ns\n" + rows + f"0.png,{bad}\n", encoding="utf-8")
    if not bad:
        with pytest.raises(InputError, match=r"line \d+"):
            _read_times_csv(path, files)
        return
    with pytest.raises(InputError, match=rf"frames.csv: line {len(stamps) + 2}: "):
        _read_times_csv(path, files)


# --------------------------------------------------------------------------- clocks (issue 13)


def test_parse_start_time():
    assert parse_start_time("1714557600.25") == 1_714_557_600_250_000_000
    assert parse_start_time("2026-05-01T10:30:00Z") == 1_777_631_400_000_000_000
    assert parse_start_time("2026-05-01T12:30:00.5+02:00") == 1_777_631_400_500_000_000
    for bad, why in (
        ("2026-05-01T10:30:00", "time zone"),
        ("yesterday", "ISO 8601"),
        ("-3", "epoch seconds"),
        ("nan", "epoch seconds"),
        ("1e30", "epoch seconds"),
    ):
        with pytest.raises(InputError, match=why):
            parse_start_time(bad)


def _with_creation_time(path: Path, unix_s: int) -> None:
    """Put a creation time into an MP4's movie header (OpenCV writes 0 there)."""
    data = bytearray(path.read_bytes())
    at = data.index(b"mvhd") + 4
    assert data[at] == 0  # version 0: 32-bit times
    data[at + 4 : at + 8] = (unix_s + QUICKTIME_EPOCH_OFFSET_S).to_bytes(4, "big")
    path.write_bytes(bytes(data))


def test_video_frames_carry_the_containers_creation_time(tmp_path):
    path = tmp_path / "flight.mp4"
    _write_video(path, _frames(np.random.default_rng(2), 5), "mp4v", fps=10.0)
    plain = open_source(path)
    assert plain.clock == "zero" and next(iter(plain)).stamp_ns == 0
    _with_creation_time(path, 1_777_631_400)
    assert mp4_creation_time_ns(path) == 1_777_631_400 * 10**9
    source = open_source(path)
    assert source.clock == "creation_time"
    stamps = [f.stamp_ns - 1_777_631_400 * 10**9 for f in source]
    np.testing.assert_allclose(np.array(stamps) / 1e6, np.arange(5) * 100.0, atol=1)
    given = open_source(path, start_ns=5 * 10**9)  # --start-time wins
    assert given.clock == "start_time" and next(iter(given)).stamp_ns == 5 * 10**9


def test_start_time_for_an_fps_folder_and_not_for_inputs_with_times(tmp_path):
    rng = np.random.default_rng(3)
    for i, img in enumerate(_frames(rng, 3)):
        cv2.imwrite(str(tmp_path / f"{i}.png"), img)
    source = open_source(tmp_path, fps=4.0, start_ns=10**18)
    assert [f.stamp_ns for f in source] == [10**18, 10**18 + 250_000_000, 10**18 + 500_000_000]
    (tmp_path / "frames.csv").write_text("filename,stamp_ns\n0.png,0\n1.png,1\n2.png,2\n")
    with pytest.raises(InputError, match="frames.csv gives this folder's times"):
        open_source(tmp_path, start_ns=10**18)
    assert mp4_creation_time_ns(tmp_path / "0.png") is None


def test_run_puts_a_video_on_the_given_clock(tmp_path):
    sim = simulate_tiny(tmp_path / "flight", frames=6)
    start_ns = parse_start_time("2026-05-01T10:30:00Z")
    settings = pipeline.RunSettings(plots=False, mcap=False, start_ns=start_ns)
    pipeline.run(
        sim.frames_path,
        load_map(bundled_map_path()),
        tmp_path / "run",
        camera=sim.camera,
        settings=settings,
        progress=False,
        detector=truth_detector(sim),
    )
    stamps = [f.stamp_ns for f in read_observations(tmp_path / "run" / "observations.jsonl")]
    assert stamps[0] == start_ns and len(stamps) == 6
