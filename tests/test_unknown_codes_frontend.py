"""A sign whose code the map lacks is counted, not silent (``DetectionResult.unknown``).

The decoder refuses a reading whose code is not in the map
(``code_not_in_map``) and keeps what it read in ``DecodeResult.unknown_code``;
the detector lists each such region with that code. One simulated frame of
the demo pylon, decoded against the map and against the map without one of
its drawn signs.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest
from signpose.frontend import detector as detector_module
from signpose.frontend.decoder import DecodeReason, DecodeResult, decode_region
from signpose.frontend.detector import DetectorSettings, PredictedSign, SignDetector
from signpose.frontend.sign import render_sign_png
from signpose.maps.loader import bundled_map_path, load_map

from signpose.io.boxes import read_boxes
from signpose.sim.flight import SimSettings, simulate


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    """One simulated 1080p frame of the demo pylon, its truth and the map's codes."""
    out = tmp_path_factory.mktemp("sim")
    sign_map = load_map(bundled_map_path())
    simulate(sign_map, out, SimSettings(frames=2, seed=78, format="png", blur=False), False)
    gray = cv2.imread(str(out / "frames" / "000001.png"), cv2.IMREAD_GRAYSCALE)
    return gray, read_boxes(out / "boxes.jsonl")[1], sign_map.codes


def _near(box, centre_px, diameter_px) -> bool:
    x, y, w, h = box
    return math.dist((x + w / 2, y + h / 2), centre_px) < 0.5 * diameter_px


def _missing_one(gray, truth, codes):
    """(the full map's detections, a drawn code they hold, the codes without it)."""
    full = SignDetector().detect(gray, codes)
    assert full.unknown == ()  # every drawn code is in the map
    drawn = {s["code"]: s for s in truth["signs"]}
    gone = next(d.code for d in full.detections if d.code in drawn)
    return full, drawn[gone], tuple(c for c in codes if c != gone)


def _same(a, b) -> bool:
    return [(d.code, d.keypoints_px) for d in a] == [(d.code, d.keypoints_px) for d in b]


def test_the_decoder_keeps_the_code_it_refused():
    frame = np.full((160, 160), 150, np.uint8)
    face = render_sign_png("0110", 80).astype(float)
    yy, xx = np.mgrid[:80, :80]
    disc = np.hypot(xx - 39.5, yy - 39.5) <= 40
    frame[40:120, 40:120] = np.where(disc, np.round(20 + face * 210 / 255), 150)
    box = (40.0, 40.0, 80.0, 80.0)
    read = decode_region(frame, box, ("0110", "1001"))
    assert read.code == "0110" and read.unknown_code is None
    refused = decode_region(frame, box, ("1001",))
    assert refused.code is None and refused.reason == DecodeReason.CODE_NOT_IN_MAP
    assert refused.unknown_code == "0110"
    assert refused.keypoints_px == {} and not refused.ok
    # Any other refusal reads no code.
    blank = np.full((160, 160), 150, np.uint8)
    assert decode_region(blank, box, ("1001",)).unknown_code is None


def test_a_map_without_a_drawn_code_lists_it_as_unknown_and_keeps_the_rest(frame):
    gray, truth, codes = frame
    full, sign, fewer = _missing_one(gray, truth, codes)
    res = SignDetector().detect(gray, fewer)
    assert [c for c, box in res.unknown if _near(box, sign["center_px"], sign["diameter_px"])] == [
        sign["code"]
    ]
    assert all(c not in fewer for c, _ in res.unknown)
    # One entry per region: no two of one code at one place.
    assert len(res.unknown) == len(set(res.unknown))
    kept = [d for d in full.detections if d.code != sign["code"]]
    assert _same(res.detections, kept)


def test_tracking_lists_the_unknown_code_too(frame):
    gray, truth, codes = frame
    full, sign, fewer = _missing_one(gray, truth, codes)
    det = SignDetector()
    others = [
        PredictedSign(s["code"], tuple(s["center_px"]), s["diameter_px"])
        for s in truth["signs"]
        if s["code"] != sign["code"]
    ]
    # A prediction of a code the frame does not show, where the unknown sign is
    # (a sign placed wrong): the tracked search there reads the unknown code.
    drawn = {s["code"] for s in truth["signs"]}
    absent = "1111"
    assert absent not in drawn
    there = PredictedSign(absent, tuple(sign["center_px"]), sign["diameter_px"])
    held = det.detect_tracked(gray, [*others, there], fewer)
    assert not held.fell_back
    assert sign["code"] in {
        c for c, box in held.unknown if _near(box, sign["center_px"], sign["diameter_px"])
    }
    # A prediction where there is nothing, with refresh: the full frame's search lists it.
    lost = PredictedSign(absent, (60.0, 60.0), 40.0)
    back = det.detect_tracked(gray, [*others, lost], fewer, refresh=True)
    assert back.fell_back
    assert [c for c, box in back.unknown if _near(box, sign["center_px"], sign["diameter_px"])] == [
        sign["code"]
    ]
    assert sign["code"] not in {d.code for d in back.detections}


def test_a_region_a_retry_reads_as_an_unknown_code_is_listed_once(monkeypatch):
    """The default crop refused for the crop (no location), a retry's crop read a
    code the map lacks: the region is that unknown code, once."""
    calls = []

    def decoding(gray, box, codes=None, settings=None):
        calls.append(settings)
        if settings is None:
            return DecodeResult(code=None, reason=DecodeReason.NO_LOCATION)
        return DecodeResult(code=None, reason=DecodeReason.CODE_NOT_IN_MAP, unknown_code="0110")

    monkeypatch.setattr(detector_module, "decode_region", decoding)
    frame = np.zeros((200, 200), np.uint8)
    box = (60.0, 60.0, 50.0, 50.0)
    unknown: list = []
    dets, undecoded = SignDetector()._decode(
        frame, np.array([box]), np.array([40]), ("1001",), unknown=unknown
    )
    assert dets == () and undecoded == 1
    assert unknown == [("0110", box)]
    assert len(calls) == 1 + len(DetectorSettings().retry_margins)
    # Without retries the region's refusal is about the crop: nothing listed.
    unknown.clear()
    SignDetector()._decode(
        frame, np.array([box]), np.array([40]), ("1001",), retry=False, unknown=unknown
    )
    assert unknown == []
