"""A member whose edge cuts a corner off a white part hides the slot beyond it.

``occlusion.cut_corners`` on a face drawn here (a homography, anti-aliased
parts, blur, JPEG; a bar as dark as the background laid over one white slot
and across a corner of the next), and on one crop of
scripts/independent_scene.py's "one slot covered" condition (seed 7 of
scripts/eval_decoder.py --independent-only) that the decoder read as another
code of the paper's map, rendered from its scene settings and the renderer's
random state at that crop. And the other side: unoccluded faces with
rounded, blurred corners are not cut.
"""

import importlib.util
import math
import sys
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from signpose.frontend import occlusion
from signpose.frontend.decoder import DecodeReason, decode_roi
from signpose.frontend.sign import PAPER_CODES, fill_polygon_aa, sign_shape

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "independent_scene.py"
# The PCG64 increment of np.random.default_rng(7).
_INC_SEED_7 = 261136684632268670825940853076396136793

_CENTRES = occlusion.PART_QUADS.mean(axis=1)
# Gray levels of the drawn face: print black, white, and a background and
# bar as dark as the print (no rim run shows either crossing).
_BLACK, _WHITE, _DARK = 40.0, 215.0, 38.0


@pytest.fixture(scope="module")
def scene():
    spec = importlib.util.spec_from_file_location("independent_scene_corner", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def _image_H_sign(sign_px: float, rotation_deg: float, size: int) -> np.ndarray:
    """Sign plane [diameters, y up] -> pixels, a rotated disc ``sign_px`` across."""
    c, s = math.cos(math.radians(rotation_deg)), math.sin(math.radians(rotation_deg))
    half = 0.5 * (size - 1)
    return np.array(
        [[sign_px * c, sign_px * s, half], [sign_px * s, -sign_px * c, half], [0, 0, 1]]
    )


def _bar(centre: np.ndarray, angle_deg: float, half_width: float) -> np.ndarray:
    """(4, 2) a straight bar through ``centre`` across the whole face [diameters]."""
    d = np.array([math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))])
    n = np.array([-d[1], d[0]])
    return np.array(
        [
            centre + t * d + o * n
            for t, o in ((-2, -half_width), (2, -half_width), (2, half_width), (-2, half_width))
        ]
    )


def _face(code, sign_px, rotation_deg, rng, bar=None, psf_px=0.6, jpeg=70) -> tuple:
    """A face on a dark background, blurred, noisy and JPEG-compressed, with
    an optional bar ((4, 2) [diameters]) in front; returns (gray, image_H_sign)."""
    size = int(math.ceil(1.6 * sign_px))
    h = _image_H_sign(sign_px, rotation_deg, size)
    img = np.full((size, size), _DARK)

    def fill(poly, value):
        uv = cv2.perspectiveTransform(np.asarray(poly, float).reshape(-1, 1, 2), h).reshape(-1, 2)
        fill_polygon_aa(img, uv, value)

    shape = sign_shape(code, 1.0)
    fill(shape.disc, _BLACK)
    for corners in shape.white_parts.values():
        fill(corners, _WHITE)
    if bar is not None:
        fill(bar, _DARK)
    img = cv2.GaussianBlur(img, (0, 0), psf_px) + rng.normal(0.0, 2.0, img.shape)
    gray = np.clip(np.round(img), 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, jpeg])
    assert ok
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE), h


def _cut(gray, h, zeros: list[int]) -> list[occlusion.Band]:
    """``cut_corners`` for a reading with the coded slots ``zeros`` read black."""
    parts = [0, 1] + [1 + k for k in range(1, 5) if k not in zeros]
    targets = _CENTRES[[1 + k for k in zeros]]
    return occlusion.cut_corners(gray, h, _BLACK, _WHITE, targets, occlusion.PART_QUADS[parts])


# A bar over slot 2 of 1110 at 42 degrees in the sign plane, 0.24 diameters
# wide, its centre line 0.01 off the slot's centre: it hides the slot whole
# and cuts 15 % off a corner of slot 1 (read without it: 1010, another code
# of the map).
_SLOT2_BAR = _bar(_CENTRES[3] + 0.01 * np.array([0.669, -0.743]), 42.0, 0.12)


@pytest.mark.parametrize("sign_px", [48.0, 70.0, 100.0])
def test_a_bar_that_cuts_a_neighbours_corner_erases_the_slot_it_hides(sign_px):
    rng = np.random.default_rng(11)
    for rotation in rng.uniform(0.0, 360.0, 4).tolist():
        gray, h = _face("1110", sign_px, rotation, rng, bar=_SLOT2_BAR)
        bands = _cut(gray, h, zeros=[2, 4])
        assert any(b.distance(_CENTRES[3:4])[0] < b.half_width for b in bands), rotation
        # Slot 4, true black, lies on the other side: not erased.
        assert not any(b.distance(_CENTRES[5:6])[0] < b.half_width for b in bands), rotation


@pytest.mark.parametrize("sign_px", [24.0, 32.0, 45.0, 80.0])
def test_blurred_and_compressed_corners_of_an_unoccluded_face_are_not_cut(sign_px):
    """Blur and JPEG round every corner alike: nothing is cut or erased."""
    rng = np.random.default_rng(5)
    for code in ("1110", "0101", "1001", "0010"):
        zeros = [k for k in range(1, 5) if code[k - 1] == "0"]
        for psf_px, jpeg in ((0.5, 70), (0.8, 75), (1.1, 85)):
            rotation = float(rng.uniform(0.0, 360.0))
            gray, h = _face(code, sign_px, rotation, rng, psf_px=psf_px, jpeg=jpeg)
            assert _cut(gray, h, zeros) == [], (code, psf_px, rotation)
            # Read, or refused for the blur (a 24 px sign at 1.1 px finds no
            # location square), never for an occluder.
            res = decode_roi(gray, PAPER_CODES)
            assert res.code in (code, None) and res.erased_slots == (), (code, psf_px, rotation)
            assert res.reason != DecodeReason.OCCLUDED, (code, psf_px, rotation)


def _rng7(state: int, uinteger: int) -> np.random.Generator:
    rng = np.random.default_rng()
    rng.bit_generator.state = {
        "bit_generator": "PCG64",
        "state": {"state": state, "inc": _INC_SEED_7},
        "has_uint32": 1,
        "uinteger": uinteger,
    }
    return rng


def test_a_member_over_slot_3_that_cuts_slot_2s_corner(scene):
    """1110 with slot 3 under a member as dark as the background beyond the
    rim (92 px sign, seed 7 "one slot covered" crop 809): its edge takes a
    corner off slot 2. Was read 1100."""
    s = scene.SceneSettings(
        sign_px=91.72811730043051,
        rotation_deg=16.962402899021477,
        tilt_deg=35.582563686738425,
        tilt_axis_deg=136.40040666815133,
        focal_px=1000.0,
        photo="camera",
        black_level=30.210674576682948,
        white_level=230.84215281039724,
        psf_sigma_px=0.49414111191547955,
        noise_sigma=1.278421563634146,
        jpeg_quality=81,
        bar_over_slot=3,
    )
    state = (54956910309988540981183340213418055129, 2467297064)
    crop = scene.render_scene_crop("1110", s, _rng7(*state))
    assert tuple(crop.covered_slots) == (3,)
    res = decode_roi(crop.image, PAPER_CODES)
    assert res.code is None and res.reason == DecodeReason.OCCLUDED
    bare = scene.render_scene_crop("1110", replace(s, bar_over_slot=0), _rng7(*state))
    assert decode_roi(bare.image, PAPER_CODES).code == "1110"
