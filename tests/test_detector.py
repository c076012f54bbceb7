"""Detection (paper §2.2): the merge, the bundled model on a rendered frame, tracking, CLI."""

from __future__ import annotations

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest
from signpose.frontend import detector as detector_module
from signpose.frontend.decoder import DecodeReason, DecodeResult, DecoderSettings, decode_region
from signpose.frontend.detector import (
    DetectionResult,
    DetectorMode,
    DetectorSettings,
    PredictedSign,
    SignDetector,
    _blobs,
    _observation,
    _opened_blobs,
    group_merge,
    one_per_sign,
    paper_merge,
    to_frame_observations,
)
from signpose.frontend.observations import SignObservation
from signpose.frontend.sign import render_sign_png
from signpose.maps.loader import bundled_map_path, load_map

from signpose.io.boxes import read_boxes
from signpose.sim.flight import SimSettings, simulate


def test_paper_merge_same_size_needs_two_windows_within_half_a_window():
    rects = np.array(
        [
            [100, 100, 40, 40],
            [104, 98, 40, 40],
            [110, 102, 40, 40],  # within R = 20 px of its neighbours
            [400, 300, 40, 40],  # alone: N = 1 < T = 2, dropped
        ]
    )
    merged, counts = paper_merge(rects, radius_frac=0.5, min_count=2)
    assert counts.tolist() == [3]
    np.testing.assert_allclose(merged[0], [(100 + 104 + 110) / 3, 100, 40, 40])


def test_paper_merge_keeps_distant_signs_apart_and_joins_sizes():
    rects = np.array(
        [
            [100, 100, 40, 40],
            [102, 100, 40, 40],
            [98, 96, 44, 44],  # another size on the same sign
            [99, 99, 44, 44],
            [300, 100, 40, 40],  # a second sign
            [303, 101, 40, 40],
        ]
    )
    merged, counts = paper_merge(rects)
    assert sorted(counts.tolist()) == [2, 4]
    first = merged[np.argmax(counts)]
    assert 40 < first[2] < 44  # average size of the two groups
    assert abs(first[0] - 99.75) < 1e-9
    # Windows too far apart for R (more than half a window) stay separate groups.
    merged, counts = paper_merge(np.array([[0, 0, 40, 40], [25, 0, 40, 40]]), min_count=1)
    assert len(merged) == 2


def test_group_merge_wraps_opencv():
    rects = np.array([[100, 100, 40, 40], [102, 100, 40, 40], [300, 300, 30, 30]])
    merged, counts = group_merge(rects, min_count=2)
    assert len(merged) == 1 and counts[0] == 2


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    """One simulated 1080p frame of the demo pylon and its truth."""
    out = tmp_path_factory.mktemp("sim")
    simulate(
        load_map(bundled_map_path()),
        out,
        SimSettings(frames=2, seed=78, format="png", blur=False),
        False,
    )
    gray = cv2.imread(str(out / "frames" / "000001.png"), cv2.IMREAD_GRAYSCALE)
    return gray, read_boxes(out / "boxes.jsonl")[1], out / "frames" / "000001.png"


def _n_true(result: DetectionResult, truth: dict) -> int:
    by_code = {s["code"]: s for s in truth["signs"]}
    n = 0
    for d in result.detections:
        s = by_code.get(d.code)
        if s and np.hypot(*np.subtract(d.center_px, s["center_px"])) < 0.5 * s["diameter_px"]:
            n += 1
    return n


def _n_covered(regions: np.ndarray, truth: dict) -> int:
    """Truth signs with a region centred within a quarter diameter of theirs."""
    c = regions[:, :2] + regions[:, 2:] / 2
    n = 0
    for s in truth["signs"]:
        if len(c) and np.min(np.hypot(*(c - s["center_px"]).T)) < 0.25 * s["diameter_px"]:
            n += 1
    return n


