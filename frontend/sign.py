"""The coded sign (paper §1.1): geometry, codes, keypoints and rendering.

This module is the single definition of the sign. Everything else reads it.

Sign frame (metres), the face as its viewers see it:
    origin at the disc centre; x to the face's right, y up (from the centre
    toward the directional rectangle), z out of the face toward the viewers.
    Right-handed: x = y cross z, matching the map's ``right = up x normal``.

Layout, in units of the disc radius R:
    * a black disc of radius R;
    * a white location square of side 0.36 R at the centre;
    * five slots on a circle of radius 0.6 R, 72 degrees apart. Slot 0 sits
      straight up and holds the thin radial directional rectangle
      (0.16 R wide, 0.5 R long). Slots 1-4 follow clockwise as the viewer
      sees the face and hold the coded rectangles (0.42 R tangential x 0.32 R
      radial), white when their bit is 1, absent (black) when it is 0.

Bit order: bits are read clockwise from the directional rectangle, the first
(slot 1) is the most significant. A code is the string of its four bits,
"0000" to "1111".

Texture pixels: a square texture of ``px`` pixels shows the face from the
front with the directional rectangle straight up. Pixel centres are at
integer coordinates (OpenCV's convention), so the texture spans
[-0.5, px - 0.5] in both axes, u to the right, v down.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from signpose.core.errors import InputError

ALL_CODES: tuple[str, ...] = tuple(format(i, "04b") for i in range(16))
PAPER_CODES: tuple[str, ...] = (
    "0001",
    "0010",
    "0100",
    "0101",
    "0110",
    "1000",
    "1001",
    "1010",
    "1100",
    "1110",
)

# Geometry in units of R.
LOCATION_SIDE_R = 0.36
SLOT_RADIUS_R = 0.6
SLOT_STEP_DEG = 72.0
DIRECTION_WIDTH_R = 0.16
DIRECTION_LENGTH_R = 0.5
CODED_TANGENTIAL_R = 0.42
CODED_RADIAL_R = 0.32
N_BITS = 4
DISC_VERTICES = 256

KEYPOINT_NAMES: tuple[str, ...] = ("center", "direction", "slot1", "slot2", "slot3", "slot4")


def validate_code(code: str) -> str:
    """Return ``code`` if it is one of "0000".."1111", else raise InputError."""
    if not isinstance(code, str) or code not in ALL_CODES:
        raise InputError(f"unknown sign code {code!r}: use four bits such as '0101'")
    return code


def code_bits(code: str) -> tuple[int, int, int, int]:
    """Bits of ``code`` in slot order 1..4 (slot 1 is the most significant)."""
    validate_code(code)
    return tuple(int(c) for c in code)  # type: ignore[return-value]


def slot_angle_rad(slot: int) -> float:
    """Angle of slot ``slot`` (0 = directional) from the sign's +x axis.

    Slot 0 is at +90 degrees (up); clockwise as the viewer sees the face means
    decreasing angle in the x-right, y-up sign frame.
    """
    return math.radians(90.0 - SLOT_STEP_DEG * slot)


def _slot_rectangle(slot: int, radius_m: float) -> np.ndarray:
    """(4, 2) corners [m] of slot ``slot``'s rectangle in the sign's x-y plane."""
    theta = slot_angle_rad(slot)
    radial = np.array([math.cos(theta), math.sin(theta)])
    tangential = np.array([math.sin(theta), -math.cos(theta)])  # clockwise direction
    if slot == 0:
        half_r, half_t = DIRECTION_LENGTH_R / 2, DIRECTION_WIDTH_R / 2
    else:
        half_r, half_t = CODED_RADIAL_R / 2, CODED_TANGENTIAL_R / 2
    centre = SLOT_RADIUS_R * radial
    corners = [
        centre + sr * half_r * radial + st * half_t * tangential
        for sr, st in ((-1, -1), (1, -1), (1, 1), (-1, 1))
    ]
    return np.asarray(corners) * radius_m


@dataclass(frozen=True)
class SignShape:
    """The drawable parts of one sign face, in the sign frame.

    Attributes:
        code: the sign's code, "0000".."1111".
        diameter_m: disc diameter [m].
        disc: (DISC_VERTICES, 2) polygon of the black disc [m], sign x-y plane.
        white_parts: name -> (4, 2) corners [m] of each white rectangle
            ("center", "direction", and "slotK" for every white coded slot).
    """

    code: str
    diameter_m: float
    disc: np.ndarray
    white_parts: dict[str, np.ndarray]


def sign_shape(code: str, diameter_m: float = 1.0) -> SignShape:
    """Polygons of the face of sign ``code`` with disc diameter ``diameter_m``."""
    bits = code_bits(code)
    r = diameter_m / 2.0
    t = np.linspace(0.0, 2 * math.pi, DISC_VERTICES, endpoint=False)
    disc = np.stack([np.cos(t), np.sin(t)], axis=1) * r
    h = LOCATION_SIDE_R / 2 * r
    parts = {
        "center": np.array([[-h, -h], [h, -h], [h, h], [-h, h]]),
        "direction": _slot_rectangle(0, r),
    }
    for slot, bit in enumerate(bits, start=1):
        if bit:
            parts[f"slot{slot}"] = _slot_rectangle(slot, r)
    return SignShape(code=code, diameter_m=diameter_m, disc=disc, white_parts=parts)


def sign_keypoints(code: str, diameter_m: float) -> dict[str, np.ndarray]:
    """Named keypoints of sign ``code`` in its own frame.

    Returns:
        name -> (3,) point [m] in the sign frame (z = 0): ``center``,
        ``direction`` and ``slotK`` for each white coded slot. Black slots have
        nothing to observe and are left out.
    """
    shape = sign_shape(code, diameter_m)
    return {
        name: np.array([*corners.mean(axis=0), 0.0]) for name, corners in shape.white_parts.items()
    }


def all_slot_keypoints(diameter_m: float) -> dict[str, np.ndarray]:
    """Every possible keypoint (all four slots, white or not) in the sign frame [m]."""
    return sign_keypoints("1111", diameter_m)


def texture_px_from_sign_xy(sign_xy_m: np.ndarray, diameter_m: float, px: int) -> np.ndarray:
    """Texture pixel coordinates of sign-plane points.

    Args:
        sign_xy_m: (N, 2) points in the sign's x-y plane [m].
        diameter_m: disc diameter [m].
        px: texture side [px]; the disc fills it.

    Returns:
        (N, 2) pixel coordinates (u right, v down, pixel centres at integers).
    """
    xy = np.asarray(sign_xy_m, dtype=float).reshape(-1, 2)
    r = diameter_m / 2.0
    scale = px / (2.0 * r)
    u = (xy[:, 0] + r) * scale - 0.5
    v = (r - xy[:, 1]) * scale - 0.5
    return np.stack([u, v], axis=1)


def fill_polygon_aa(
    image: np.ndarray, polygon_px: np.ndarray, value: float, supersample: int = 4
) -> None:
    """Fill ``polygon_px`` into float ``image`` with area-weighted anti-aliasing.

    Rendering helper shared by the PNG writer and the simulator. The polygon
    is rasterised at ``supersample`` times the resolution inside its bounding
    box and box-filtered down, then blended into ``image`` (in place; this is
    a drawing primitive on a buffer the caller owns).

    Args:
        image: (H, W) float image, changed in place.
        polygon_px: (N, 2) vertices in pixel coordinates (centres at integers).
        value: intensity to paint.
        supersample: sub-samples per pixel side.
    """
    h, w = image.shape[:2]
    poly = np.asarray(polygon_px, dtype=float).reshape(-1, 2)
    x0 = max(int(math.floor(poly[:, 0].min() + 0.5)), 0)
    y0 = max(int(math.floor(poly[:, 1].min() + 0.5)), 0)
    x1 = min(int(math.ceil(poly[:, 0].max() + 0.5)), w)
    y1 = min(int(math.ceil(poly[:, 1].max() + 0.5)), h)
    if x1 <= x0 or y1 <= y0:
        return
    s = supersample
    mask = np.zeros(((y1 - y0) * s, (x1 - x0) * s), np.uint8)
    # Pixel (x, y) covers [x-0.5, x+0.5); sub-pixel centres sit at
    # x - 0.5 + (k + 0.5)/s, hence the shift below.
    local = (poly - [x0 - 0.5, y0 - 0.5]) * s - 0.5
    shift = 4
    pts = np.round(local * (1 << shift)).astype(np.int32)
    cv2.fillPoly(mask, [pts], 255, lineType=cv2.LINE_8, shift=shift)
    cover = mask.reshape(y1 - y0, s, x1 - x0, s).mean(axis=(1, 3)) / 255.0
    roi = image[y0:y1, x0:x1]
    roi *= 1.0 - cover
    roi += cover * value


def render_sign_png(code: str, px: int = 512, supersample: int = 4) -> np.ndarray:
    """Square uint8 image of the face, the disc filling it, white outside.

    The directional rectangle points straight up, so the top of the image is
    the sign's ``up``.
    """
    shape = sign_shape(code, 1.0)
    img = np.full((px, px), 255.0)
    fill_polygon_aa(img, texture_px_from_sign_xy(shape.disc, 1.0, px), 0.0, supersample)
    for corners in shape.white_parts.values():
        fill_polygon_aa(img, texture_px_from_sign_xy(corners, 1.0, px), 255.0, supersample)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def render_sign_svg(code: str, diameter_mm: float = 800.0) -> str:
    """Printable SVG of the face at true size (millimetres)."""
    shape = sign_shape(code, diameter_mm / 1000.0)
    r_mm = diameter_mm / 2.0

    def pts(corners_m: np.ndarray) -> str:
        # SVG y grows downward; the sign's y grows up.
        return " ".join(f"{x * 1000 + r_mm:.3f},{r_mm - y * 1000:.3f}" for x, y in corners_m)

    rects = "\n".join(
        f'  <polygon points="{pts(c)}" fill="#fff"><title>{name}</title></polygon>'
        for name, c in shape.white_parts.items()
    )
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{diameter_mm:g}mm" '
        f'height="{diameter_mm:g}mm" viewBox="0 0 {diameter_mm:g} {diameter_mm:g}">\n'
        f"  <title>signpose sign {code} ({diameter_mm:g} mm)</title>\n"
        f'  <circle cx="{r_mm:g}" cy="{r_mm:g}" r="{r_mm:g}" fill="#000"/>\n'
        f"{rects}\n</svg>\n"
    )
