"""A sign the map does not have is counted and, read in many frames, a warning.

The decoder refuses a code the map does not have (``code_not_in_map``); the
run lists those readings in report.json and warns when one code is read in
``UNKNOWN_CODE_FRAMES`` frames or more (a sign missing from the map is
otherwise silent: its readings are simply absent).
"""

from __future__ import annotations

import json
from dataclasses import replace

import pytest
from conftest import simulate_tiny, truth_detector
from signpose.maps.loader import bundled_map_path, load_map, map_to_dict, parse_map

from signpose import pipeline
from signpose.io.boxes import read_boxes
from signpose.io.observations import read_observations


@pytest.fixture(scope="module")
def tiny_flight(tmp_path_factory):
    return simulate_tiny(tmp_path_factory.mktemp("flight"))


class _MapLacks:
    """The truth, with every reading of ``code`` refused as the decoder refuses a code
    the map does not have (on the first ``frames`` frames only, when given)."""

    def __init__(self, truth, code: str, frames: int | None = None):
        self.truth, self.code, self.frames, self.seen, self.refused = truth, code, frames, 0, 0

    def _refused(self, result):
        self.seen += 1
        if self.frames is not None and self.seen > self.frames:
            return result
        keep = tuple(d for d in result.detections if d.code != self.code)
        gone = [d for d in result.detections if d.code == self.code]
        self.refused += len(gone)
        unknown = tuple((d.code, tuple(float(c) for c in d.bbox_px)) for d in gone)
        return replace(result, detections=keep, unknown=unknown)

    # The truth of every drawn sign (not only the map's codes): what the decoder reads.
    def detect(self, image, codes=None, mode="fast"):
        return self._refused(self.truth.detect(image, None, mode))

    def detect_tracked(self, image, predictions, codes=None, refresh=False):
        return self._refused(self.truth.detect_tracked(image, predictions, None, refresh))


def _map_without(code: str):
    data = map_to_dict(load_map(bundled_map_path()))
    data["signs"] = [s for s in data["signs"] if s["code"] != code]
    return parse_map(data, "short.yaml")


def _run(tiny_flight, tmp_path, sign_map, detector, tracking=True):
    lines: list[str] = []
    result = pipeline.run(
        tiny_flight.frames_path,
        sign_map,
        tmp_path / "run",
        camera=tiny_flight.camera,
        settings=pipeline.RunSettings(
            observe=pipeline.ObserveSettings(tracking=tracking), plots=False, mcap=False
        ),
        progress=False,
        detector=detector,
        echo=lines.append,
    )
    return result, lines, json.loads((tmp_path / "run" / "report.json").read_text())


def _most_seen_code(tiny_flight) -> str:
    counts: dict[str, int] = {}
    for f in read_boxes(tiny_flight.boxes_path):
        for s in f["signs"]:
            counts[s["code"]] = counts.get(s["code"], 0) + 1
    return max(sorted(counts), key=counts.get)


@pytest.mark.parametrize("tracking", [True, False])
def test_a_sign_missing_from_the_map_is_a_warning(tiny_flight, tmp_path, tracking):
    code = _most_seen_code(tiny_flight)
    detector = _MapLacks(truth_detector(tiny_flight), code)
    result, lines, report = _run(tiny_flight, tmp_path, _map_without(code), detector, tracking)
    n = detector.refused
    assert n >= pipeline.UNKNOWN_CODE_FRAMES  # the flight shows it often enough
    assert result.refused["code_not_in_map"] == n
    warned = [w for w in lines if f"code {code} was read in {n} frames" in w]
    assert len(warned) == 1 and "short.yaml has no sign of that code" in warned[0]
    assert any(f"code {code} was read" in w for w in report["warnings"])
    listed = report["pipeline"]["refused"]["observations"]
    assert {r["code"] for r in listed} == {code}
    assert all(r["reason"] == "code_not_in_map" for r in listed)
    assert sorted(r["frame"] for r in listed) == sorted({r["frame"] for r in listed})
    written = read_observations(tmp_path / "run" / "observations.jsonl")
    assert all(s.code != code for f in written for s in f.signs)


def test_a_few_unknown_readings_are_counted_not_warned(tiny_flight, tmp_path):
    code = _most_seen_code(tiny_flight)
    few = pipeline.UNKNOWN_CODE_FRAMES - 1
    detector = _MapLacks(truth_detector(tiny_flight), code, frames=few)
    result, lines, report = _run(tiny_flight, tmp_path, load_map(bundled_map_path()), detector)
    assert 0 < result.refused["code_not_in_map"] <= few
    assert not any("was read in" in w for w in lines)
    assert not any("was read in" in w for w in report.get("warnings", []))


def test_the_wrong_map_names_the_codes_read(tiny_flight, tmp_path):
    """A map of another site: the refusal says which codes the frames showed."""
    other = parse_map(
        {
            "frame": "elsewhere",
            "signs": [{"code": "1111", "center_m": [0, 0, 10], "diameter_m": 0.8, "sigma_m": 0.01}],
        },
        "other.yaml",
    )
    code = _most_seen_code(tiny_flight)

    class _OnlyUnknown(_MapLacks):
        def _refused(self, result):
            unknown = tuple((d.code, tuple(float(c) for c in d.bbox_px)) for d in result.detections)
            return replace(result, detections=(), unknown=unknown)

    with pytest.raises(pipeline.InputError, match=rf"the frames show [0-9, ]*{code}"):
        _run(tiny_flight, tmp_path, other, _OnlyUnknown(truth_detector(tiny_flight), code))