@pytest.mark.parametrize("mode", ["fast", "paper"])
def test_bundled_model_finds_every_sign_region_of_a_rendered_frame(frame, mode):
    gray, truth, _ = frame
    det = SignDetector(settings=DetectorSettings(decode=False))
    result = det.detect(gray, mode=mode)
    assert len(truth["signs"]) >= 5
    assert _n_covered(result.regions, truth) >= 0.9 * len(truth["signs"])
    assert result.n_regions <= 4 * len(truth["signs"])


def _decodable(gray: np.ndarray, truth: dict) -> int:
    from signpose.frontend.decoder import decode_region

    return sum(decode_region(gray, s["bbox_px"]).code == s["code"] for s in truth["signs"])


@pytest.mark.parametrize("mode", ["fast", "paper"])
def test_bundled_model_detects_and_decodes_the_signs_of_a_rendered_frame(frame, mode):
    gray, truth, _ = frame
    result = SignDetector().detect(gray, load_map(bundled_map_path()).codes, mode=mode)
    # The decoder's own reading of the true boxes is the ceiling.
    ceiling = _decodable(gray, truth)
    assert ceiling >= 3
    assert _n_true(result, truth) >= 0.8 * ceiling
    assert len(result.detections) == _n_true(result, truth)  # nothing false
    assert result.n_regions == len(result.detections) + result.n_undecoded or (
        result.n_regions > len(result.detections)
    )
    # Every region is a detection, a weaker duplicate of one, or undecoded.
    assert len(result.detections) + result.n_undecoded <= result.n_regions


def test_tracking_finds_predicted_signs_and_falls_back_when_lost(frame):
    gray, truth, _ = frame
    det = SignDetector()
    preds = [(s["code"], tuple(s["center_px"]), s["diameter_px"]) for s in truth["signs"]]
    res = det.detect_tracked(gray, preds)
    assert res.mode == "track"
    ceiling = _decodable(gray, truth)
    assert _n_true(res, truth) >= 0.8 * ceiling
    # A prediction where there is no sign: lost, so the full frame is searched.
    lost = det.detect_tracked(gray, [("1111", (60.0, 60.0), 40.0)])
    assert lost.fell_back
    assert _n_true(lost, truth) >= 0.8 * ceiling
    # The time spent verifying before the fallback is still reported (inside decode).
    assert lost.timing["verify"] > 0.0
    assert lost.timing["decode"] >= lost.timing["verify"]


def test_tracking_with_refresh_needs_every_predicted_sign(frame):
    gray, truth, _ = frame
    det = SignDetector()
    preds = [
        PredictedSign(s["code"], tuple(s["center_px"]), s["diameter_px"]) for s in truth["signs"]
    ]
    # One real sign and one where there is none: half is found, enough without refresh.
    found = next(
        p for p in preds if p.code in {d.code for d in det.detect_tracked(gray, preds).detections}
    )
    half = [found, PredictedSign("1111" if found.code != "1111" else "0000", (60.0, 60.0), 40.0)]
    assert not det.detect_tracked(gray, half).fell_back
    assert det.detect_tracked(gray, half, refresh=True).fell_back
    # Stateless: the same call gives the same answer again.
    assert not det.detect_tracked(gray, half).fell_back


def _obs(code: str, u: float, v: float, size: float, score: float) -> SignObservation:
    return SignObservation(
        code, {"center": (u, v)}, (u - size / 2, v - size / 2, size, size), 0.3, score
    )


def test_one_per_sign_merges_regions_of_one_sign_and_keeps_a_code_seen_twice():
    readings = [
        _obs("0101", 100.0, 100.0, 40.0, 0.5),
        _obs("0101", 104.0, 98.0, 44.0, 0.9),  # the same sign, a better reading
        _obs("0101", 400.0, 100.0, 40.0, 0.7),  # the same code elsewhere: kept for the pipeline
        _obs("0011", 250.0, 300.0, 40.0, 0.6),
    ]
    kept = one_per_sign(readings)
    assert [(o.code, o.center_px) for o in kept] == [
        ("0011", (250.0, 300.0)),
        ("0101", (104.0, 98.0)),
        ("0101", (400.0, 100.0)),
    ]


