"""A member in front laid over one white coded slot must not give another code.

Each case is one crop of scripts/independent_scene.py's "one slot covered"
condition (seed 2017 of scripts/eval_decoder.py --independent-only) that the
decoder read as another code of the paper's map: rendered here from its
scene settings and the renderer's random state at that crop (no image
fixture). Each test checks both sides: the crop is now refused, and the same
scene without the member decodes to the truth (the refusal is the member's).
"""

import importlib.util
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from signpose.frontend.decoder import DecodeReason, decode_roi
from signpose.frontend.sign import PAPER_CODES

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "independent_scene.py"
_INC = 127265218069137303202403448684290734789


@pytest.fixture(scope="module")
def scene():
    spec = importlib.util.spec_from_file_location("independent_scene_one_slot", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # its dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def _rng(state: int, uinteger: int) -> np.random.Generator:
    rng = np.random.default_rng()
    rng.bit_generator.state = {
        "bit_generator": "PCG64",
        "state": {"state": state, "inc": _INC},
        "has_uint32": 1,
        "uinteger": uinteger,
    }
    return rng


def _both_sides(scene, code: str, state: tuple[int, int], **settings) -> None:
    s = scene.SceneSettings(**settings)
    crop = scene.render_scene_crop(code, s, _rng(*state))
    assert tuple(crop.covered_slots) == (s.bar_over_slot,)
    res = decode_roi(crop.image, PAPER_CODES)
    assert res.code is None and res.reason == DecodeReason.OCCLUDED
    bare = scene.render_scene_crop(code, replace(s, bar_over_slot=0), _rng(*state))
    assert decode_roi(bare.image, PAPER_CODES).code == code


def test_a_member_seen_with_both_edges_beyond_one_rim_crossing_only(scene):
    """1010 with slot 3 under a dark member (24 px sign): beyond one rim crossing
    the member shows both edges, beyond the other it runs over dark clutter.
    Was read 1000."""
    _both_sides(
        scene,
        "1010",
        (167831563008558329356898465079288523927, 190149766),
        sign_px=24.556388111628134,
        rotation_deg=239.90557679409466,
        tilt_deg=31.51260071562988,
        tilt_axis_deg=90.08205077528116,
        focal_px=1000.0,
        photo="camera",
        black_level=40.96167659829629,
        white_level=234.87053649384424,
        psf_sigma_px=0.4748766226748564,
        noise_sigma=2.6675097080737453,
        jpeg_quality=82,
        bar_over_slot=3,
    )


def test_a_shaded_member_whose_dark_edge_is_print_black(scene):
    """1001 with slot 1 under a shaded member lighter than the print on one
    side and print black on the other (102 px sign): the slot's centre lay
    just outside the member's measured extent. Was read 0001."""
    _both_sides(
        scene,
        "1001",
        (152551121966766572560851315433929049228, 2600044795),
        sign_px=102.6742587041495,
        rotation_deg=6.45684501441385,
        tilt_deg=29.031633945684334,
        tilt_axis_deg=92.72837137290483,
        focal_px=600.0,
        photo="grass",
        black_level=46.88660472835203,
        white_level=198.89492752818433,
        psf_sigma_px=0.47944664402348636,
        noise_sigma=1.8813647990125955,
        jpeg_quality=82,
        bar_over_slot=1,
        bars_behind=1,
    )
