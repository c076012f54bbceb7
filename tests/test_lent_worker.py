"""Issue 14: once no chunk is left to start, an idle worker detects frames of a chunk still
observed (through the main process), so the last chunk does not leave a core idle.

The observations are the same bytes as inline, and a frame that crashes the lent worker
loses the same frames as without it.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import time

import numpy as np
import pytest
from signpose.maps.loader import bundled_map_path, load_map

from signpose import pipeline
from signpose.io.observations import read_observations
from signpose.io.sources import open_source
from signpose.sim.flight import SimSettings, simulate

DIED_EXIT_CODE = 3
# Chunk 1 (frames 3-5 at chunk_frames=3) is this slow per frame [s]: chunks 0 and 2 are
# done long before it, and their worker is lent to it.
SLOW_FRAME_S = 2.0


def _digest(image: np.ndarray) -> str:
    return hashlib.sha1(np.ascontiguousarray(image).tobytes()).hexdigest()


class _SlowDetector:
    """The pipeline's detector, slow on some frames and exiting the process on one."""

    def __init__(self, detector, slow: frozenset[str], dies: str) -> None:
        self.detector = detector
        self.slow = slow
        self.dies = dies

    def _wait(self, gray) -> None:
        digest = _digest(gray)
        if digest == self.dies:
            os._exit(DIED_EXIT_CODE)
        if digest in self.slow:
            time.sleep(SLOW_FRAME_S)

    def detect(self, image, codes=None, mode="fast"):
        self._wait(image)
        return self.detector.detect(image, codes, mode)

    def detect_tracked(self, image, predictions, codes=None, refresh=False):
        self._wait(image)
        return self.detector.detect_tracked(image, predictions, codes, refresh)


def slow_detector(settings, slow: frozenset[str], dies: str = ""):
    """A module-level factory (a worker process is sent it)."""
    return _SlowDetector(pipeline.make_detector(settings), slow, dies)


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """8 frames at 960x540, big enough for the trained cascade and the decoder."""
    settings = SimSettings(frames=8, width=960, height=540)
    return simulate(
        load_map(bundled_map_path()), tmp_path_factory.mktemp("lent"), settings, progress=False
    )


def _observe(flight, out, workers: int, make=None):
    settings = pipeline.ObserveSettings(workers=workers, chunk_frames=3)
    source = open_source(flight.frames_path)
    sign_map = load_map(bundled_map_path())
    return pipeline.observe(
        source, sign_map, flight.camera, settings, False, out, detector_factory=make
    )


def test_a_lent_worker_gives_the_bytes_of_an_inline_run(flight, tmp_path):
    frames = list(open_source(flight.frames_path))
    slow = frozenset(_digest(f.gray()) for f in frames[3:6])
    make = functools.partial(slow_detector, slow=slow)
    lent = _observe(flight, tmp_path / "w2.jsonl", 2, make)
    inline = _observe(flight, tmp_path / "w1.jsonl", 1)
    assert lent.lent_frames >= 1  # chunk 1's worker had frames detected by the other one
    assert inline.lent_frames == 0
    assert (tmp_path / "w2.jsonl").read_bytes() == (tmp_path / "w1.jsonl").read_bytes()
    assert (lent.tracked_frames, lent.full_frames) == (inline.tracked_frames, inline.full_frames)


def test_a_frame_that_crashes_the_lent_worker_loses_the_frames_it_loses_without_it(
    flight, tmp_path
):
    frames = list(open_source(flight.frames_path))
    slow = frozenset(_digest(f.gray()) for f in frames[3:6])
    make = functools.partial(slow_detector, slow=slow, dies=_digest(frames[5].gray()))
    settings = pipeline.RunSettings(
        observe=pipeline.ObserveSettings(workers=2, chunk_frames=3), plots=False, mcap=False
    )
    out = tmp_path / "run"
    result = pipeline.run(
        flight.frames_path,
        load_map(bundled_map_path()),
        out,
        camera=flight.camera,
        settings=settings,
        progress=False,
        detector_factory=make,
    )
    # Frame 5 kills whichever worker detects it (the lent one, then chunk 1's own): frame 3
    # was finished and sent, frame 4 (finished once frame 5 is detected) is lost with it.
    assert [f.frame for f in read_observations(out / "observations.jsonl")] == [0, 1, 2, 3, 6, 7]
    assert result.n_frames == 6
    reason = f"died (exit code {DIED_EXIT_CODE})"
    report = json.loads((out / "report.json").read_text())["pipeline"]
    assert report["missing_frames"] == [{"start": 4, "stop": 6, "reason": reason}]
