"""Occlusion-aware decoding (issue 11, item 1): a covered slot is erased, never guessed."""

import json

import cv2
import numpy as np
import pytest
from signpose.frontend import decoder, occlusion
from signpose.frontend.decoder import REASONS, DecodeReason, decode_roi
from signpose.frontend.homography import apply_homography
from signpose.frontend.observations import FrameObservations, SignObservation
from signpose.frontend.sign import PAPER_CODES, slot_angle_rad

from signpose.io.observations import frame_from_dict, frame_to_json
from signpose.sim.crops import render_crop

BAR_GRAY = 70  # a steel member: darker than the sky, lighter than the print's black


def _crop_with_bar_over_slot(
    code: str,
    slot: int,
    rng,
    sign_px: float = 90.0,
    radial_offset: float = 0.0,
    width: float = 0.2,
):
    """A clean crop with a wide dark bar laid tangentially over coded slot ``slot``.

    The bar is ``width`` diameters wide (0.2: the slot is 0.16 radially), its
    centre line ``radial_offset`` diameters outward of the slot's centre, and
    runs past the disc's rim on both sides, as a pylon member in front of the
    sign would.
    """
    crop = render_crop(code, rng, sign_px=sign_px, rotation_deg=25.0, background="plain")
    theta = slot_angle_rad(slot)
    radial = np.array([np.cos(theta), np.sin(theta)])
    tangential = np.array([np.sin(theta), -np.cos(theta)])
    centre = (0.3 + radial_offset) * radial  # diameter units (the crop's sign is 1 m across)
    ends = apply_homography(crop.crop_H_sign, np.stack([centre - tangential, centre + tangential]))
    width_px = width * sign_px
    image = crop.image.copy()
    p0, p1 = (tuple(int(round(v)) for v in p) for p in ends)
    cv2.line(image, p0, p1, BAR_GRAY, int(round(width_px)), cv2.LINE_AA)
    return crop, image


def test_a_member_beside_a_black_slot_does_not_erase_it(monkeypatch):
    """A member 0.08 diameters wide whose centre line runs 0.13 outward of black
    slot 2's centre (the slot ends 0.08 out) covers none of the slot: slot 2
    stays 0 (an erased slot 2 would leave 1010 and 1000 of the map). Erasing
    every slot a band merely reaches refused it."""
    crop, image = _crop_with_bar_over_slot(
        "1010", 2, np.random.default_rng(4), radial_offset=0.13, width=0.08
    )
    res = decode_roi(image, PAPER_CODES)
    assert res.code == "1010" and res.erased_slots == ()
    monkeypatch.setattr(decoder, "_ERASE_REACH", 0.08)  # the slot's half side
    assert decode_roi(image, PAPER_CODES).code is None


def test_bar_over_a_white_slot_is_refused_when_another_map_code_fits():
    """1011 with slot 1 hidden reads x011: with 0011 in the map it must not become 0011."""
    crop, image = _crop_with_bar_over_slot("1011", 1, np.random.default_rng(3))
    assert decode_roi(crop.image, ["1011", "0011"]).code == "1011"  # unhidden: read whole
    res = decode_roi(image, ["1011", "0011", "0101"])
    assert res.code is None
    assert res.reason == DecodeReason.OCCLUDED


def test_bar_over_a_white_slot_is_accepted_with_erased_slots_when_the_map_makes_it_unique():
    crop, image = _crop_with_bar_over_slot("1011", 1, np.random.default_rng(3))
    res = decode_roi(image, ["1011", "0101", "1110"])
    assert res.code == "1011", res.reason
    assert 1 in res.erased_slots
    # The covered part's keypoint is dropped; the others stay accurate.
    assert "slot1" not in res.keypoints_px
    for name in ("center", "direction", "slot3"):
        assert np.hypot(*np.subtract(res.keypoints_px[name], crop.keypoints_px[name])) < 0.5
    assert set(res.keypoint_sigma_px) == set(res.keypoints_px)


def test_without_a_map_any_erased_slot_is_refused():
    _, image = _crop_with_bar_over_slot("1011", 1, np.random.default_rng(4))
    res = decode_roi(image)  # all 16 codes allowed: x011 fits two of them
    assert res.code is None and res.reason == DecodeReason.OCCLUDED


