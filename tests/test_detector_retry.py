"""Crop retries on regions the decoder refuses (issue 11 item 6); eval_detector's miss causes."""

from __future__ import annotations

import importlib.util
import math
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from signpose.frontend import detector as detector_module
from signpose.frontend.decoder import DecodeReason, DecodeResult, DecoderSettings, decode_region
from signpose.frontend.detector import DetectorSettings, SignDetector
from signpose.frontend.sign import render_sign_png
from signpose.maps.loader import bundled_map_path, load_map

from signpose.io.boxes import read_boxes
from signpose.sim.flight import SimSettings, simulate

DIAMETER_PX = 60  # its cut box (36 px) is above retry_small_px
CUT_BOX_FRAC = 0.6  # a region this fraction of the disc: the default crop cuts its rim
NO_RETRIES = DetectorSettings(retry_margins=(), retry_small_margins=())
# The decoder's own second crop around the disc it fitted reads these centred
# regions already; the retries are measured without it.
NO_RECROP = DecoderSettings(recrop_cut_rim=False)


@pytest.fixture
def without_recrop(monkeypatch):
    """The detector's decoder with ``recrop_cut_rim`` off (the retries' own effect)."""

    def decode(gray, box, codes=None, settings=None):
        base = DecoderSettings() if settings is None else settings
        return decode_region(gray, box, codes, replace(base, recrop_cut_rim=False))

    monkeypatch.setattr(detector_module, "decode_region", decode)


def _sign_frame(
    code: str = "0101", diameter_px: int = DIAMETER_PX
) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """(200, 200) frame with one sign at its middle, and a box cutting its rim."""
    frame = np.full((200, 200), 150, np.uint8)
    face = render_sign_png(code, diameter_px).astype(float)
    yy, xx = np.mgrid[:diameter_px, :diameter_px]
    disc = np.hypot(xx - (diameter_px - 1) / 2, yy - (diameter_px - 1) / 2) <= diameter_px / 2
    x0 = 100 - diameter_px // 2
    patch = frame[x0 : x0 + diameter_px, x0 : x0 + diameter_px]
    frame[x0 : x0 + diameter_px, x0 : x0 + diameter_px] = np.where(
        disc, np.round(20 + face * (230 - 20) / 255), patch
    )
    side = CUT_BOX_FRAC * diameter_px
    return frame, (100 - side / 2, 100 - side / 2, side, side)


def test_the_decoder_reads_a_centred_region_whose_crop_cuts_the_rim_around_its_disc():
    frame, box = _sign_frame()
    assert decode_region(frame, box, settings=NO_RECROP).reason == DecodeReason.CUT_BY_EDGE
    res = decode_region(frame, box)
    assert res.code == "0101"
    assert math.dist(res.keypoints_px["center"], (99.5, 99.5)) < 1.0
    assert SignDetector(settings=NO_RETRIES).decode_box(frame, box, n_windows=1).code == "0101"


def test_a_region_whose_crop_cuts_the_rim_is_read_with_a_wider_crop(without_recrop):
    frame, box = _sign_frame()
    assert decode_region(frame, box, settings=NO_RECROP).reason == DecodeReason.CUT_BY_EDGE
    det = SignDetector()
    res = det.decode_box(frame, box, n_windows=40)
    assert res.code == "0101"
    assert math.dist(res.keypoints_px["center"], (99.5, 99.5)) < 1.0
    # Without retries, or for a region few windows agree on, it stays refused.
    plain = SignDetector(settings=NO_RETRIES)
    assert plain.decode_box(frame, box, n_windows=40).reason == DecodeReason.CUT_BY_EDGE
    weak = DetectorSettings().retry_min_windows - 1
    assert box[2] > DetectorSettings().retry_small_px
    assert det.decode_box(frame, box, n_windows=weak).reason == DecodeReason.CUT_BY_EDGE
    # The region goes through the same path when a frame is decoded.
    dets, undecoded = det._decode(frame, np.array([box]), np.array([40]), None)
    assert [d.code for d in dets] == ["0101"] and undecoded == 0
    assert plain._decode(frame, np.array([box]), np.array([40]), None) == ((), 1)
    # Tracking's searched regions are not retried (its cost is kept).
    assert det._decode(frame, np.array([box]), np.array([40]), None, retry=False) == ((), 1)