def test_to_frame_observations_keeps_codes_and_keypoints():
    det = _obs("0101", 10.0, 20.0, 30.0, 0.9)
    raw = SignObservation("", {"center": (5.0, 5.0)}, (0, 0, 10, 10), float("inf"), 0.5)
    result = DetectionResult((det, raw), 2, 0, mode=DetectorMode.FAST)
    obs = to_frame_observations(result, 7, 123, (1920, 1080))
    assert obs.frame == 7 and obs.stamp_ns == 123 and obs.image_size == (1920, 1080)
    assert obs.signs == (det,)  # the region without a code is left out


def test_cli_prints_one_json_line_per_image(frame, tmp_path, capsys):
    from signpose.cli import main

    _, truth, png = frame
    missing = tmp_path / "missing.png"
    assert main(["detect", str(png), str(missing)]) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert [x["image"] for x in lines] == [str(png), str(missing)]
    assert "error" in lines[1]
    codes = {s["code"] for s in lines[0]["signs"]}
    assert len(codes & {s["code"] for s in truth["signs"]}) >= 3
    sign = lines[0]["signs"][0]
    assert set(sign) == {"code", "center_px", "bbox_px", "keypoints_px", "score"}
    assert main(["detect", str(missing)]) == 2


def test_a_sign_in_front_of_a_bright_part_is_a_candidate_despite_darker_regions_elsewhere():
    """Fast mode's dark threshold is also local: a dark mass elsewhere does not hide a sign."""
    frame = np.full((480, 640), 150, np.uint8)
    frame[:, :120] = 0  # a black region (a photograph's shadow), the frame's darkest
    face = render_sign_png("0101", 60).astype(float)
    frame[300:360, 400:460] = np.round(40 + face * (200 - 40) / 255)  # its black is 40, not 0
    center = (430, 330)

    def candidate_at_sign(settings: DetectorSettings) -> bool:
        rois = SignDetector(settings=settings).candidate_rois(frame)
        return any(
            x <= center[0] < x + w and y <= center[1] < y + h and size < 200
            for x, y, w, h, size in rois
        )

    assert candidate_at_sign(DetectorSettings())
    assert not candidate_at_sign(DetectorSettings(fast_local_tiles=(0, 0)))


def test_a_sign_in_front_of_a_black_sky_is_a_candidate():
    """Darker than the paint all round (a night sky), the disc is found as a grey blob."""
    frame = np.full((480, 640), 4, np.uint8)
    face = render_sign_png("0110", 60).astype(float)
    disc = np.round(35 + face * (200 - 35) / 255)
    yy, xx = np.mgrid[:60, :60]
    outside = np.hypot(xx - 29.5, yy - 29.5) > 30
    frame[300:360, 400:460] = np.where(outside, frame[300:360, 400:460], disc)
    frame[352:358, 300:560] = 110  # a lattice bar in front of the disc's lower rim
    frame[100:106, 50:600] = 110
    center = (430, 330)

    def candidate_at_sign(settings: DetectorSettings) -> bool:
        rois = SignDetector(settings=settings).candidate_rois(frame)
        return any(
            x <= center[0] < x + w and y <= center[1] < y + h and 30 <= size <= 120
            for x, y, w, h, size in rois
        )

    assert candidate_at_sign(DetectorSettings())
    assert not candidate_at_sign(DetectorSettings(fast_grey_discs=False))


