"""Issue 14: a flight observed in chunks, each read from a seek, in worker processes.

The chunk reads give the frames one pass in order gives (images hashed), a
worker that dies loses its chunk only, and the run says which frames are missing.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os

import cv2
import numpy as np
import pytest
from conftest import simulate_tiny
from signpose.maps.loader import bundled_map_path, load_map

from signpose import pipeline
from signpose.io import sources
from signpose.io.observations import read_observations
from signpose.io.sources import RangeRead, open_source, read_range
from signpose.sim.flight import SimSettings, simulate

DIED_EXIT_CODE = 3


def _digest(image: np.ndarray) -> str:
    return hashlib.sha1(np.ascontiguousarray(image).tobytes()).hexdigest()


def _frames(frames) -> list[tuple[int, int, str]]:
    return [(f.index, f.stamp_ns, _digest(f.image)) for f in frames]


def _chunked(path, bounds, **kw) -> tuple[list[tuple[int, int, str]], list[str]]:
    """The frames of ``path`` read chunk by chunk, each from a freshly opened source."""
    size = next(iter(open_source(path, **kw))).image_size  # the flight's: its first frame's
    reads = [RangeRead(a, b, size) for a, b in bounds]
    out = []
    for read in reads:
        out += _frames(read_range(open_source(path, **kw), read))
    return out, open_source(path, **kw).range_problems(reads)


@pytest.fixture(scope="module")
def tiny_video(tmp_path_factory):
    return simulate_tiny(tmp_path_factory.mktemp("video"), frames=16)


def test_a_chunk_read_after_a_seek_is_the_sequential_decode(tiny_video):
    """The simulator's mp4v video: every chunk's frames hash like the pass in order's."""
    source = open_source(tiny_video.frames_path)
    assert source.range_length == 16
    in_order = _frames(source)
    chunked, problems = _chunked(tiny_video.frames_path, [(0, 5), (5, 11), (11, None)])
    assert chunked == in_order
    assert problems == source.problems == []
    # Past the end: nothing, and the video is not said to stop early.
    assert _chunked(tiny_video.frames_path, [(0, 16), (16, None)]) == (in_order, [])


def test_chunks_of_an_mcap_log_are_its_frames_in_order(tmp_path):
    """A log is read from its start for every chunk: the messages before it for their stamps."""
    sim = simulate_tiny(tmp_path, frames=12, fmt="mcap")
    source = open_source(sim.frames_path)
    assert source.range_length == 12
    in_order = _frames(source)
    chunked, problems = _chunked(sim.frames_path, [(0, 4), (4, 9), (9, None)])
    assert chunked == in_order
    assert problems == source.problems == []


def test_a_video_that_cannot_seek_is_decoded_up_to_the_chunk(tiny_video, monkeypatch):
    in_order = _frames(open_source(tiny_video.frames_path))
    monkeypatch.setattr(sources, "_seek", lambda cap, position: False)
    assert _chunked(tiny_video.frames_path, [(0, 7), (7, None)]) == (in_order, [])


def test_chunks_of_a_folder_report_what_a_pass_in_order_reports(tmp_path):
    rng = np.random.default_rng(3)
    folder = tmp_path / "frames"
    folder.mkdir()
    sizes = [(48, 32)] * 3 + [(40, 30)] + [(48, 32)] * 4
    for i, (w, h) in enumerate(sizes):
        cv2.imwrite(str(folder / f"{i:03d}.png"), rng.integers(0, 255, (h, w, 3), np.uint8))
    (folder / "005.png").write_bytes(b"not a png")
    source = open_source(folder, fps=10.0)
    in_order = _frames(source)
    chunked, problems = _chunked(folder, [(0, 3), (3, 6), (6, None)], fps=10.0)
    # Chunk positions are image numbers; the flight's indices count the frames read.
    assert [(i, s, d) for i, (_, s, d) in enumerate(chunked)] == in_order
    assert [p for p, _, _ in chunked] == [0, 1, 2, 4, 6, 7]
    assert problems == source.problems
    assert len(problems) == 2 and "005.png" in problems[0] and "40x30" in problems[1]