def test_a_small_region_is_retried_whatever_its_window_count(without_recrop):
    """The sliding window's 24 px windows fit a sign near that size only a few times."""
    frame, box = _sign_frame(diameter_px=40)
    assert box[2] <= DetectorSettings().retry_small_px
    assert decode_region(frame, box, settings=NO_RECROP).reason == DecodeReason.CUT_BY_EDGE
    assert SignDetector().decode_box(frame, box, n_windows=2).code == "0101"
    off = SignDetector(settings=DetectorSettings(retry_small_px=0.0))
    assert off.decode_box(frame, box, n_windows=2).code is None


@pytest.mark.parametrize("reason", [DecodeReason.OCCLUDED, DecodeReason.CODE_NOT_IN_MAP])
def test_a_refusal_about_the_sign_is_not_tried_again(monkeypatch, reason):
    """Occluded or a code the map lacks: another crop would be a second guess at the verdict."""
    calls = []

    def refusing(gray, box, codes=None, settings=None):
        calls.append(settings)
        return DecodeResult(code=None, reason=reason)

    monkeypatch.setattr(detector_module, "decode_region", refusing)
    frame, box = _sign_frame()
    res = SignDetector().decode_box(frame, box, n_windows=100)
    assert res.reason == reason and len(calls) == 1
    # A refusal about the crop is tried with every retry margin.
    calls.clear()
    monkeypatch.setattr(
        detector_module,
        "decode_region",
        lambda gray, box, codes=None, settings=None: (
            calls.append(settings) or DecodeResult(code=None, reason=DecodeReason.NO_LOCATION)
        ),
    )
    SignDetector().decode_box(frame, box, n_windows=100)
    assert [s.region_margin for s in calls[1:]] == list(DetectorSettings().retry_margins)


@pytest.fixture(scope="module")
def far_frame(tmp_path_factory):
    """A frame of the orbit at 62 m (signs about 21 px, one of them partly hidden) and its truth."""
    out = tmp_path_factory.mktemp("orbit")
    sign_map = load_map(bundled_map_path())
    settings = SimSettings(frames=2, trajectory="orbit", distance_m=62.0, seed=78, format="png")
    simulate(sign_map, out, settings, progress=False)
    gray = cv2.imread(str(out / "frames" / "000001.png"), cv2.IMREAD_GRAYSCALE)
    return gray, read_boxes(out / "boxes.jsonl")[1], sign_map


def test_on_a_far_frame_the_retries_find_a_small_sign_and_nothing_false(far_frame):
    gray, truth, sign_map = far_frame
    before = SignDetector(settings=NO_RETRIES).detect(gray, sign_map.codes)
    after = SignDetector().detect(gray, sign_map.codes)
    assert {d.code for d in before.detections} < {d.code for d in after.detections}
    assert after.n_undecoded < before.n_undecoded
    by_code = {s["code"]: s for s in truth["signs"]}
    for d in after.detections:  # every reading is a sign of the frame, where it is
        s = by_code[d.code]
        assert math.dist(d.center_px, s["center_px"]) < 0.25 * s["diameter_px"]
        assert s["diameter_px"] < 30


