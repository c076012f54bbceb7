"""A detector region off its sign near a wide lens's edge: the crop cuts the rim.

``data/fisheye_frame41_edge.png`` is the lower right corner (rows 540-719,
columns 1040-1279) of frame 41 of scripts/eval_flight.py's fisheye flight
(equidistant lens, 120 deg across, 1280x720; drawn by
scripts/independent_flight.py). Sign 1110 lies at x 1131-1198, y 636-709,
about 60 deg off the camera's axis; the cascade's merged region
(1141, 616, 72, 72) sits 20 px high, so the default crop (margin 0.25) cuts
the disc's lower rim (``cut_by_edge``) and the detector's retries at margins
0.05 / 0.5 find no location rectangle. The decoder now crops once more
around the disc it fitted (``DecoderSettings.recrop_cut_rim``).
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from signpose.frontend.decoder import DecodeReason, DecoderSettings, decode_region
from signpose.frontend.detector import DetectorSettings, SignDetector

CORNER = Path(__file__).parent / "data" / "fisheye_frame41_edge.png"
CORNER_ORIGIN_PX = (1040, 540)  # the corner's (column, row) in the frame
CODE = "1110"
MAP_CODES = ("0001", "0010", "0100", "0101", "0110", "1000", "1001", "1010", "1100", "1110")
# The merged region of frame 41 [px], in the corner's pixels.
REGION = (1141.0 - 1040.0, 616.0 - 540.0, 72.0, 72.0)
# The sign's centre read from a crop that holds the disc (margin 0.3) [px].
CENTRE_PX = (1165.14 - 1040.0, 672.72 - 540.0)
# Slot 3's centre read from that crop [px].
SLOT3_PX = (round(1176.6 - 1040.0), round(652.7 - 540.0))
OLD = DecoderSettings(recrop_cut_rim=False)


@pytest.fixture(scope="module")
def corner() -> np.ndarray:
    gray = cv2.imread(str(CORNER), cv2.IMREAD_GRAYSCALE)
    assert gray is not None and gray.shape == (180, 240)
    return gray


def test_the_offset_region_reads_after_a_crop_around_the_fitted_disc(corner):
    old = decode_region(corner, REGION, MAP_CODES, OLD)
    assert old.code is None and old.reason == DecodeReason.CUT_BY_EDGE
    # The refusal carries the disc it fitted, in the image's pixels.
    assert old.ellipse is not None
    assert math.dist(old.ellipse[0], CENTRE_PX) < 1.0
    res = decode_region(corner, REGION, MAP_CODES)
    assert res.code == CODE and res.reason == DecodeReason.OK
    assert math.dist(res.keypoints_px["center"], CENTRE_PX) < 0.1
    # The keypoints of a crop that held the disc in the first place.
    held = decode_region(corner, REGION, MAP_CODES, DecoderSettings(region_margin=0.3))
    assert held.code == CODE
    assert set(res.keypoints_px) == set(held.keypoints_px)
    for name, uv in held.keypoints_px.items():
        assert math.dist(res.keypoints_px[name], uv) < 0.05
    assert res.keypoint_sigma_px.keys() == res.keypoints_px.keys()
    # The detector's retry margins alone do not read it.
    for margin in DetectorSettings().retry_margins:
        assert (
            decode_region(
                corner,
                REGION,
                MAP_CODES,
                DecoderSettings(region_margin=margin, recrop_cut_rim=False),
            ).code
            is None
        )
    assert SignDetector().decode_box(corner, REGION, n_windows=40, codes=MAP_CODES).code == CODE


def test_the_second_crop_keeps_the_checks_a_code_the_map_lacks_stays_refused(corner):
    others = tuple(c for c in MAP_CODES if c != CODE)
    assert decode_region(corner, REGION, others, OLD).reason == DecodeReason.CUT_BY_EDGE
    res = decode_region(corner, REGION, others)
    assert res.code is None and res.reason == DecodeReason.CODE_NOT_IN_MAP
    # A gray member across slot 3 leaves 1110 and 1100 open: occluded, as
    # on a crop that holds the disc, not a code.
    covered = corner.copy()
    cv2.line(covered, (SLOT3_PX[0] - 60, SLOT3_PX[1]), (SLOT3_PX[0] + 60, SLOT3_PX[1]), 90, 9)
    assert decode_region(covered, REGION, MAP_CODES, OLD).reason == DecodeReason.CUT_BY_EDGE
    held = decode_region(covered, REGION, MAP_CODES, DecoderSettings(region_margin=0.3))
    assert held.reason == DecodeReason.OCCLUDED
    res = decode_region(covered, REGION, MAP_CODES)
    assert res.code is None and res.reason == DecodeReason.OCCLUDED


def _lowest_rim_row(ellipse) -> float:
    (_, cv), (major, minor), angle_deg = ellipse
    s, c = math.sin(math.radians(angle_deg)), math.cos(math.radians(angle_deg))
    return cv + 0.5 * math.hypot(major * s, minor * c)


@pytest.mark.parametrize("rows", [166, 168])
def test_a_sign_the_image_border_cuts_stays_refused(corner, rows):
    """The image ends 3 / 1 rows above the disc's lowest point (row 169 of the corner).

    With 1 row missing a crop around the true box still reads it (the
    decoder's rim test is at 0.46 diameters); the second crop is not made
    for a disc that leaves the image, so the offset region stays refused.
    """
    cut = corner[:rows]
    res = decode_region(cut, REGION, MAP_CODES)
    assert res.code is None and res.reason == DecodeReason.CUT_BY_EDGE
    assert _lowest_rim_row(res.ellipse) > rows - 0.5  # the fitted rim leaves the image
    # The disc fits inside one more row of image: then it reads.
    assert _lowest_rim_row(res.ellipse) < 170 - 0.5
    assert decode_region(corner[:170], REGION, MAP_CODES).code == CODE


def test_a_disc_fitted_beside_the_region_is_not_cropped_again(corner):
    """The region's box must hold the fitted disc's centre: a reading of a sign
    beside the region would carry a box that misses it."""
    beside = (CENTRE_PX[0] + 8.0, 117.0, 72.0, 72.0)  # the centre 8 px left of the box
    old = decode_region(corner, beside, MAP_CODES, OLD)
    assert old.reason == DecodeReason.CUT_BY_EDGE
    assert math.dist(old.ellipse[0], CENTRE_PX) < 1.5  # the right disc, outside the box
    res = decode_region(corner, beside, MAP_CODES)
    assert res.code is None and res.reason == DecodeReason.CUT_BY_EDGE
    holding = (CENTRE_PX[0] - 2.0, 117.0, 72.0, 72.0)
    assert decode_region(corner, holding, MAP_CODES, OLD).reason == DecodeReason.CUT_BY_EDGE
    assert decode_region(corner, holding, MAP_CODES).code == CODE
