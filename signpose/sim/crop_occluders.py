"""What covers a sign in a synthetic crop: members, conductors, insulators, and the truth of it.

An occluder is a straight band across the whole crop (it continues past the
disc's rim, as a lattice member or a conductor in front of a sign does),
drawn over the face before blur, noise and JPEG. Kinds and their defaults
(each drawn from the crop's generator when not given):

    ``member``     a lattice member (angle steel): 0.06-0.25 x sign_px wide,
                   grey level 40-110.
    ``conductor``  a conductor: 0.8-2 px x max(1, sign_px / 60) wide, grey 20-80
                   (what ``CropSettings.power_line`` draws).
    ``insulator``  an insulator string: a core 0.3 x the shed diameter wide with
                   sheds (discs) 0.12-0.25 x sign_px across every 0.6 shed
                   diameters, grey 90-150 (toughened glass).

The band passes through ``through``: a part of the face (``center``,
``direction``, ``slot1``..``slot4``, whether the slot is white or black), a
crop pixel (u, v), or, when None, a random point within 0.3 sign_px of the
disc centre; at ``angle_deg`` from the u axis toward +v (random when None).

Truth (``coverage``): the share of each part's area the occluders cover,
measured on anti-aliased masks before blur; a coded slot counts as covered
when that share is at least ``signpose.io.boxes.COVERED_FRACTION``.
Crop pixels: u right, v down, centres at integers.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from signpose.frontend.homography import apply_homography
from signpose.frontend.sign import fill_polygon_aa, sign_shape
from signpose.io.boxes import COVERED_FRACTION, PART_NAMES

OCCLUDER_KINDS = ("member", "conductor", "insulator")
TRUTH_SUPERSAMPLE = 4


@dataclass(frozen=True)
class CropOccluder:
    """One band in front of the sign (fields left None are drawn at random, see module doc).

    Attributes:
        kind: one of ``OCCLUDER_KINDS``.
        through: a part name, a crop pixel (u, v), or None.
        angle_deg: direction of the band from the u axis toward +v [deg].
        width_px: band width [px] (for an insulator: the sheds' diameter).
        value: grey level 0..255 of the band.
    """

    kind: str = "member"
    through: str | tuple[float, float] | None = None
    angle_deg: float | None = None
    width_px: float | None = None
    value: float | None = None


@dataclass(frozen=True)
class Band:
    """A drawn occluder: kind, centre line (two far end points [px]), width [px], grey level,
    direction [rad] from the u axis toward +v."""

    kind: str
    p0: np.ndarray
    p1: np.ndarray
    width_px: float
    value: float
    angle_rad: float

    def to_json(self) -> dict:
        return {
            "kind": self.kind,
            "angle_deg": math.degrees(self.angle_rad),
            "width_px": float(self.width_px),
            "value": float(self.value),
        }


def bar(image: np.ndarray, p0, p1, width: float, value: float) -> None:
    """Draw a straight bar of ``width`` px from p0 to p1 into float ``image`` (anti-aliased)."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    d = p1 - p0
    n = np.array([-d[1], d[0]]) / max(np.hypot(*d), 1e-9) * width / 2
    fill_polygon_aa(image, np.array([p0 + n, p1 + n, p1 - n, p0 - n]), value, supersample=4)


def line_through(rng: np.random.Generator, h: int, w: int, point=None, angle=None):
    """End points of a line crossing the whole (h, w) image (random point/angle when None)."""
    if point is None:
        point = (rng.uniform(0, w), rng.uniform(0, h))
    if angle is None:
        angle = rng.uniform(0, math.pi)
    d = np.array([math.cos(angle), math.sin(angle)]) * 2 * (h + w)
    p = np.asarray(point, float)
    return p - d, p + d


def part_polygons_px(crop_H_sign: np.ndarray, diameter_m: float) -> dict[str, np.ndarray]:
    """Part name -> (4, 2) corners [px] of every part, white or black, in the crop."""
    parts = sign_shape("1111", diameter_m).white_parts
    return {name: apply_homography(crop_H_sign, parts[name]) for name in PART_NAMES}


def _default_width(kind: str, sign_px: float, rng: np.random.Generator) -> float:
    if kind == "member":
        return float(rng.uniform(0.06, 0.25) * sign_px)
    if kind == "conductor":
        return float(rng.uniform(0.8, 2.0) * max(1.0, sign_px / 60.0))
    return float(rng.uniform(0.12, 0.25) * sign_px)


def _default_value(kind: str, rng: np.random.Generator) -> float:
    lo, hi = {"member": (40, 110), "conductor": (20, 80), "insulator": (90, 150)}[kind]
    return float(rng.uniform(lo, hi))


def place(
    occluder: CropOccluder,
    rng: np.random.Generator,
    side: int,
    center_px: np.ndarray,
    parts_px: dict[str, np.ndarray],
    sign_px: float,
) -> Band:
    """The band ``occluder`` describes in a ``side`` x ``side`` crop (random fields drawn)."""
    if occluder.kind not in OCCLUDER_KINDS:
        raise ValueError(f"unknown occluder {occluder.kind!r}: use one of {OCCLUDER_KINDS}")
    angle = (
        math.radians(occluder.angle_deg)
        if occluder.angle_deg is not None
        else rng.uniform(0, math.pi)
    )
    if occluder.through is None:
        point = np.asarray(center_px) + rng.uniform(-0.3, 0.3, size=2) * sign_px
    elif isinstance(occluder.through, str):
        if occluder.through not in parts_px:
            raise ValueError(f"unknown part {occluder.through!r}: use one of {PART_NAMES}")
        point = parts_px[occluder.through].mean(axis=0)
    else:
        point = np.asarray(occluder.through, float)
    width = (
        occluder.width_px
        if occluder.width_px is not None
        else _default_width(occluder.kind, sign_px, rng)
    )
    value = occluder.value if occluder.value is not None else _default_value(occluder.kind, rng)
    p0, p1 = line_through(rng, side, side, point=point, angle=angle)
    return Band(occluder.kind, p0, p1, float(width), float(value), float(angle))


def draw_band(image: np.ndarray, band: Band, value: float | None = None) -> None:
    """Paint ``band`` into float ``image`` (in place) at its grey level or ``value``."""
    v = band.value if value is None else value
    if band.kind != "insulator":
        bar(image, band.p0, band.p1, band.width_px, v)
        return
    # A core along the string, and a shed (a disc seen edge-on-ish) every 0.6 diameters.
    bar(image, band.p0, band.p1, 0.3 * band.width_px, v)
    d = band.p1 - band.p0
    length = float(np.hypot(*d))
    along, normal = d / length, np.array([-d[1], d[0]]) / length
    h, w = image.shape[:2]
    mid = 0.5 * (band.p0 + band.p1)
    step = 0.6 * band.width_px
    half = 0.5 * band.width_px
    for k in range(-int(length / step / 2), int(length / step / 2) + 1):
        c = mid + k * step * along
        if not (-half <= c[0] <= w + half and -half <= c[1] <= h + half):
            continue
        t = np.linspace(0, 2 * math.pi, 24, endpoint=False)[:, None]
        shed = c + np.cos(t) * half * normal + np.sin(t) * 0.12 * band.width_px * along
        fill_polygon_aa(image, shed, v, supersample=4)


def coverage(
    bands: Sequence[Band], parts_px: dict[str, np.ndarray], shape: tuple[int, int]
) -> tuple[dict[str, float], tuple[int, ...]]:
    """(part name -> covered share of its area, coded slots covered >= COVERED_FRACTION)."""
    if not bands:
        return {name: 0.0 for name in parts_px}, ()
    mask = np.zeros(shape, np.float64)
    for band in bands:
        draw_band(mask, band, 1.0)
    cover = {}
    for name, poly in parts_px.items():
        part = np.zeros(shape, np.float64)
        fill_polygon_aa(part, poly, 1.0, TRUTH_SUPERSAMPLE)
        area = float(part.sum())
        cover[name] = float((part * mask).sum()) / area if area > 0 else 0.0
    slots = tuple(k for k in range(1, 5) if cover[f"slot{k}"] >= COVERED_FRACTION)
    return cover, slots