def dying_detector(settings: pipeline.ObserveSettings, digest: str) -> pipeline.Detector:
    """The pipeline's detector, in a process that exits at once on the frame hashing to ``digest``
    (a library crashing on a corrupt frame)."""
    return _Dying(pipeline.make_detector(settings), digest)


class _Dying:
    def __init__(self, detector, digest: str) -> None:
        self.detector = detector
        self.digest = digest

    def _check(self, gray) -> None:
        if _digest(gray) == self.digest:
            os._exit(DIED_EXIT_CODE)

    def detect(self, image, codes=None, mode="fast"):
        self._check(image)
        return self.detector.detect(image, codes, mode)

    def detect_tracked(self, image, predictions, codes=None, refresh=False):
        self._check(image)
        return self.detector.detect_tracked(image, predictions, codes, refresh)


@pytest.fixture(scope="module")
def real_flight(tmp_path_factory):
    """8 frames at 960x540, big enough for the trained cascade and the decoder."""
    settings = SimSettings(frames=8, width=960, height=540)
    return simulate(
        load_map(bundled_map_path()), tmp_path_factory.mktemp("real"), settings, progress=False
    )


def test_a_worker_that_dies_loses_only_its_chunk(real_flight, tmp_path):
    frames = list(open_source(real_flight.frames_path))
    make = functools.partial(dying_detector, digest=_digest(frames[4].gray()))
    settings = pipeline.RunSettings(
        observe=pipeline.ObserveSettings(workers=2, chunk_frames=3), plots=False, mcap=False
    )
    out = tmp_path / "run"
    result = pipeline.run(
        real_flight.frames_path,
        load_map(bundled_map_path()),
        out,
        camera=real_flight.camera,
        settings=settings,
        progress=False,
        detector_factory=make,
    )
    # Chunk 1 (frames 3-5) is lost; the chunks before and after it are observed.
    assert [f.frame for f in read_observations(out / "observations.jsonl")] == [0, 1, 2, 6, 7]
    assert result.n_frames == 5
    reason = f"died (exit code {DIED_EXIT_CODE})"
    assert result.problems == (
        f"{real_flight.frames_path}: frames 3 to 5 not observed: the process observing them "
        f"{reason}; the other frames were observed",
    )
    report = json.loads((out / "report.json").read_text())["pipeline"]
    assert report["missing_frames"] == [{"start": 3, "stop": 6, "reason": reason}]
    assert report["problems"] == list(result.problems)
    assert result.coverage["pnp"] == pytest.approx(1.0)  # of the frames observed


def test_a_source_read_in_order_only_gives_the_same_chunks(real_flight, tmp_path):
    """A source that cannot be reopened (no spec) is chunked by frame count, inline: same bytes."""
    sign_map = load_map(bundled_map_path())
    settings = pipeline.ObserveSettings(workers=1, chunk_frames=3)
    written = []
    for spec in (True, False):
        source = open_source(real_flight.frames_path)
        if not spec:
            source.spec = None
        out = tmp_path / f"spec_{spec}.jsonl"
        result = pipeline.observe(source, sign_map, real_flight.camera, settings, False, out)
        assert result.full_frames >= 3  # a full-frame search at each chunk's start
        written.append(out.read_bytes())
    assert written[0] == written[1]


def test_a_process_job_writes_its_cpu_where_profile_env_says(tmp_path, monkeypatch):
    """pipeline.PROFILE_ENV: a job's CPU record (bench_pipeline counts the chunk and plot
    processes' CPU from these); nothing without it."""

    def work(n, scale=1.0):
        return scale * sum(i * i for i in range(n))

    monkeypatch.delenv(pipeline.PROFILE_ENV, raising=False)
    assert pipeline._profiled("chunk", 3, work, 10, scale=2.0) == 570.0
    monkeypatch.setenv(pipeline.PROFILE_ENV, str(tmp_path))
    assert pipeline._profiled("chunk", 3, work, 300_000) == work(300_000)
    (record,) = [json.loads(p.read_text()) for p in tmp_path.iterdir()]
    assert record["kind"] == "chunk" and record["job"] == 3 and record["pid"] == os.getpid()
    assert record["cpu_s"] > 0 and record["cpu_before_s"] > 0
    assert record["start"] <= record["end"]