def test_observations_carry_the_decoders_erased_slots_and_keypoint_sigmas():
    res = DecodeResult(
        code="1011",
        reason=DecodeReason.OK,
        keypoints_px={"center": (10.0, 20.0), "slot3": (12.0, 22.0)},
        sigma_px=0.08,
        quality=0.9,
        erased_slots=(1,),
        keypoint_sigma_px={"center": (0.05, 0.06), "slot3": (0.1, 0.1), "slot1": (0.2, 0.2)},
    )
    obs = _observation(res, (0.0, 0.0, 30.0, 30.0), 4)
    assert obs.erased_slots == (1,)
    # A sigma of a keypoint the reading dropped is not reported.
    assert obs.keypoint_sigma_px == {"center": (0.05, 0.06), "slot3": (0.1, 0.1)}
    assert obs.sigma_px == pytest.approx(0.08)


def test_on_a_photograph_with_dark_regions_a_wider_window_range_finds_a_hidden_sign(
    tmp_path, monkeypatch
):
    """A dark background joined to a sign's blob misstates its size (fast_scale_dark).

    Measured without the decoder's second crop around a disc the region's crop
    cuts (``recrop_cut_rim``), which reads the narrow range's region too.
    """

    def decode(gray, box, codes=None, settings=None):
        base = DecoderSettings() if settings is None else settings
        return decode_region(gray, box, codes, replace(base, recrop_cut_rim=False))

    monkeypatch.setattr(detector_module, "decode_region", decode)
    sign_map = load_map(bundled_map_path())
    settings = SimSettings(
        frames=3,
        trajectory="climb-hover-depart",
        distance_m=28.0,
        seed=4346,  # eval_detector's photo flight 2 (coffee): its frame 0
        format="png",
        photo=True,
    )
    simulate(sign_map, tmp_path, settings, progress=False)
    gray = cv2.imread(str(tmp_path / "frames" / "000000.png"), cv2.IMREAD_GRAYSCALE)
    truth = read_boxes(tmp_path / "boxes.jsonl")[0]
    narrow = DetectorSettings(fast_scale_dark=DetectorSettings().fast_scale)
    before = SignDetector(settings=narrow).detect(gray, sign_map.codes).detections
    after = SignDetector().detect(gray, sign_map.codes).detections
    assert {d.code for d in before} < {d.code for d in after}
    by_code = {s["code"]: s for s in truth["signs"]}
    for d in after:  # every reading is a sign of the frame, where it is
        s = by_code[d.code]
        assert np.hypot(*np.subtract(d.center_px, s["center_px"])) < 0.25 * s["diameter_px"]


def test_the_opened_blobs_are_those_of_the_whole_mask():
    """Fast mode opens and labels only the box of the dark pixels: the same blobs,
    in the same order, as the opening and labelling of the whole mask."""
    rng = np.random.default_rng(31)
    compared = 0
    for trial in range(40):
        mask = np.zeros((120, 200), np.uint8)
        for _ in range(int(rng.integers(0, 8))):
            x, y = int(rng.integers(-10, 200)), int(rng.integers(-10, 120))
            w, h = int(rng.integers(1, 30)), int(rng.integers(1, 30))
            mask[max(y, 0) : y + h, max(x, 0) : x + w] = 1
        mask[rng.random(mask.shape) < 0.01 * (trial % 3)] = 1  # speckle, some at the edges
        if trial % 4 == 3:  # irregular blobs with holes and branches
            blobs = cv2.GaussianBlur(rng.random(mask.shape).astype(np.float32), (0, 0), 3.0)
            mask[blobs > np.quantile(blobs, 0.8)] = 1
        for k in (5, 11):
            whole = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((k, k), np.uint8))
            _, _, stats, _ = cv2.connectedComponentsWithStats(whole, connectivity=8)
            assert _opened_blobs(mask, k) == stats[1:].tolist(), (trial, k)
            compared += len(stats) - 1
        # The labelling itself (the grey discs' lit pixels are labelled whole).
        _, _, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        assert _blobs(mask) == stats[1:].tolist(), trial
    assert compared > 50