def test_white_that_the_reading_does_not_explain_is_found():
    """The 1110-read-as-1000 failure: two white slots the homography missed."""
    crop = render_crop("1110", np.random.default_rng(5), sign_px=60, rotation_deg=40)
    as_1110 = (0, 1, 2, 3, 4)  # centre, direction, slots 1-3
    as_1000 = (0, 1, 2)
    # The crop's sign is 1 m across, so its homography is in diameter units.
    h = crop.crop_H_sign
    black, white = 28.0, 232.0
    assert not occlusion.unexplained_white(crop.image, h, as_1110, black, white, 0.035)
    assert occlusion.unexplained_white(crop.image, h, as_1000, black, white, 0.035)


def test_reason_tokens_are_the_file_tokens():
    assert json.dumps(DecodeReason.CODE_NOT_IN_MAP) == '"code_not_in_map"'
    assert "occluded" in REASONS and "inconsistent" in REASONS
    assert DecodeReason("no_sign") is DecodeReason.NO_SIGN


@pytest.mark.parametrize("erased", [(), (2,), (1, 4)])
def test_observation_fields_round_trip(erased):
    sign = SignObservation(
        code="1011",
        keypoints_px={"center": (10.0, 20.0), "direction": (11.0, 15.0)},
        sigma_px=0.1,
        erased_slots=erased,
        keypoint_sigma_px={"center": (0.05, 0.07)} if erased else {},
    )
    obs = FrameObservations(0, 0, (64, 48), (sign,))
    line = frame_to_json(obs)
    assert ("erased_slots" in line) == bool(erased)  # old files stay as they were
    back = frame_from_dict(json.loads(line)).signs[0]
    assert back.erased_slots == erased
    assert back.keypoint_sigma_px == sign.keypoint_sigma_px


def test_bad_erased_slots_are_rejected():
    d = {
        "frame": 0,
        "stamp_ns": 0,
        "image_size": [8, 8],
        "signs": [{"code": "0001", "keypoints_px": {"center": [1, 2]}, "erased_slots": [5]}],
    }
    with pytest.raises(ValueError, match="erased_slots"):
        frame_from_dict(d)


def test_sigma_grows_when_a_line_crosses_the_face():
    """The calibrated sigma sees a conductor across the sign (sim truth: errors grow)."""
    rng = np.random.default_rng(12)
    clean = decode_roi(render_crop("1010", rng, sign_px=80, rotation_deg=30).image)
    crossed = [
        decode_roi(render_crop("1010", rng, sign_px=80, rotation_deg=30, power_line=True).image)
        for _ in range(6)
    ]
    crossed = [r for r in crossed if r.code == "1010"]
    assert clean.code == "1010" and crossed
    assert set(clean.keypoint_sigma_px) == set(clean.keypoints_px)
    su, sv = clean.keypoint_sigma_px["center"]
    # a clean 80 px sign: a few hundredths of a pixel, about the same on both axes
    # (the model is per axis: each part's own residual to the fit is anisotropic)
    assert 0.0 < su < 0.1 and sv == pytest.approx(su, rel=0.05)
    assert max(r.keypoint_sigma_px["center"][0] for r in crossed) > 2 * su


def test_sampling_takes_any_number_of_points():
    """cv2.remap refuses maps of 32767 columns or more: long point lists still sample."""
    rng = np.random.default_rng(3)
    gray = rng.integers(0, 256, (40, 60), dtype=np.uint8)
    uv = np.concatenate([rng.uniform(0, 59, (40000, 1)), rng.uniform(0, 39, (40000, 1))], 1)
    uv[:3] = [[0, 0], [59, 39], [10, 20]]
    vals = occlusion._sample(gray, uv)
    assert vals.shape == (40000,)
    assert vals[:3].tolist() == [gray[0, 0], gray[39, 59], gray[20, 10]]
    assert occlusion._sample(gray, np.zeros((0, 2))).shape == (0,)


def test_rim_bands_on_a_ring_of_many_dark_runs_and_a_huge_crop():
    """A ring of alternating gray levels (many rim runs at every threshold,
    hundreds of chords) and a sign 1500 px across decode without an exception."""
    h = np.array([[100.0, 0, 100], [0, -100.0, 100], [0, 0, 1]])
    yy, xx = np.mgrid[0:200, 0:200]
    sector = (np.degrees(np.arctan2(100 - yy, xx - 100)) // (360 / 64)).astype(int) % 3
    gray = np.choose(sector, [20, 60, 230]).astype(np.uint8)
    gray[np.hypot(xx - 100, yy - 100) < 50] = 20
    bands = occlusion.dark_bands(gray, h, 20.0, 230.0, True, np.zeros((0, 2)))
    assert isinstance(bands, list)
    big = render_crop("0110", np.random.default_rng(4), sign_px=1500.0, background="plain")
    assert decode_roi(big.image).code in (None, "0110")