def _eval_detector():
    path = Path(__file__).resolve().parents[1] / "scripts" / "eval_detector.py"
    spec = importlib.util.spec_from_file_location("eval_detector", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["eval_detector"] = mod
    spec.loader.exec_module(mod)
    return mod


def test_eval_detector_names_the_cause_of_each_miss(without_recrop):
    ev = _eval_detector()
    frame, cut_box = _sign_frame()
    side = float(DIAMETER_PX)
    true_box = (100 - side / 2, 100 - side / 2, side, side)
    sign = {"code": "0101", "center_px": [99.5, 99.5], "diameter_px": side, "bbox_px": true_box}
    plain = SignDetector(settings=NO_RETRIES)
    far = np.array([[0.0, 0.0, 30.0, 30.0]])
    counts = np.array([40])
    # No region near it; in fast mode also no candidate region holding its centre.
    assert ev.miss_cause(frame, sign, plain, far, counts, None, None)[0] == "no_region"
    assert ev.miss_cause(frame, sign, plain, far, counts, None, [])[0] == "no_candidate"
    # A region whose crop is refused while the true box reads: the crop's fault, and
    # the crop is too tight.
    cause, geometry, reason = ev.miss_cause(
        frame, sign, plain, np.array([cut_box]), counts, None, None
    )
    assert (cause, geometry, reason) == ("refused_crop", "too_tight", "cut_by_edge")
    # The sign hidden (its face grey): the true box is refused too.
    blank = frame.copy()
    blank[85:115, 85:115] = 60
    assert ev.miss_cause(blank, sign, plain, np.array([true_box]), counts, None, None)[0] == (
        "refused_sign"
    )


def test_eval_detector_condition_flights_put_the_references_first_and_the_hard_ones_last():
    ev = _eval_detector()
    flights = ev.condition_flights(photo_flights=2, hard_flights=1, frames=3, seed=10)
    assert [(name, label) for name, label, _ in flights] == [
        ("photo0", ""),
        ("photo1", ""),
        ("photo2", ""),
        ("photo3", ""),
        ("hard0", "hard"),
    ]
    photo = [s.photo for _, _, s in flights]
    assert photo == [False, False, True, True, True]  # hard() has photographs too
    assert [s.seed for _, _, s in flights] == [110, 111, 112, 113, 210]
    assert flights[-1][2].members > 0 and all(s.frames == 3 for _, _, s in flights)
    assert ev.condition_flights(0, 0, 3, 10) == []


def test_a_frame_retries_at_most_retry_max_regions_regions_the_strongest_first(monkeypatch):
    """A frame full of sign-like texture does not pay two more decodes per region."""
    calls = []

    def refusing(gray, box, codes=None, settings=None):
        calls.append((box, settings))
        return DecodeResult(code=None, reason=DecodeReason.NO_LOCATION)

    monkeypatch.setattr(detector_module, "decode_region", refusing)
    frame = np.zeros((100, 400), np.uint8)
    regions = np.array([[10.0 * i, 10.0, 20.0, 20.0] for i in range(8)])  # small: retryable
    counts = np.array([3, 9, 1, 7, 2, 8, 5, 4])
    det = SignDetector(settings=DetectorSettings(retry_max_regions=3))
    assert det._decode(frame, regions, counts, None) == ((), 8)
    retried = [box[0] for box, settings in calls if settings is not None]
    s = DetectorSettings()
    n_margins = len(s.retry_margins) + len(s.retry_small_margins)  # small regions: both
    # The three with most windows (9, 8, 7: regions 1, 5, 3), each with every margin.
    assert retried == [10.0] * n_margins + [50.0] * n_margins + [30.0] * n_margins


def test_the_retries_time_is_reported_as_a_part_of_the_decoding(without_recrop):
    """DetectionResult.timing["retry"]: the crop retries' ms, within "decode"."""
    frame, box = _sign_frame()
    det = SignDetector()
    timing: dict[str, float] = {}
    dets, _ = det._decode(frame, np.array([box]), np.array([40]), None, timing=timing)
    assert [d.code for d in dets] == ["0101"]  # read by a retry (the default crop cuts the rim)
    assert timing["retry"] > 0.0
    res = det._finish(frame, np.array([box] * 40), None, "fast", {}, 0.0)  # 40 windows
    assert [d.code for d in res.detections] == ["0101"]
    assert 0.0 < res.timing["retry"] <= res.timing["decode"]
    # A region the default crop reads is not retried: no retry time.
    whole = (
        100 - DIAMETER_PX * 0.75,
        100 - DIAMETER_PX * 0.75,
        1.5 * DIAMETER_PX,
        1.5 * DIAMETER_PX,
    )
    timing = {}
    dets, _ = det._decode(frame, np.array([whole]), np.array([40]), None, timing=timing)
    assert [d.code for d in dets] == ["0101"] and timing.get("retry", 0.0) == 0.0
