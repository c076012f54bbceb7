"""The paper's contour decoder (§1.2, steps 2-7) with sub-pixel keypoints.

One region of interest (a crop around one sign) in, one ``DecodeResult`` out.

Steps, as in the paper, and where this module departs from it:

2. gray: colour crops are converted to one channel.
3. binarise at the crop's mean gray level.
4. contours; the sign's extent is the largest dark region that encloses
   white holes. Instead of the paper's external (axis-aligned) rectangles we
   keep each contour's moments: under perspective a rectangle's axis-aligned
   box is neither centred on it nor shaped like it, while the area centroid
   and second moments transform predictably (the centroid exactly under an
   affine map) and also give each hole's aspect ratio at any rotation.
5. location rectangle: the hole closest to the centre of the sign's extent.
6. directional rectangle: among the other holes, the one with the smallest
   area and the largest aspect ratio.
7. read the bits clockwise from the direction centre -> directional
   rectangle, first bit = most significant. Under an oblique view the angles
   between holes are distorted, so they are measured after undoing the
   affine part of the view, estimated from the disc's (or the location
   square's) second moments, which are isotropic on the sign.

Then, beyond the paper:

* a homography ``image_H_sign`` is fitted to the rectangles' centroids; the
  centroid of a tilted rectangle is not the image of its centre, so the fit
  predicts each rectangle's image centroid exactly (projected polygon) and
  iterates the small correction. Every keypoint is the sign-frame keypoint
  mapped through this homography (sub-pixel, the same map for all). The
  centroids are gray-level ones (white fraction per pixel), which blur and
  the threshold do not move. Codes with fewer than two white slots have
  too few rectangles for a homography: their perspective comes from the
  disc's rim (the polar of the centre is the vanishing line).
* the paper's mean threshold first; when it fails, Otsu's, a higher one
  (blur joining parts), a local mean (dark surroundings) and an opened mask
  (a cable across the face), in turn.
* verification: gray levels sampled through the homography at all five slot
  positions must show exactly one thin white rectangle (the directional one)
  and wide white or black coded slots that agree with the contours. A crop
  that does not pass returns no code and a reason; one wrong code costs far
  more than one missed frame.
* occlusion (``frontend.occlusion``): a coded slot is read as 1, 0 or erased
  (gray levels neither clearly white nor the disc's black, or a band in front
  of the face over the slot's centre: dark beyond the rim, or off the print's
  black on the rim band, ``occlusion.off_black_bands``). A code is accepted
  only when exactly one code of ``codes`` fits the slots that are not
  erased; the result carries
  ``erased_slots`` and has no keypoints of covered parts. Otherwise the
  reading is refused (``occluded``), and so is a code whose every white slot
  is erased unless one of them shows white in part (``occlusion.shows_white``).
  ``DecoderSettings.search_bars`` adds a line search for print-black bars
  (``occlusion.straight_bars``; off: it refuses some unoccluded signs).
  White on the face that the read code does not explain is refused too
  (``inconsistent``). A dark band beside white parts that show white
  throughout (dark photograph beyond the rim joined across the black face)
  is not in front of them (``occlusion.dark_bands``' ``clean``); the
  keypoints of the clean parts it reaches, but the location square's, are
  not reported (a conductor there pulls a centroid without darkening the
  part). Independent scenes, 1,000 per condition, seeds 2017 / 99 / 7 / 5 /
  31 and held out 123 / 77: the same wrong codes (5 / 5 / 8 / 16 / 8 / 6 /
  10), unoccluded photographs 94.8 -> 95.7 % on seed 2017 (see the commit).
* codes with fewer than two white slots are read under the rim's
  perspective (``_rim_view``): three parts fix only an affine map, which
  misplaced the samples of clean oblique signs (the simulator's main set,
  80-200 px: 723 -> 732 of 784 decoded).
* specular glare (issue 11): a reading that fails or erases a slot is read
  again with a smooth glow taken off the samples (``_without_glow``: a
  cubic in the sign plane fitted to the samples black whatever the code,
  kept only when it fits them all, lifts the face by 0.1 of the contrast
  and is a round bump at its peak); the occlusion evidence then reads the
  flattened face, and a black-read slot under a band of the plain image
  stays erased. Independent scenes, 1,000 per condition, seed 2017 / 99:
  glare 31.2 -> 52.7 / 31.9 -> 55.5 %, the same wrong codes (7 / 9).
  Tried and dropped: a quadratic (43.7 % on seed 2017 with the residual
  bound 0.16, 33.1 % with 0.08); neither the roundness test nor the plain
  image's bands (58.3 %, but wrong codes 7 -> 31: members over a slot
  taken for glow); the plain image's ``off_black_bands`` only (57.1 /
  60.7 %, 2 new wrong codes per seed); curvature ratio 0.15 (no more
  glare decoded, one new wrong code). Left: glare whose spot breaks the
  contours (no_location, cut_by_edge: ~20 % of glare crops) or whose glow
  a cubic does not follow (a narrow spot).
* the paper's first robustness rule: a code that is not in ``codes`` (the
  map's codes) is dropped (``code_not_in_map``); the refusal keeps the code
  read in ``unknown_code`` (a sign the map misses is then countable).
* keypoint noise: ``keypoint_sigma_px`` per keypoint and axis from
  ``frontend.keypoint_noise``, calibrated against the simulator by
  scripts/calibrate_sigma.py.

Image coordinates: pixel centres at integers (OpenCV), u right, v down. The
sign is seen from the front, so "clockwise as the viewer sees the face" is
clockwise on screen.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from signpose.frontend import occlusion
from signpose.frontend.homography import (
    Ellipse,
    affine_design,
    disc_ellipse,
    fit_affine,
    fit_homography,
    polygon_centroids,
    prepare_source,
    px_per_diameter,
)

# The sigma model lives in its own module; these names stay importable from here.
from signpose.frontend.keypoint_noise import (  # noqa: F401
    SIGMA_MODEL,
    PartMeasures,
    SigmaInputs,
    SigmaModel,
    keypoint_sigmas,
    mean_sigma,
    measure_parts,
    unfitted_residuals_px,
)
from signpose.frontend.sign import (
    ALL_CODES,
    N_BITS,
    SLOT_STEP_DEG,
    sign_shape,
    slot_angle_rad,
)


class DecodeReason(enum.StrEnum):
    """Why a crop gave no code ("ok" when it did); the value is the file token."""

    OK = "ok"
    NO_SIGN = "no_sign"  # nothing sign-like: no dark region with white holes
    NO_LOCATION = "no_location"  # no hole can be the location rectangle
    AMBIGUOUS_DIRECTION = "ambiguous_direction"  # no single thin rectangle among the slots
    INCONSISTENT = "inconsistent"  # contours and gray levels disagree about the bits
    LOW_CONTRAST = "low_contrast"  # black and white too close to read
    CUT_BY_EDGE = "cut_by_edge"  # part of the sign lies outside the crop
    CODE_NOT_IN_MAP = "code_not_in_map"  # decoded, but the map has no sign with this code
    OCCLUDED = "occluded"  # covered slots leave more than one code of the map possible


REASONS: tuple[str, ...] = tuple(r.value for r in DecodeReason)
# Refusals that end the search: the sign was read and verified, and the
# answer is no (another hypothesis would only be a worse reading of it).
_FINAL_REASONS = frozenset({DecodeReason.CODE_NOT_IN_MAP, DecodeReason.OCCLUDED})
# Which failure names a crop best when several hypotheses fail (higher wins).
_REASON_RANK = {
    DecodeReason.NO_SIGN: 0,
    DecodeReason.NO_LOCATION: 1,
    DecodeReason.LOW_CONTRAST: 2,
    DecodeReason.AMBIGUOUS_DIRECTION: 3,
    DecodeReason.INCONSISTENT: 4,
    DecodeReason.CUT_BY_EDGE: 5,
    DecodeReason.OCCLUDED: 6,  # the sign was read, but covered slots leave it open
    DecodeReason.CODE_NOT_IN_MAP: 7,
    DecodeReason.OK: 8,
}

# Sign geometry with the disc diameter as unit (the homography's sign plane).
_SHAPE = sign_shape("1111", 1.0)
_PART_NAMES: tuple[str, ...] = ("center", "direction", "slot1", "slot2", "slot3", "slot4")
_PART_QUADS = np.stack([_SHAPE.white_parts[n] for n in _PART_NAMES])  # (6, 4, 2)
_PART_CENTRES = _PART_QUADS.mean(axis=1)  # (6, 2)
_SLOT_RADIUS = float(np.hypot(*_PART_CENTRES[1]))  # 0.3 diameters
_SLOT_ANGLES = np.array([slot_angle_rad(k) for k in range(N_BITS + 1)])
_LOCATION_SIDE = float(_PART_QUADS[0, 1, 0] - _PART_QUADS[0, 0, 0])


def _sample_points() -> np.ndarray:
    """Sign-plane points sampled for verification (diameter units), in blocks.

    * per slot position k (0..4): a tangential line of 5 points across the
      slot centre (offsets -0.1..0.1 diameters: wider than the directional
      rectangle, about as wide as a coded one);
    * the directional rectangle's length: 2 points along it;
    * black references between the slots, inside, on and outside the ring;
    * the location square: its centre and 4 points halfway to its corners.
    """
    pts = []
    for ang in _SLOT_ANGLES:
        radial = np.array([math.cos(ang), math.sin(ang)])
        tangential = np.array([math.sin(ang), -math.cos(ang)])
        for o in _OFFSETS:
            pts.append(_SLOT_RADIUS * radial + o * tangential)
    up = np.array([0.0, 1.0])
    pts += [(_SLOT_RADIUS - 0.07) * up, (_SLOT_RADIUS + 0.07) * up]
    for ang in _SLOT_ANGLES - math.radians(36.0):
        radial = np.array([math.cos(ang), math.sin(ang)])
        pts += [0.41 * radial, 0.3 * radial, 0.19 * radial]
    h = _LOCATION_SIDE / 4
    pts += [[0.0, 0.0], [-h, -h], [h, -h], [h, h], [-h, h]]
    # Radially inside and outside every coded slot: black whatever the code,
    # which pins the scale (a hypothesis at the wrong size puts white here).
    for ang in _SLOT_ANGLES[1:]:
        radial = np.array([math.cos(ang), math.sin(ang)])
        pts += [0.15 * radial, 0.45 * radial]
    # Just outside the four edges of every coded slot (two points per edge):
    # black around a white rectangle, lit too when a glare spot fakes one.
    half_t, half_r = _CODED_HALF
    for ang in _SLOT_ANGLES[1:]:
        radial = np.array([math.cos(ang), math.sin(ang)])
        tangential = np.array([math.sin(ang), -math.cos(ang)])
        c = _SLOT_RADIUS * radial
        for s in (-1.0, 1.0):
            for o in (-0.5, 0.5):
                pts.append(c + s * (half_t + _EDGE_GAP) * tangential + o * half_r * radial)
                pts.append(c + s * (half_r + _EDGE_GAP) * radial + o * half_t * tangential)
    # Along the long edges of every coded slot, off its centre line: a black
    # slot is the disc's black there too, where dirt or a bar laid along a
    # white slot leaves the slot's white rim showing.
    for ang in _SLOT_ANGLES[1:]:
        radial = np.array([math.cos(ang), math.sin(ang)])
        tangential = np.array([math.sin(ang), -math.cos(ang)])
        c = _SLOT_RADIUS * radial
        for r in _INNER_RADIAL:
            for o in (-0.06, 0.0, 0.06):
                pts.append(c + r * radial + o * tangential)
    return np.asarray(pts)


_OFFSETS = np.array([-0.1, -0.05, 0.0, 0.05, 0.1])
# A coded slot's half sides (tangential, radial) [diameters], and how far
# outside its edges the edge samples lie.
_CODED_HALF = (0.105, 0.08)
_EDGE_GAP = 0.05
_N_EDGE = 8
_EDGE_CONTRAST = 0.5
_INNER_RADIAL = (-0.09, -0.075, 0.075, 0.09)
_N_INNER = 3 * len(_INNER_RADIAL)
_N_OFFSETS = len(_OFFSETS)
_N_SLOT_SAMPLES = (N_BITS + 1) * _N_OFFSETS
_SAMPLES = _sample_points()
_S_DIR_LEN = slice(_N_SLOT_SAMPLES, _N_SLOT_SAMPLES + 2)
_S_BLACK = slice(_N_SLOT_SAMPLES + 2, _N_SLOT_SAMPLES + 2 + 15)
_S_LOC = slice(_N_SLOT_SAMPLES + 17, _N_SLOT_SAMPLES + 22)
_S_AROUND = slice(_N_SLOT_SAMPLES + 22, _N_SLOT_SAMPLES + 30)
_EDGE_STARTS = tuple(range(_N_SLOT_SAMPLES + 30, _N_SLOT_SAMPLES + 30 + N_BITS * _N_EDGE, _N_EDGE))
_INNER_STARTS = tuple(
    range(_EDGE_STARTS[-1] + _N_EDGE, _EDGE_STARTS[-1] + _N_EDGE + N_BITS * _N_INNER, _N_INNER)
)
_SLOT_STARTS = tuple(range(0, _N_SLOT_SAMPLES, _N_OFFSETS))
# Disc rim points that must lie inside the crop for a reading to count.
_RIM = 0.46 * np.stack(
    [
        np.cos(np.linspace(0, 2 * np.pi, 24, endpoint=False)),
        np.sin(np.linspace(0, 2 * np.pi, 24, endpoint=False)),
    ],
    axis=1,
)
# Expected (centre, mean across) of a slot, as fractions black -> white.
_UNIT_STEPS = np.array([[0.0, 0.0], [0.01, 0.0], [0.0, 0.01]])


def _grow_directions() -> np.ndarray:
    """(6, 4, 2) per-corner offsets that grow each part by one unit on every side."""
    out = np.zeros_like(_PART_QUADS)
    for p, quad in enumerate(_PART_QUADS):
        d = quad - quad.mean(axis=0)
        ax = (d[1] - d[0]) / np.linalg.norm(d[1] - d[0])
        ay = (d[3] - d[0]) / np.linalg.norm(d[3] - d[0])
        # Corner order follows the part's own edges; orient by the corner offsets.
        for k in range(4):
            sx = 1.0 if d[k] @ ax > 0 else -1.0
            sy = 1.0 if d[k] @ ay > 0 else -1.0
            out[p, k] = sx * ax + sy * ay
    return out


_PART_GROW = _grow_directions()
# Half the smaller side of each part [diameters], for "does a band reach it".
_PART_HALF = np.array(
    [0.5 * min(np.linalg.norm(q[1] - q[0]), np.linalg.norm(q[3] - q[0])) for q in _PART_QUADS]
)
# The outer sampling ring of ``occlusion.dark_bands`` must lie in the crop.
_OUTER_RING = 0.61 * _RIM / 0.46
# Least aspect ratio of the directional rectangle's hole (3.1 on the sign,
# less once blur rounds a small one).
_MIN_DIRECTION_ASPECT = 1.5
# Largest distance of the fitted disc's centre from a disc-like region's
# centroid, as a fraction of the disc's major axis.
_MAX_CENTRE_SHIFT = 0.1
# Most erased slots a reading may keep (more is a wrong geometry, not an occluder).
_MAX_ERASED = 2
# A white part whose interior is at least this white (least sample) shows
# nothing in front of it.
_CLEAN_INSIDE = 0.7
# Samples this close to a band's edge [diameters] count as under it (blur).
_SAMPLE_BAND_MARGIN = 0.03
# A black-read slot is erased when its centre lies under a band (this close
# to its edge [diameters]). A band that only reaches the slot's edge (the
# part's half side, 0.08, was used) leaves white in its reading samples, so
# a white slot under it reads erased by its gray levels, never 0: that reach
# refused signs for nothing (seeds 2017 and 99, 1,000 per condition: the
# same wrong codes; one slot covered / 1 slot unique 42 -> 50 %, unoccluded
# photographs 94.5 -> 94.9 %, faded 81.5 -> 82.6 %).
_ERASE_REACH = 0.0
# Margin around the explained parts when looking for unexplained white:
# at least this many diameters, and at least _BLUR_PX pixels.
_UNEXPLAINED_GROW = 0.035
_BLUR_PX = 2.0


def _code_parts(code: str) -> tuple[list[int], tuple[str, ...], np.ndarray]:
    """White parts of ``code``: part indices, keypoint names, sign-plane centres (P, 2)."""
    names = ("center", "direction") + tuple(
        f"slot{s}" for s in range(1, N_BITS + 1) if code[s - 1] == "1"
    )
    idx = [_PART_NAMES.index(n) for n in names]
    return idx, names, _PART_CENTRES[idx]


_CODE_PARTS = {code: _code_parts(code) for code in ALL_CODES}


def _translated(h: np.ndarray, shift_px) -> np.ndarray:
    """(3, 3) ``h`` followed by a shift of (du, dv) pixels."""
    du, dv = shift_px
    return np.array([[1.0, 0.0, du], [0.0, 1.0, dv], [0.0, 0.0, 1.0]]) @ h


def _project(h: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(N, 2) sign-plane points through (3, 3) ``h`` to pixels."""
    return cv2.perspectiveTransform(xy.reshape(-1, 1, 2), h).reshape(-1, 2)


_CLASS_BLACK = (0.0, 0.0)
_CLASS_DIRECTION = (1.0, 0.4)
_CLASS_CODED = (1.0, 0.85)


@dataclass(frozen=True)
class DecoderSettings:
    """Decoder tuning.

    Attributes:
        min_sign_px: smallest disc diameter read [px]; smaller is ``no_sign``.
        max_regions: dark regions tried, largest first.
        max_location_candidates: holes tried as location rectangle per region.
        max_direction_candidates: holes tried as directional rectangle.
        min_contrast: least white - black gray-level difference.
        min_bit_margin: least normalised margin of each slot's class decision.
        min_direction_margin: least cost margin between the best and the
            second-best rotation of the slot pattern.
        min_axis_ratio: least minor/major axis ratio of the disc's image
            (0.4: about 66 degrees off the sign's normal).
        min_fill: least disc diameter as a fraction of the crop's larger side.
        max_black_frac: a black slot's samples stay below this white fraction.
        black_slot_level: the least white fraction of a black slot's middle
            samples stays below this: a dark member over a white slot reads
            a flat gray just above the print's black (0.08-0.1 seen), which
            must erase the slot rather than read 0. The least, not the mean:
            a smudge of dirt over part of a black slot raises some of them,
            a member hiding a white slot all of them.
        min_white_frac: a white slot's samples stay above this white fraction.
        edge_margin_px: the sign's rim must stay this far inside the crop [px].
        thresholds: binarisations tried in turn until one decodes: "mean"
            (the paper's), then fallbacks "otsu", "high", "adaptive", "open".
        perspective_correction: fit the homography to the rectangles' image
            centroids (True) rather than treating centroids as images of the
            rectangles' centres (False, biased under perspective; kept to
            measure that bias).
        region_margin: ``decode_region`` grows the box by this fraction per side.
        recrop_cut_rim: when the crop cut the fitted disc's rim
            (``cut_by_edge``), the disc's centre lies in the box and the
            disc inside the image,
            ``decode_region`` decodes once more on a crop around the disc
            (its bounding box grown by ``region_margin``); the reading goes
            through every check of the first, and counts only when the
            disc it reads is centred in the box too. A detector region off the
            sign by a third of its size (a wide lens's edge, where the
            cascade's windows sit off the sign) then reads. A disc that the
            image's border cuts stays refused.
        search_bars: also search every straight line through a black-read
            slot for a bar as black as the print beyond one rim crossing
            (``occlusion.straight_bars``), erasing the slot. Off: on the
            independent scenes (1,000 per condition, seeds 2017 / 99) it
            takes the wrong codes 7 -> 4 / 9 -> 7 of 10,000 but refuses one
            unoccluded sign more in jpeg 70 and mixed (2017) and in photo,
            gain and faded (99): dark clutter or a print-black bar behind
            the disc looks the same,
            and decoding takes about twice the CPU (median 2.3 -> 4.9 ms per
            photo-background crop).
    """

    min_sign_px: float = 10.0
    max_regions: int = 3
    max_location_candidates: int = 2
    max_direction_candidates: int = 3
    min_contrast: float = 25.0
    min_bit_margin: float = 0.12
    min_direction_margin: float = 0.15
    min_axis_ratio: float = 0.4
    min_fill: float = 0.25
    max_black_frac: float = 0.25
    black_slot_level: float = 0.07
    min_white_frac: float = 0.55
    edge_margin_px: float = 0.0
    thresholds: tuple[str, ...] = ("mean", "otsu", "high", "adaptive", "open")
    perspective_correction: bool = True
    region_margin: float = 0.25
    search_bars: bool = False
    recrop_cut_rim: bool = True


@dataclass(frozen=True)
class DecodeResult:
    """The decoder's reading of one crop.

    Attributes:
        code: the decoded code "0000".."1111", or None.
        reason: ``DecodeReason.OK`` when ``code`` is set, else why not; a
            ``StrEnum``, so it compares equal to (and is written as) its
            lowercase token.
        keypoints_px: keypoint name -> (u, v) in the pixels of the image passed
            in (centres at integers): ``center``, ``direction`` and each white
            ``slotK``, less the covered parts and those a band beside them may
            pull (``_Occlusion.unreported``). Empty when there is no code.
        ellipse: the disc's image ((cx, cy), (major, minor), angle_deg), full
            axes, cv2.RotatedRect angle convention; None when unknown. A
            ``cut_by_edge`` refusal carries the disc the refused hypothesis
            fitted (its rim partly outside the crop), an ``occluded`` or
            ``code_not_in_map`` one the disc of the sign it read (when the
            refusal came after the fit).
        quality: confidence in [0, 1] (bit margins and fit residual).
        sigma_px: estimated standard deviation of each keypoint coordinate
            [px], for the estimator's measurement noise.
        image_H_sign: (3, 3) homography from the sign plane, in units of the
            disc diameter (x right, y up, origin at the centre), to image
            pixels; None when there is no code.
        residual_px: RMS residual of the homography fit [px]; NaN when the
            fit is exact (four or fewer rectangles).
        erased_slots: coded slots (1..4) whose bit the image does not show
            (an occluder, a gray slot); the code is the one code of the map
            that fits the other slots.
        keypoint_sigma_px: keypoint name -> (sigma_u, sigma_v) [px], the
            calibrated standard deviation of each coordinate (see
            ``keypoint_sigmas``); ``sigma_px`` is their geometric mean.
        sigma_inputs: what ``keypoint_sigmas`` was given (for calibration).
        unknown_code: a ``code_not_in_map`` refusal's reading: the code the
            crop shows, verified as any accepted code is, that the map lacks
            (``code`` stays None); None otherwise. For telling a user which
            sign the map misses.
    """

    code: str | None
    reason: DecodeReason
    keypoints_px: dict[str, tuple[float, float]] = field(default_factory=dict)
    ellipse: Ellipse | None = None
    quality: float = 0.0
    sigma_px: float = float("inf")
    image_H_sign: np.ndarray | None = None
    residual_px: float = float("nan")
    erased_slots: tuple[int, ...] = ()
    keypoint_sigma_px: dict[str, tuple[float, float]] = field(default_factory=dict)
    sigma_inputs: SigmaInputs | None = None
    unknown_code: str | None = None

    @property
    def ok(self) -> bool:
        return self.code is not None


@dataclass
class _Hole:
    centroid: tuple[float, float]  # px
    area: float  # px^2 (contour polygon)
    cov: tuple[float, float, float]  # second central moments / area (uu, uv, vv) [px^2]
    aspect: float


def _fail(
    reason: DecodeReason,
    quality: float = 0.0,
    ellipse: Ellipse | None = None,
    unknown_code: str | None = None,
) -> DecodeResult:
    return DecodeResult(
        code=None, reason=reason, quality=quality, ellipse=ellipse, unknown_code=unknown_code
    )


def _moments(contour: np.ndarray) -> tuple[float, float, float, tuple[float, float, float]] | None:
    """(area, cu, cv, (uu, uv, vv)) of a contour polygon, in plain floats."""
    m = cv2.moments(contour)
    a = m["m00"]
    if a <= 0:
        return None
    return a, m["m10"] / a, m["m01"] / a, (m["mu20"] / a, m["mu11"] / a, m["mu02"] / a)


def _eig2(a: float, b: float, c: float) -> tuple[float, float]:
    """Eigenvalues (small, large) of the symmetric 2x2 matrix [[a, b], [b, c]]."""
    m = 0.5 * (a + c)
    r = math.sqrt(max(0.25 * (a - c) ** 2 + b * b, 0.0))
    return m - r, m + r


def _hole(contour: np.ndarray, area: float) -> _Hole:
    mo = _moments(contour) if area > 0 else None
    if mo is None:
        # A one-pixel-wide hole traces to a zero-area polygon: use its points.
        pts = contour.reshape(-1, 2).astype(float)
        c = pts.mean(axis=0)
        d = pts - c
        m = d.T @ d / len(pts)
        cov = (float(m[0, 0]), float(m[0, 1]), float(m[1, 1]))
        area = float(len(pts))
        c = (float(c[0]), float(c[1]))
    else:
        area, cu, cv, cov = mo
        c = (cu, cv)
    # A pixel's own extent.
    cov = (cov[0] + 1.0 / 12.0, cov[1], cov[2] + 1.0 / 12.0)
    lo, hi = _eig2(*cov)
    aspect = math.sqrt(hi / max(lo, 1e-9))
    return _Hole(centroid=c, area=area, cov=cov, aspect=aspect)


def _whitener(cov: tuple[float, float, float], variance_per_unit: float) -> np.ndarray | None:
    """(2, 2) map from image offsets [px] to sign-plane units (y up), up to a rotation.

    ``cov`` (uu, uv, vv) is the image second-moment matrix of a shape whose
    sign-plane second moments are ``variance_per_unit * I`` (a disc or a
    square). The inverse square root undoes the affine part of the view; the
    v-axis flip keeps the result a proper rotation away from the sign frame.
    """
    # Flip v (down) to y (up): the off-diagonal term changes sign.
    a, b, c = cov[0], -cov[1], cov[2]
    det = a * c - b * b
    if det <= 1e-12 or a <= 0:
        return None
    # Inverse square root of [[a, b], [b, c]] in closed form.
    sq = math.sqrt(det)
    t = math.sqrt(a + c + 2 * sq)
    k = math.sqrt(variance_per_unit) / (sq * t)
    return np.array([[k * (c + sq), k * b], [-k * b, -k * (a + sq)]])


def _sample(gray: np.ndarray, uv: np.ndarray) -> list[float]:
    """Bilinear gray levels of ``gray`` at (N, 2) pixel positions ``uv``, as floats."""
    m = uv.astype(np.float32).reshape(1, -1, 2)
    out = cv2.remap(gray, m, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(-1).tolist()


@dataclass(frozen=True)
class _Reading:
    """Gray-level reading of the five slot positions under one homography.

    Attributes:
        code: the four bits ("x" where erased), or None when the reading
            fails (``reason``).
        margin: the smaller of the bit and direction decision margins.
        black, white: the disc's and the location square's gray levels.
        spread: interquartile spread of the disc's black samples, as a
            fraction of white - black (noise, JPEG, dirt, glare).
        glow: (coefficients, floor [gray], contrast [gray]) of the smooth
            glow taken off the face before reading (``_without_glow``), or
            None when the plain gray levels were read.
    """

    code: str | None
    reason: DecodeReason
    margin: float
    black: float
    white: float
    spread: float = 0.0
    glow: tuple | None = None


# Why the slot reading works on Python floats rather than numpy arrays: it
# handles about 60 scalars per hypothesis, where numpy's per-call overhead
# dominates. Written with numpy it made the decoder's share of a tracked
# 1080p frame 9.0 -> 13.6 ms (scripts/bench_frontend.py --quick, median).


def _levels(vals: list[float]) -> tuple[float, float]:
    """The disc's black and the location square's white gray level from the samples."""
    # A low quantile, not the median: light leaking onto a few black samples
    # must show up as a spread, not raise the black level.
    black = sorted(vals[_S_BLACK])[3]
    white = sorted(vals[_S_LOC])[len(vals[_S_LOC]) // 2]
    return black, white


# Samples black whatever the code (between the slots, radially beside and
# just outside every coded slot): the glow model is fitted to these.
_BLACK_EVERYWHERE = np.array(
    list(range(*_S_BLACK.indices(len(_SAMPLES))))
    + list(range(*_S_AROUND.indices(len(_SAMPLES))))
    + [i for s in _EDGE_STARTS for i in range(s, s + _N_EDGE)]
)


def _poly_design(xy: np.ndarray) -> np.ndarray:
    """(N, 10) monomials of (N, 2) sign-plane points up to the third degree."""
    x, y = xy[:, 0], xy[:, 1]
    return np.stack([x**i * y ** (d - i) for d in range(4) for i in range(d + 1)], axis=1)


_GLOW_DESIGN = _poly_design(_SAMPLES)
# A glow is taken off only when it lifts the face by this much at its peak
# (fraction of the contrast), its cubic fits every black-everywhere
# sample this well, and at most this share of them are outliers.
_GLOW_MIN = 0.1
_GLOW_MAX_RESIDUAL = 0.16
_GLOW_MAX_OUTLIERS = 0.1
# Least ratio of the glow's two curvatures (both downward).
_GLOW_ROUND = 0.3
# Gray levels at or above this are saturated (the glow's true level unknown).
_SATURATED = 250.0

# Finite-difference step [diameters] of the glow's curvature at its peak.
_HESSIAN_STEP = 0.02
_HESSIAN_OFFSETS = _HESSIAN_STEP * np.array(
    [[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [-1, -1], [1, -1], [-1, 1]], float
)


def _hessian(coef: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(2, 2) second derivatives of the polynomial ``coef`` at sign-plane point ``xy``."""
    f = _poly_design(xy[None, :] + _HESSIAN_OFFSETS) @ coef
    h2 = _HESSIAN_STEP**2
    fxx = (f[1] + f[2] - 2 * f[0]) / h2
    fyy = (f[3] + f[4] - 2 * f[0]) / h2
    fxy = (f[5] + f[6] - f[7] - f[8]) / (4 * h2)
    return np.array([[fxx, fxy], [fxy, fyy]])


def _without_glow(vals: list[float]) -> tuple[list[float], np.ndarray, float] | None:
    """The samples with a smooth glow on the face taken off, the glow's
    coefficients (``_poly_design``) and its floor [gray], or None.

    Specular glare adds a smooth glow over the face (it lifts the black
    slots near its peak towards gray). A cubic in the sign plane is
    fitted to the samples that are black whatever the code and subtracted
    from every sample. None when there is no glow worth taking off, or when
    the black samples do not follow one smooth surface, or it is not a round
    bump at its peak (a bar lighter than the print is a straight band with
    edges, flat along itself). A saturated
    sample stays as it is where a black one could not have saturated under
    the glow, and is made gray (erased) where it could.
    """
    v = np.asarray(vals, float)
    a = _GLOW_DESIGN[_BLACK_EVERYWHERE]
    b = v[_BLACK_EVERYWHERE]
    keep = b < _SATURATED
    if keep.sum() < 0.9 * len(b):
        return None
    coef = np.linalg.lstsq(a[keep], b[keep], rcond=None)[0]
    resid = b - a @ coef
    scale = max(1.4826 * float(np.median(np.abs(resid[keep]))), 1.0)
    keep &= np.abs(resid) <= 3.0 * scale
    coef = np.linalg.lstsq(a[keep], b[keep], rcond=None)[0]
    fit_black = a @ coef
    floor = float(fit_black.min())
    white = float(np.median(v[_S_LOC]))
    contrast = white - floor
    if contrast <= 0:
        return None
    resid = (b - fit_black) / contrast
    if (~keep).mean() > _GLOW_MAX_OUTLIERS or np.abs(resid).max() > _GLOW_MAX_RESIDUAL:
        return None
    glow = np.maximum(_GLOW_DESIGN @ coef - floor, 0.0)
    if glow.max() < _GLOW_MIN * contrast:
        return None
    # A glow is a round bump (its curvature the same way in every direction,
    # up to the view's foreshortening); a straight band is flat along itself.
    curv = np.linalg.eigvalsh(_hessian(coef, _SAMPLES[int(np.argmax(glow))]))
    if curv[1] >= 0 or curv[1] > _GLOW_ROUND * curv[0]:
        return None
    return _glow_off(v, glow, floor, contrast).tolist(), coef, floor


def _glow_off(v: np.ndarray, glow: np.ndarray, floor: float, contrast: float) -> np.ndarray:
    """Gray values ``v`` with ``glow`` taken off (``_without_glow``'s fit, above its
    ``floor``): a saturated value stays as it is where a black one under that glow
    could not have saturated, and is made mid-gray (erased) where it could."""
    flat = v - glow
    saturated = v >= _SATURATED
    flat[saturated] = v[saturated]
    flat[saturated & (floor + glow + 0.5 * contrast >= _SATURATED)] = floor + 0.5 * contrast
    return flat


def _flattened(gray: np.ndarray, image_H_sign: np.ndarray, glow: tuple) -> np.ndarray:
    """(H, W) uint8 ``gray`` with the face's glow (``_Reading.glow``) taken off
    inside the disc (``_glow_off``)."""
    coef, floor, contrast = glow
    h, w = gray.shape
    _, sign_H_image = cv2.invert(image_H_sign)
    vv, uu = np.mgrid[0:h, 0:w]
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)
    xy = _project(sign_H_image, uv)
    on_face = np.hypot(xy[:, 0], xy[:, 1]) < 0.5
    v = gray.reshape(-1).astype(float)
    glow_px = np.where(on_face, np.maximum(_poly_design(xy) @ coef - floor, 0.0), 0.0)
    flat = _glow_off(v, glow_px, floor, contrast)
    return np.clip(np.round(flat), 0, 255).astype(np.uint8).reshape(h, w)


def _face_is_sign_like(frac: list[float], hidden: frozenset[int] = frozenset()) -> bool:
    """The disc between the parts is dark and the location square white throughout.

    ``frac``: white fractions of all samples; ``hidden``: indices of samples
    that an occluder in front covers, left out. A random dark blob with two
    bright holes is not a sign.
    """

    def seen(part: slice) -> list[float]:
        if not hidden:
            return frac[part]
        return [frac[i] for i in range(*part.indices(len(frac))) if i not in hidden]

    blacks, around = sorted(seen(_S_BLACK)), sorted(seen(_S_AROUND))
    if len(blacks) < 8 or len(around) < 4:
        return False
    return (
        blacks[-2] <= 0.3  # the second brightest
        and min(frac[_S_LOC]) >= 0.6
        and min(frac[_S_DIR_LEN]) >= 0.45
        and around[-2] <= 0.5
    )


def _hidden_samples(
    gray: np.ndarray, image_H_sign: np.ndarray, black: float, white: float
) -> frozenset[int]:
    """Indices of ``_SAMPLES`` under a dark band in front of the face."""
    h, w = gray.shape
    inside = _inside(_project(image_H_sign, _OUTER_RING), w, h, 0.0)
    bands = occlusion.dark_bands(gray, image_H_sign, black, white, inside, _PART_CENTRES[:2])
    # A bar in front lighter than the print (it brightens the black references).
    bands += occlusion.off_black_bands(gray, image_H_sign, black, white, _SAMPLES[_S_BLACK])
    under = occlusion.crossed(bands, _SAMPLES, np.full(len(_SAMPLES), _SAMPLE_BAND_MARGIN))
    return frozenset(np.flatnonzero(under).tolist())


def _class_cost(row: list[float], cls: tuple[float, float]) -> float:
    """Squared distance of a slot's (centre, mean across) white fractions to a class."""
    centre = row[_N_OFFSETS // 2]
    mean = sum(row) / _N_OFFSETS
    return (centre - cls[0]) ** 2 + (mean - cls[1]) ** 2


def _slot_is_clear(row: list[float], bit: bool, settings: DecoderSettings) -> bool:
    """A coded slot is clearly white or clearly black (``row``: white fractions across)."""
    lo, hi = settings.max_black_frac, settings.min_white_frac
    centre = row[_N_OFFSETS // 2]
    if bit:
        return centre >= hi and min(row[1:-1]) >= hi - 0.1 and sum(row) / _N_OFFSETS >= hi
    # The least of the middle samples: a member hiding a white slot raises
    # them all, a smudge of dirt over part of a black slot only some.
    middle = min(row[1:-1])
    return centre <= lo and max(row) <= lo + 0.1 and middle <= settings.black_slot_level


def _has_edges(frac: list[float], row: list[float], k: int) -> bool:
    """Coded slot ``k`` (1..4), read white, is a white rectangle with dark surroundings.

    Its mean white fraction across (``row``) stands at least ``_EDGE_CONTRAST``
    above the median just outside its edges. A specular spot on the black
    face that the threshold turns into a hole where a slot should be is lit
    around as well (rows 0.62-0.64 white over edges 0.2-0.34 on the
    independent scenes' glare, against a contrast >= 0.65 for 99 % of real
    white slots there, blur and faded faces included).
    """
    start = _EDGE_STARTS[k - 1]
    edges = sorted(frac[start : start + _N_EDGE])
    median = 0.5 * (edges[_N_EDGE // 2 - 1] + edges[_N_EDGE // 2])
    return sum(row) / _N_OFFSETS - median >= _EDGE_CONTRAST


def _black_inside(frac: list[float], k: int, settings: DecoderSettings) -> bool:
    """Coded slot ``k`` (1..4), read black, is black along its long edges too
    (dirt or a bar laid along a white slot darkens its middle only)."""
    start = _INNER_STARTS[k - 1]
    return max(frac[start : start + _N_INNER]) <= settings.max_black_frac + 0.1


def _read_slots(gray: np.ndarray, image_H_sign: np.ndarray, settings: DecoderSettings) -> _Reading:
    """Classify the five slot positions from gray levels under ``image_H_sign``.

    Each slot is black, a coded (wide) white rectangle, or the thin directional
    one. The pattern must hold exactly one directional rectangle, and that at
    slot position 0 (where the contours put it), with a clear margin. Each
    coded slot must be clearly one thing: a half-white slot (dirt, a cable,
    heavy blur, a wrong geometry) is refused rather than guessed.

    A reading that fails or erases a slot is tried again on the samples with
    a smooth glow taken off (``_without_glow``: specular glare lifts the
    black slots near it to gray); the second reading is kept only when it
    erases fewer slots and agrees with the first on every slot both read.
    """
    vals = _sample(gray, _project(image_H_sign, _SAMPLES))
    first = _classify_slots(gray, image_H_sign, vals, settings)
    if first.code is not None and "x" not in first.code:
        return first
    glow = _without_glow(vals)
    if glow is None:
        return first
    second = _classify_slots(gray, image_H_sign, glow[0], settings)
    if second.code is None:
        return first
    if first.code is not None and not (
        second.code.count("x") < first.code.count("x") and _consistent(first.code, second.code)
    ):
        return first
    return replace(second, glow=(glow[1], glow[2], second.white - second.black))


def _classify_slots(
    gray: np.ndarray, image_H_sign: np.ndarray, vals: list[float], settings: DecoderSettings
) -> _Reading:
    """``_read_slots`` on the gray levels ``vals`` of ``_SAMPLES``."""
    black, white = _levels(vals)
    contrast = white - black
    if contrast < settings.min_contrast:
        return _Reading(None, DecodeReason.LOW_CONTRAST, 0.0, black, white)
    frac = [(v - black) / contrast for v in vals]
    if not _face_is_sign_like(frac):
        # A bar in front may brighten the black references: leave out what it
        # covers (only worth looking when the white parts are where they belong).
        if min(frac[_S_LOC]) < 0.6 or min(frac[_S_DIR_LEN]) < 0.45:
            return _Reading(None, DecodeReason.INCONSISTENT, 0.0, black, white)
        hidden = _hidden_samples(gray, image_H_sign, black, white)
        if not hidden or not _face_is_sign_like(frac, hidden):
            return _Reading(None, DecodeReason.INCONSISTENT, 0.0, black, white)
    rows = [frac[k : k + _N_OFFSETS] for k in _SLOT_STARTS]
    cost_black = [_class_cost(r, _CLASS_BLACK) for r in rows]
    cost_dir = [_class_cost(r, _CLASS_DIRECTION) for r in rows]
    cost_coded = [_class_cost(r, _CLASS_CODED) for r in rows]
    best_bit = [min(b, c) for b, c in zip(cost_black, cost_coded, strict=True)]
    # The pattern's cost with the directional rectangle at each position.
    total = sum(best_bit)
    rotation_cost = [d + total - b for d, b in zip(cost_dir, best_bit, strict=True)]
    order = sorted(range(N_BITS + 1), key=rotation_cost.__getitem__)
    direction_margin = rotation_cost[order[1]] - rotation_cost[order[0]]
    if order[0] != 0 or direction_margin < settings.min_direction_margin:
        return _Reading(None, DecodeReason.AMBIGUOUS_DIRECTION, direction_margin, black, white)
    lo, hi = settings.max_black_frac, settings.min_white_frac
    mid = _N_OFFSETS // 2
    blacks = sorted(frac[_S_BLACK])
    spread = blacks[-4] - blacks[3]
    if not (rows[0][mid] >= hi - 0.1 and rows[0][0] <= lo + 0.1 and rows[0][-1] <= lo + 0.1):
        return _Reading(None, DecodeReason.INCONSISTENT, direction_margin, black, white)
    # A slot that is neither clearly white nor clearly black is erased: its bit
    # is unknown, not guessed.
    pattern, margins = [], [direction_margin]
    for k in range(1, N_BITS + 1):
        bit = cost_coded[k] < cost_black[k]
        bit_margin = abs(cost_coded[k] - cost_black[k])
        clear = _slot_is_clear(rows[k], bit, settings) and (
            _has_edges(frac, rows[k], k) if bit else _black_inside(frac, k, settings)
        )
        if bit_margin < settings.min_bit_margin or not clear:
            pattern.append("x")
        else:
            pattern.append("1" if bit else "0")
            margins.append(bit_margin)
    if pattern.count("x") > _MAX_ERASED:
        return _Reading(None, DecodeReason.INCONSISTENT, min(margins), black, white)
    return _Reading("".join(pattern), DecodeReason.OK, min(margins), black, white, spread)


def _subpixel_centroids(
    gray: np.ndarray,
    image_H_sign: np.ndarray,
    parts: list[int],
    black: float,
    white: float,
    pad_px: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Gray-level centroids of white parts, each in a window around its prediction.

    The weight of a pixel is its white fraction (I - black) / (white - black)
    in [0, 1]: the covered area of an anti-aliased, blurred rectangle, whose
    centroid is the rectangle's area centroid as long as the window holds the
    whole blur (unlike a binary contour's, which moves with the threshold).
    The window is the predicted rectangle grown by ``pad_px``, at most
    halfway to its neighbours in the sign plane.

    Returns:
        (P, 2) centroids [px], (P,) boolean "measured" and (P,) white area
        (sum of white fractions) [px^2], NaN where not measured.
    """
    h, w = gray.shape
    n = len(parts)
    out = np.zeros((n, 2))
    white_area = np.full(n, np.nan)
    steps = _project(image_H_sign, _UNIT_STEPS)
    scale = math.sqrt(abs(np.linalg.det(steps[1:] - steps[0]))) / 0.01  # px per diameter
    grow = min(pad_px / max(scale, 1e-9), 0.035)
    _, _, flat_quads, _, flat_grow = _parts_geometry(parts)
    polys = _project(image_H_sign, flat_quads + grow * flat_grow).reshape(n, 4, 2)
    lo_l = np.floor(polys.min(axis=1)).tolist()
    hi_l = (np.ceil(polys.max(axis=1)) + 1).tolist()
    # (NaN compares false: invalid.)
    valid_l = [
        lo[0] >= 0 and lo[1] >= 0 and hi[0] <= w and hi[1] <= h
        for lo, hi in zip(lo_l, hi_l, strict=True)
    ]
    idx = [i for i in range(n) if valid_l[i]]
    valid = np.array(valid_l, dtype=bool)
    if not idx:
        return out, valid, white_area
    # One window over all parts, one label per part (the grown rectangles do
    # not overlap in the sign plane; a pixel on two rasterised borders goes
    # to the later part). The sums per part run over the part's own box, in
    # double precision (cv2.moments).
    boxes = [(int(lo_l[i][0]), int(lo_l[i][1]), int(hi_l[i][0]), int(hi_l[i][1])) for i in idx]
    x0 = min(bx[0] for bx in boxes)
    y0 = min(bx[1] for bx in boxes)
    x1 = max(bx[2] for bx in boxes)
    y1 = max(bx[3] for bx in boxes)
    labels = np.zeros((y1 - y0, x1 - x0), np.uint8)
    pts = np.round((polys - (x0, y0)) * 16).astype(np.int32)
    for i in idx:
        cv2.fillConvexPoly(labels, pts[i], i + 1, lineType=cv2.LINE_8, shift=4)
    wt = gray[y0:y1, x0:x1] - np.float32(black)
    wt *= np.float32(1.0 / max(white - black, 1e-6))
    np.clip(wt, 0.0, 1.0, out=wt)
    for i, (a0, b0, a1, b1) in zip(idx, boxes, strict=True):
        a0, b0, a1, b1 = a0 - x0, b0 - y0, a1 - x0, b1 - y0
        win = wt[b0:b1, a0:a1]
        m = cv2.moments(win * (labels[b0:b1, a0:a1] == i + 1))
        white_area[i] = m["m00"]
        if m["m00"] > 0:
            out[i, 0] = x0 + a0 + m["m10"] / m["m00"]
            out[i, 1] = y0 + b0 + m["m01"] / m["m00"]
        else:
            valid[i] = False
    return out, valid, white_area


def _fit_parts(
    parts: list[int],
    measured_px: np.ndarray,
    fallback: np.ndarray | None,
    passes: int = 2,
    want_residual: bool = True,
) -> tuple[np.ndarray | None, float]:
    """Homography with predicted rectangle centroids matching ``measured_px``.

    A rectangle's image centroid is not the image of its centre under a
    perspective map. Starting from a fit of the centres, each pass moves the
    targets by the centroid offset that the current homography predicts
    (exact, from the projected polygons) and refits; two passes converge to
    far below the noise since the offset is second order in the part size.

    Returns:
        (image_H_sign, rms residual [px]) or (None, nan).
    """
    src, quads, flat_quads, prepared, _ = _parts_geometry(parts)
    n = len(parts)
    if n >= 4:
        h = fit_homography(src, measured_px, prepared)
    elif n == 3:
        h = fit_affine(src, measured_px, prepared)
    else:
        h = fallback
    if h is None:
        return None, float("nan")
    if n >= 4:
        for _ in range(passes):
            proj_quads = _project(h, flat_quads).reshape(quads.shape)
            offset = polygon_centroids(proj_quads) - _project(h, src)
            h_new = fit_homography(src, measured_px - offset, prepared)
            if h_new is None:
                break
            h = h_new
    if n <= 4 or not want_residual:
        return h, float("nan")  # an exact fit has no residual to report
    proj_quads = _project(h, flat_quads).reshape(quads.shape)
    resid = polygon_centroids(proj_quads) - measured_px
    rms = float(np.sqrt((resid**2).sum(axis=1).mean()))
    return h, rms


_PARTS_CACHE: dict[tuple[int, ...], tuple] = {}


def _parts_geometry(parts: list[int]) -> tuple:
    """Cached per part list: centres (P, 2), quads (P, 4, 2), quads (4P, 2),
    the prepared homography source (affine design matrix for fewer than four
    parts) and the corners' growth directions (4P, 2)."""
    key = tuple(parts)
    geo = _PARTS_CACHE.get(key)
    if geo is None:
        src = _PART_CENTRES[list(key)]
        quads = _PART_QUADS[list(key)]
        prepared = prepare_source(src) if len(key) >= 4 else affine_design(src)
        grow = _PART_GROW[list(key)].reshape(-1, 2)
        geo = (src, quads, np.ascontiguousarray(quads.reshape(-1, 2)), prepared, grow)
        _PARTS_CACHE[key] = geo
    return geo


def _affine_from_two(
    loc: np.ndarray, direction: np.ndarray, whitener: np.ndarray
) -> np.ndarray | None:
    """Affine image_H_sign from the location and directional centres and a whitener.

    ``whitener`` maps image offsets to sign units up to a rotation; the
    rotation (and a scale check) come from the directional rectangle.
    """
    q = whitener @ np.subtract(direction, loc)
    r = float(np.hypot(*q))
    if r <= 1e-9:
        return None
    # Rotate q onto +y (the directional rectangle's sign-plane direction).
    ang = math.atan2(q[1], q[0]) - math.pi / 2
    c, s = math.cos(-ang), math.sin(-ang)
    rot = np.array([[c, -s], [s, c]])
    m = (_SLOT_RADIUS / r) * rot @ whitener  # sign_from_img
    det = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    if abs(det) < 1e-12:
        return None
    img_from_sign = np.array([[m[1, 1], -m[0, 1]], [-m[1, 0], m[0, 0]]]) / det
    h = np.eye(3)
    h[:2, :2] = img_from_sign
    h[:2, 2] = loc
    return h


def _border_run(contour: np.ndarray, w: int, h: int) -> float:
    """Longest stretch [px] of ``contour`` along one side of the (w, h) crop.

    A disc cut by the crop's edge lies along it for a chord; a cable that
    joins the disc to the edge touches it for a few pixels only.
    """
    pts = contour.reshape(-1, 2)
    best = 0.0
    for axis, value in ((0, 0), (0, w - 1), (1, 0), (1, h - 1)):
        on = pts[pts[:, axis] == value]
        if len(on) >= 2:
            best = max(best, float(np.ptp(on[:, 1 - axis])))
    return best


def _inside(points: np.ndarray, w: int, h: int, margin: float) -> bool:
    (u0, v0) = points.min(axis=0).tolist()
    (u1, v1) = points.max(axis=0).tolist()
    return (
        u0 >= -0.5 + margin
        and u1 <= w - 0.5 - margin
        and v0 >= -0.5 + margin
        and v1 <= h - 0.5 - margin
    )


def _as_gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    if img.dtype != np.uint8:
        img = np.clip(img, 0, 255).astype(np.uint8)
    return img


def decode_roi(
    gray: np.ndarray,
    codes: Iterable[str] | None = None,
    settings: DecoderSettings = DecoderSettings(),
) -> DecodeResult:
    """Decode the one sign in a crop (paper §1.2, steps 2-7).

    Args:
        gray: (H, W) uint8 gray crop (a (H, W, 3) BGR crop is converted),
            the sign roughly centred and filling much of it.
        codes: the codes the map holds; any other decoded code is dropped
            (``code_not_in_map``). None accepts all 16.
        settings: tuning.

    Returns:
        The reading; keypoints in the crop's pixels.
    """
    g = _as_gray(gray)
    if g.ndim != 2 or min(g.shape) < settings.min_sign_px:
        return _fail(DecodeReason.NO_SIGN)
    allowed = None if codes is None else frozenset(codes)
    best: DecodeResult | None = None
    for kind in settings.thresholds:
        dark = _dark_mask(g, kind)
        if dark is None:
            continue
        if kind == "open":
            # Read gray levels with the thin dark line closed too.
            k = _open_kernel(g)
            res = _decode_at(cv2.morphologyEx(g, cv2.MORPH_CLOSE, k), dark, allowed, settings)
            res = _crossed_by_a_line(res)
        else:
            res = _decode_at(g, dark, allowed, settings)
        if res.code is not None or res.reason in _FINAL_REASONS:
            return res
        if best is None:
            # The first binarisation (the paper's) names the failure; the
            # fallbacks' noisier masks would only blur the reason.
            best = res
    return best if best is not None else _fail(DecodeReason.NO_SIGN)


def _crossed_by_a_line(res: DecodeResult) -> DecodeResult:
    """A reading through the "open" fallback: a thin line crosses the face.

    Its gray levels came from the closed crop, where the line no longer
    shows, so the occlusion evidence could not see it; the sigmas can.
    """
    if res.sigma_inputs is None:
        return res
    inputs = replace(res.sigma_inputs, crossed=True, closed=True)
    sigmas = keypoint_sigmas(inputs, res.keypoint_sigma_px)
    return replace(
        res,
        sigma_inputs=inputs,
        keypoint_sigma_px=sigmas,
        sigma_px=mean_sigma(sigmas),
    )


def _open_kernel(g: np.ndarray) -> np.ndarray:
    k = max(3, int(round(0.035 * min(g.shape))) | 1)
    return np.ones((k, k), np.uint8)


def _dark_mask(g: np.ndarray, kind: str) -> np.ndarray | None:
    """255 where the crop is dark (the disc), 0 where white, by threshold ``kind``.

    ``mean`` is the paper's step 3. The others are fallbacks for crops where
    the mean fails: Otsu's two-class split, a threshold halfway between the
    mean and the brightest pixels (blur merging nearby white parts), and a
    local mean (backgrounds darker than the disc's surroundings on one side).
    """
    if kind == "mean":
        _, dark = cv2.threshold(g, cv2.mean(g)[0], 255, cv2.THRESH_BINARY_INV)
    elif kind == "otsu":
        _, dark = cv2.threshold(g, 0, 255, cv2.THRESH_BINARY_INV + cv2.THRESH_OTSU)
    elif kind == "high":
        flat = g.reshape(-1)
        k = int(0.98 * (flat.size - 1))
        top = float(np.partition(flat, k)[k])
        _, dark = cv2.threshold(g, 0.5 * (cv2.mean(g)[0] + top), 255, cv2.THRESH_BINARY_INV)
    elif kind == "open":
        # A thin dark line across the face (a power line) splits white
        # rectangles into pieces; opening the dark mask with a kernel wider
        # than the line and narrower than the gaps between parts joins them.
        if min(g.shape) < 60:
            return None
        _, dark = cv2.threshold(g, cv2.mean(g)[0], 255, cv2.THRESH_BINARY_INV)
        dark = cv2.morphologyEx(dark, cv2.MORPH_OPEN, _open_kernel(g))
    elif kind == "adaptive":
        block = max(3, (min(g.shape) // 3) | 1)
        dark = cv2.adaptiveThreshold(
            g, 255, cv2.ADAPTIVE_THRESH_MEAN_C, cv2.THRESH_BINARY_INV, block, 0
        )
    else:
        raise ValueError(f"unknown threshold kind {kind!r}")
    return dark


def _decode_at(
    g: np.ndarray, dark: np.ndarray, allowed: frozenset[str] | None, settings: DecoderSettings
) -> DecodeResult:
    h, w = g.shape
    contours, hierarchy = cv2.findContours(dark, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_SIMPLE)
    if hierarchy is None:
        return _fail(DecodeReason.NO_SIGN)
    hier = hierarchy[0].tolist()
    regions = []
    for i in range(len(contours)):
        if hier[i][3] >= 0 or hier[i][2] < 0:
            continue
        area = cv2.contourArea(contours[i])
        if area < 0.5 * settings.min_sign_px**2:
            continue
        regions.append((area, i))
    if not regions:
        return _fail(DecodeReason.NO_SIGN)
    regions.sort(reverse=True)  # step 4: the largest extent first
    best_fail = _fail(DecodeReason.NO_LOCATION)
    crop_centre = np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    for _, i in regions[: settings.max_regions]:
        res = _decode_region_contour(g, contours, hier, i, crop_centre, allowed, settings)
        if res.code is not None or res.reason in _FINAL_REASONS:
            return res
        if _REASON_RANK[res.reason] > _REASON_RANK[best_fail.reason]:
            best_fail = res
    return best_fail


@dataclass(frozen=True)
class _Region:
    """One dark region of a crop and what every hypothesis about it shares.

    Attributes:
        gray: (H, W) uint8 crop.
        holes: the region's white holes.
        centroids_px: (N, 2) the holes' centroids [px].
        cut: whether the crop's edge cuts the region along a chord (lazy).
        rim_contour: the region's outer contour when it is disc-like, else None.
        disc_area_px: its area [px^2] when disc-like, else None.
        disc_centre_px: its centroid [px] when disc-like, else None.
        allowed: the map's codes, or None for all.
        settings: tuning.
    """

    gray: np.ndarray
    holes: list[_Hole]
    centroids_px: np.ndarray
    cut: _LazyFlag
    rim_contour: np.ndarray | None
    disc_area_px: float | None
    disc_centre_px: tuple[float, float] | None
    allowed: frozenset[str] | None
    settings: DecoderSettings


@dataclass(frozen=True)
class _Hypothesis:
    """Which holes are the location and directional rectangles.

    Attributes:
        location, direction: hole indices.
        rel: (N, 2) every hole's offset from the location hole, whitened
            (sign units up to a rotation).
        radius: (N,) the norms of ``rel``.
    """

    location: int
    direction: int
    rel: np.ndarray
    radius: np.ndarray


def _region_holes(contours, hier: list[list[int]], i: int, area: float) -> list[_Hole]:
    """The white holes of region ``i`` large enough to be parts of a sign."""
    holes: list[_Hole] = []
    child = hier[i][2]
    min_hole = max(1.0, 2e-3 * area)
    while child >= 0:
        hc = contours[child]
        # Polygon area of a hole's contour (its bordering dark pixels) is about
        # its pixel count minus half its perimeter; thin holes count by points.
        a = cv2.contourArea(hc)
        if max(a, 0.5 * len(hc)) >= min_hole:
            holes.append(_hole(hc, a))
        child = hier[child][0]
    return holes


def _is_disc_like(outer: np.ndarray, area: float, centre_px, cov, touches: bool) -> bool:
    """The region's area matches the ellipse of its moments and its radius is steady.

    Then its centroid and second moments describe the disc.
    """
    det = cov[0] * cov[2] - cov[1] * cov[1]
    if touches or det <= 0 or abs(area / (4 * math.pi * math.sqrt(det)) - 1.0) >= 0.12:
        return False
    # A square passes the area test too: require a steady radius once the
    # moments' ellipse is made a circle (a square's varies by +-20 %).
    wt = _whitener(cov, 1.0)
    if wt is None:
        return False
    # Vertices and edge midpoints: the contour is chain-compressed, so a
    # square is four corners.
    pts = outer.reshape(-1, 2).astype(float)
    prev = np.concatenate([pts[-1:], pts[:-1]])
    pts = np.concatenate([pts, 0.5 * (pts + prev)])
    rad = np.linalg.norm((pts - centre_px) @ wt.T, axis=1)
    return bool(rad.std() < 0.07 * rad.mean())


def _decode_region_contour(
    g: np.ndarray,
    contours,
    hier: list[list[int]],
    i: int,
    crop_centre: np.ndarray,
    allowed: frozenset[str] | None,
    settings: DecoderSettings,
) -> DecodeResult:
    h, w = g.shape
    outer = contours[i]
    mo = _moments(outer)
    if mo is None:
        return _fail(DecodeReason.NO_SIGN)
    area, ocu, ocv, outer_cov = mo
    holes = _region_holes(contours, hier, i, area)
    if len(holes) < 2:
        return _fail(DecodeReason.NO_LOCATION)
    x, y, bw, bh = cv2.boundingRect(outer)
    touches = x <= 0 or y <= 0 or x + bw >= w or y + bh >= h
    disc_like = _is_disc_like(outer, area, (ocu, ocv), outer_cov, touches)
    ref = np.array([ocu, ocv]) if disc_like else crop_centre
    # Cut by the crop's edge along a chord (not just a cable's width); only
    # asked when a hypothesis puts the rim outside.
    cut = _LazyFlag(
        lambda: touches and _border_run(outer, w, h) >= max(4.0, 0.15 * math.sqrt(area))
    )
    region = _Region(
        gray=g,
        holes=holes,
        centroids_px=np.array([hl.centroid for hl in holes]),
        cut=cut,
        rim_contour=outer if disc_like else None,
        disc_area_px=area if disc_like else None,
        disc_centre_px=(ocu, ocv) if disc_like else None,
        allowed=allowed,
        settings=settings,
    )
    # The disc's second moments: (R^2 / 4) I with R = 0.5 diameters; the same
    # for every location candidate.
    disc_whitener = _whitener(outer_cov, 0.0625) if disc_like else None
    # Step 5: the hole closest to the centre of the sign's extent.
    dist = np.linalg.norm(region.centroids_px - ref, axis=1)
    by_dist = np.argsort(dist, kind="stable").tolist()
    best = _fail(DecodeReason.NO_LOCATION)
    for li in by_dist[: settings.max_location_candidates]:
        # The disc's whitener, else the location square's (side^2 / 12 I).
        whitener = disc_whitener
        if not disc_like:
            whitener = _whitener(holes[li].cov, _LOCATION_SIDE**2 / 12.0)
        if whitener is None:
            continue
        res = _try_location(region, li, whitener)
        if res.code is not None or res.reason in _FINAL_REASONS:
            return res
        if _REASON_RANK[res.reason] > _REASON_RANK[best.reason]:
            best = res
    return best


def _try_location(region: _Region, li: int, whitener: np.ndarray) -> DecodeResult:
    """Try hole ``li`` as the location rectangle with the ring's directional candidates."""
    holes = region.holes
    rel = (region.centroids_px - region.centroids_px[li]) @ whitener.T
    radius = np.linalg.norm(rel, axis=1)
    ring = [k for k in range(len(holes)) if k != li and _RING_MIN < radius[k] < _RING_MAX]
    best = _fail(DecodeReason.NO_LOCATION)
    # Step 6: smallest area and largest aspect ratio.
    ring.sort(key=lambda k: -holes[k].aspect / holes[k].area)
    for di in ring[: region.settings.max_direction_candidates]:
        # Step 6's "largest aspect ratio", as a condition: the thin directional
        # rectangle (0.08 x 0.25 diameters) is more elongated than the square.
        if holes[di].aspect < max(_MIN_DIRECTION_ASPECT, holes[li].aspect):
            continue
        hyp = _Hypothesis(location=li, direction=di, rel=rel, radius=radius)
        res = _try_hypothesis(region, hyp, whitener)
        if res.code is not None or res.reason in _FINAL_REASONS:
            return res
        if _REASON_RANK[res.reason] > _REASON_RANK[best.reason]:
            best = res
    return best


class _LazyFlag:
    """A boolean computed on first use (and only then)."""

    def __init__(self, fn) -> None:
        self._fn = fn
        self._value: bool | None = None

    @property
    def value(self) -> bool:
        if self._value is None:
            self._value = bool(self._fn())
        return self._value


# Whitened radius band [diameters] of the slot ring's holes (slots at 0.3).
_RING_MIN, _RING_MAX = 0.17, 0.45
# Largest angular offset [deg] of a hole from its slot's nominal direction.
_SLOT_TOLERANCE_DEG = 26.0


def _assign_slots(holes: list[_Hole], hyp: _Hypothesis) -> dict[int, int]:
    """Step 7: coded slot (1..4) -> hole index, clockwise from centre -> directional.

    The largest hole wins a slot claimed twice.
    """
    ang = np.arctan2(hyp.rel[:, 1], hyp.rel[:, 0])
    # Sign frame y up: clockwise = decreasing angle.
    cw = np.degrees(ang[hyp.direction] - ang) % 360.0
    slots: dict[int, int] = {}
    for k in range(len(holes)):
        if k in (hyp.location, hyp.direction) or not _RING_MIN < hyp.radius[k] < _RING_MAX:
            continue
        nearest = int(round(float(cw[k]) / SLOT_STEP_DEG))
        s = nearest % 5
        if s == 0 or abs(cw[k] - SLOT_STEP_DEG * nearest) > _SLOT_TOLERANCE_DEG:
            continue
        if s in slots and holes[slots[s]].area >= holes[k].area:
            continue
        slots[s] = k
    return slots


def _initial_fit(
    region: _Region, hyp: _Hypothesis, slots: dict[int, int], whitener: np.ndarray
) -> tuple[np.ndarray | None, float, DecodeResult | None]:
    """image_H_sign from the contours' centroids and its disc's major axis [px],
    or the failure that rules it out."""
    holes, settings = region.holes, region.settings
    h, w = region.gray.shape
    parts = [0, 1] + [1 + s for s in sorted(slots)]
    used = [hyp.location, hyp.direction] + [slots[s] for s in sorted(slots)]
    measured = region.centroids_px[used]
    fallback = None
    if len(parts) < 3:
        fallback = _affine_from_two(
            holes[hyp.location].centroid, holes[hyp.direction].centroid, whitener
        )
    image_H_sign, _ = _fit_parts(parts, measured, fallback, passes=0, want_residual=False)
    if image_H_sign is None:
        return None, 0.0, _fail(DecodeReason.NO_LOCATION)
    # A plausible view: not beyond ~75 degrees, and a disc that fills a good
    # part of the crop (a region of interest is "almost full of the sign").
    # Collapsed hypotheses (e.g. a location square split by a cable taken
    # for a sign) squeeze all samples onto a line and must not get that far.
    ellipse = _safe_disc_ellipse(image_H_sign)
    if ellipse is None:
        return None, 0.0, _fail(DecodeReason.NO_LOCATION)
    (_, _), (major, minor), _ = ellipse
    if not (
        minor >= settings.min_axis_ratio * major
        and major >= max(settings.min_sign_px, settings.min_fill * max(w, h))
    ):
        return None, 0.0, _fail(DecodeReason.NO_LOCATION)
    disc_area = region.disc_area_px
    if disc_area is not None and not 0.6 < math.pi * major * minor / 4 / disc_area < 1.6:
        return None, 0.0, _fail(DecodeReason.NO_LOCATION)
    # The fitted disc sits where the disc-like region is (a hypothesis made of
    # parts shifted by one slot can match sizes but not the place).
    centre = region.disc_centre_px
    if centre is not None and math.dist(ellipse[0], centre) > _MAX_CENTRE_SHIFT * major:
        return None, 0.0, _fail(DecodeReason.NO_LOCATION)
    rim = _project(image_H_sign, _RIM)
    if not _inside(rim, w, h, settings.edge_margin_px):
        # Only a plausible sign counts as cut: a wild hypothesis can also
        # put its rim outside.
        span = float(np.ptp(rim, axis=0).max())
        plausible = span < 1.6 * max(w, h) and region.cut.value
        if not plausible:
            return None, major, _fail(DecodeReason.NO_LOCATION)
        # The fitted disc goes with the refusal: ``decode_region`` crops
        # around it once more when the crop, not the image, cut the rim.
        return None, major, _fail(DecodeReason.CUT_BY_EDGE, ellipse=ellipse)
    return image_H_sign, major, None


def _has_unexplained_holes(
    region: _Region, hyp: _Hypothesis, slots: dict[int, int], image_H_sign: np.ndarray
) -> bool:
    """A large hole inside the disc that the hypothesis leaves unexplained.

    A sign shows no white inside its disc besides its rectangles.
    """
    used = {hyp.location, hyp.direction, *slots.values()}
    others = [k for k in range(len(region.holes)) if k not in used]
    if not others:
        return False
    _, sign_H_image = cv2.invert(image_H_sign)
    pos = _project(sign_H_image, region.centroids_px[others])
    inside = np.linalg.norm(pos, axis=1) < 0.47
    big = np.array([region.holes[k].area for k in others]) > 0.3 * region.holes[hyp.location].area
    return bool((inside & big).any())


@dataclass(frozen=True)
class _Refined:
    """The sub-pixel homography of an accepted reading.

    Attributes:
        image_H_sign: (3, 3) homography [sign diameters -> px].
        used_parts: part indices whose gray-level centroid was measured.
        centroids_px: (len(used_parts), 2) those centroids [px].
        residual_px: RMS fit residual [px], NaN for an exact fit.
        fill_deficit: the largest share of a part's area missing from its
            white area (a line or dirt across it; blur keeps the sum).
    """

    image_H_sign: np.ndarray
    used_parts: list[int]
    centroids_px: np.ndarray
    residual_px: float
    fill_deficit: float = 0.0


def _fill_deficit(
    image_H_sign: np.ndarray, parts: list[int], white_area: np.ndarray, valid: np.ndarray
) -> float:
    """Largest 1 - white area / projected area over the measured parts (0 when clean)."""
    if not valid.any():
        return 0.0
    quads = _project(image_H_sign, _PART_QUADS[parts].reshape(-1, 2)).reshape(-1, 4, 2)
    x, y = quads[..., 0], quads[..., 1]
    nxt = [1, 2, 3, 0]
    area = 0.5 * np.abs((x * y[:, nxt] - x[:, nxt] * y).sum(axis=1))
    ratio = white_area[valid] / np.maximum(area[valid], 1e-9)
    return float(np.clip(1.0 - ratio, 0.0, 1.0).max())


def _refine(
    region: _Region,
    image_H_sign: np.ndarray,
    parts: list[int],
    pattern: str,
    reading: _Reading,
    major_px: float,
) -> _Refined | None:
    """Refit to the gray-level centroids of ``parts``; None when the story changes.

    ``pattern``: the accepted bits, "x" where erased.
    """
    g, settings = region.gray, region.settings
    cents, valid, white_area = _subpixel_centroids(
        g, image_H_sign, parts, reading.black, reading.white, 1.5
    )
    deficit = _fill_deficit(image_H_sign, parts, white_area, valid)
    use = [p for p, v in zip(parts, valid, strict=True) if v]
    cents_used = cents[valid]
    if len(use) < 2:
        return _Refined(image_H_sign, use, cents_used, float("nan"), deficit)
    fallback = _refit_fallback(image_H_sign, cents, valid) if len(use) < 3 else None
    passes = 1 if settings.perspective_correction else 0
    h_ref, rms = _fit_parts(use, cents_used, fallback, passes=passes)
    if h_ref is None:
        return None
    # The refined geometry must tell the same story: the sign centre stays
    # put (within a tenth of the diameter) and the slots read the same. The
    # refined map passes through the measured centroids, so a wild one can
    # keep them and still be wrong elsewhere: read again.
    before = _project(image_H_sign, _PART_CENTRES[:2])
    after = _project(h_ref, _PART_CENTRES[:2])
    moved = float(np.abs(after - before).max())
    again = _read_slots(g, h_ref, settings).code
    if moved > 0.1 * major_px or again is None or not _consistent(again, pattern):
        return None
    return _Refined(h_ref, use, cents_used, rms, deficit)


def _rim_view(
    region: _Region, image_H_sign: np.ndarray, used: list[int], parts: list[int]
) -> np.ndarray:
    """The view to read a code with fewer than two white slots under: the rim's
    homography (``_homography_from_rim``) through the location and directional
    holes' centroids, when the region is disc-like and that map puts every
    part of ``parts`` (holes ``used``) where its hole is, within
    ``_RIM_VIEW_TOLERANCE`` diameters; else ``image_H_sign``.

    Three parts or fewer fix only an affine map, which under an oblique view
    misplaces the rest of the face: a clean sign 160 px across at 52 degrees
    (scripts/eval_decoder.py's main set) then shows white beside its
    rectangles and dark rim runs on the face, and was refused.
    """
    if region.rim_contour is None or not region.settings.perspective_correction:
        return image_H_sign
    measured = region.centroids_px[used]
    h_rim = _homography_from_rim(region.rim_contour, measured[0], measured[1])
    if h_rim is None:
        return image_H_sign
    h_rim = _translated(h_rim, measured[0] - _project(h_rim, _PART_CENTRES[:1])[0])
    gap_px = float(np.hypot(*(_project(h_rim, _PART_CENTRES[parts]) - measured).T).max())
    if gap_px > _RIM_VIEW_TOLERANCE * px_per_diameter(image_H_sign):
        return image_H_sign
    return h_rim


# How far [diameters] the rim's view may put a part from its hole's centroid
# (the centroids of tilted rectangles are off their centres by far less).
_RIM_VIEW_TOLERANCE = 0.05


def _keypoints_from_rim(
    region: _Region, refined: _Refined, kp_parts: list[int], uv: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Keypoints and image_H_sign with the perspective taken from the disc's rim.

    For codes with too few parts for a homography: each measured part's
    predicted centroid offset under the rim's homography is removed.
    """
    use, cents_used = refined.used_parts, refined.centroids_px
    h_rim = _homography_from_rim(region.rim_contour, cents_used[0], cents_used[1])
    if h_rim is None:
        return uv, refined.image_H_sign
    quads = _PART_QUADS[use]
    proj = _project(h_rim, quads.reshape(-1, 2)).reshape(quads.shape)
    offset = polygon_centroids(proj) - _project(h_rim, _PART_CENTRES[use])
    fixed = dict(zip(use, cents_used - offset, strict=True))
    uv = np.array([fixed.get(p, q) for p, q in zip(kp_parts, uv, strict=True)])
    shift = fixed[0] - _project(h_rim, _PART_CENTRES[:1])[0]
    return uv, _translated(h_rim, shift)


def _pool(allowed: frozenset[str] | None) -> list[str]:
    """The codes a reading may take: the map's, or all 16."""
    return list(ALL_CODES) if allowed is None else sorted(allowed)


@dataclass(frozen=True)
class _Occlusion:
    """What the face shows of an occluder under one reading.

    Attributes:
        pattern: the reading's bits with "x" for every erased slot.
        covered_parts: part indices (0..5) a band or a dark patch covers.
        disturbance: 1 - the least white fraction inside the white parts kept.
        unreported: white parts read but whose keypoints are not reported:
            clean parts (not the location square) that a band ``beside`` them
            reaches (``occlusion.Band.beside``), whose centroids it may pull.
    """

    pattern: str
    covered_parts: frozenset[int]
    disturbance: float = 0.0
    unreported: frozenset[int] = frozenset()


def _occluder_bands(
    g: np.ndarray,
    image_H_sign: np.ndarray,
    reading: _Reading,
    outline_intact: bool,
    search_bars: bool,
    clean_parts: frozenset[int] = frozenset(),
) -> list[occlusion.Band]:
    """Every band of ``frontend.occlusion`` the reading's evidence allows (see
    ``_occlusion``), before the test against clean white parts.

    ``clean_parts``: white parts (indices into ``_PART_NAMES``) that show
    white throughout; a wide dark band beside one is not taken to be in front.
    """
    h, w = g.shape
    inside = _inside(_project(image_H_sign, _OUTER_RING), w, h, 0.0)
    white = [0, 1] + [1 + k for k in range(1, N_BITS + 1) if reading.code[k - 1] == "1"]
    clean = np.array([p in clean_parts for p in white], bool)
    zeros = [1 + k for k in range(1, N_BITS + 1) if reading.code[k - 1] == "0"]
    # The rim's dark runs, sampled once for both kinds of band (none wanted
    # when neither looks: no ring inside the crop and an intact outline).
    runs = []
    if inside or not outline_intact:
        runs = occlusion.rim_runs(g, image_H_sign, reading.black, reading.white)
    bands = occlusion.dark_bands(
        g, image_H_sign, reading.black, reading.white, inside, _PART_CENTRES[white], runs, clean
    )
    if outline_intact:
        bands = [b for b in bands if b.in_front or b.beside]
    else:
        # A black-read slot under a bar whose other end is lost in the dark.
        bands += occlusion.bars_through(
            g, image_H_sign, reading.black, reading.white, _PART_CENTRES[zeros], runs
        )
        if search_bars:
            bands += occlusion.straight_bars(
                g,
                image_H_sign,
                reading.black,
                reading.white,
                _PART_CENTRES[zeros],
                _PART_QUADS[white],
            )
    # An object in front whose gray is not the print's black, over a black-read slot.
    bands += occlusion.off_black_bands(
        g, image_H_sign, reading.black, reading.white, _PART_CENTRES[zeros]
    )
    return bands


def _occlusion(
    g: np.ndarray,
    image_H_sign: np.ndarray,
    reading: _Reading,
    outline_intact: bool,
    search_bars: bool = False,
) -> _Occlusion:
    """Erase black-read slots a dark band crosses; find the white parts it covers.

    ``outline_intact``: the disc's dark region is disc-like (nothing dark
    joins its outline). Then no bar darker than the binarisation threshold
    crosses the rim, and the weak evidence (a print-black band, which may as
    well lie behind) is not used. ``search_bars``: see ``DecoderSettings``.
    """
    pattern = list(reading.code)
    white = [0, 1] + [1 + k for k in range(1, N_BITS + 1) if pattern[k - 1] == "1"]
    inside_white = occlusion.interior_min_white(
        g, image_H_sign, _PART_QUADS[white], reading.black, reading.white, np.equal(white, 1)
    )
    # White parts that show white throughout: a dark band beside one is not
    # in front of it (``occlusion.dark_bands``' ``clean``).
    clean_parts = frozenset(
        p for p, m in zip(white, inside_white.tolist(), strict=True) if m >= _CLEAN_INSIDE
    )
    bands = _occluder_bands(g, image_H_sign, reading, outline_intact, search_bars, clean_parts)
    if bands:
        # A band whose centre line runs over a white part that shows white
        # throughout is not in front of it: no evidence of an occluder (on
        # photographs, dark background beyond the rim joined by a chord).
        clean = [p for p, m in zip(white, inside_white.tolist(), strict=True) if m >= _CLEAN_INSIDE]
        if clean:
            c = _PART_CENTRES[clean]
            bands = [b for b in bands if not (b.distance(c) < b.half_width).any()]
    # A white slot reads black only when a band hides all of its reading
    # samples (its centre line and the inner samples): a black-read slot is
    # erased when its centre lies under a band, not when a band grazes it.
    erasing = [b for b in bands if b.erases]
    band_hits = occlusion.crossed(erasing, _PART_CENTRES, np.full(len(_PART_CENTRES), _ERASE_REACH))
    # A white part that shows white throughout is only dropped under a band
    # seen in front (a black bar that may be behind leaves it alone).
    front_hits = occlusion.crossed([b for b in bands if b.in_front], _PART_CENTRES, _PART_HALF)
    covered = {
        p for p, m in zip(white, inside_white.tolist(), strict=True) if m < occlusion.COVERED_INSIDE
    }
    # How far the least clean of the parts kept falls short of white (dirt,
    # a thin line across it): their centroids carry that.
    kept = [m for p, m in zip(white, inside_white.tolist(), strict=True) if p not in covered]
    disturbance = float(np.clip(1.0 - min(kept), 0.0, 1.0)) if kept else 0.0
    # Tried and dropped: keeping a location or directional rectangle that a
    # band in front reaches while it shows white throughout (and its white
    # area whole). 0.5-3 points more decoded in every condition of the
    # independent scenes and no wrong code, but a bar beside the rectangle,
    # inside its centroid window, moved its centroid up to 3 px on a 90 px
    # sign (and, through the refit, others by 8 sigma).
    covered |= {p for p in white if front_hits[p]}
    for k in range(1, N_BITS + 1):
        if pattern[k - 1] == "0" and band_hits[1 + k]:
            pattern[k - 1] = "x"
        if pattern[k - 1] == "x":
            covered.add(1 + k)
    beside_hits = occlusion.crossed([b for b in bands if b.beside], _PART_CENTRES, _PART_HALF)
    unreported = frozenset(p for p in white if p != 0 and beside_hits[p]) - covered
    return _Occlusion("".join(pattern), frozenset(covered), disturbance, unreported)


def _erased_under_plain_bands(
    region: _Region, image_H_sign: np.ndarray, reading: _Reading
) -> _Reading:
    """``reading`` (read with a glow taken off) with every black-read slot that
    a band of the plain gray levels crosses erased: a bar lighter than the
    print over a black slot lifts it as a glow would, but it is a straight
    band that the plain image's evidence sees."""
    bands = _occluder_bands(
        region.gray,
        image_H_sign,
        reading,
        region.rim_contour is not None,
        region.settings.search_bars,
    )
    hits = occlusion.crossed(bands, _PART_CENTRES, np.full(len(_PART_CENTRES), _ERASE_REACH))
    code = "".join("x" if b == "0" and hits[1 + k] else b for k, b in enumerate(reading.code))
    return replace(reading, code=code)


def _accept_code(
    region: _Region, image_H_sign: np.ndarray, reading: _Reading, scale_px: float
) -> tuple[str | None, _Occlusion | None, DecodeReason]:
    """The one code the reading allows, with its occlusion, or why there is none."""
    occ = _occlusion(
        region.gray,
        image_H_sign,
        reading,
        region.rim_contour is not None,
        region.settings.search_bars,
    )
    if {0, 1} & occ.covered_parts:
        return None, occ, DecodeReason.OCCLUDED  # no sign frame without both
    # Slots of unknown bit and the read code's white parts explain white.
    known = [0, 1] + [1 + k for k in range(1, N_BITS + 1) if occ.pattern[k - 1] != "0"]
    grow = max(_UNEXPLAINED_GROW, _BLUR_PX / max(scale_px, 1.0))
    if occlusion.unexplained_white(
        region.gray, image_H_sign, tuple(known), reading.black, reading.white, grow
    ):
        return None, occ, DecodeReason.INCONSISTENT
    if "x" not in occ.pattern:
        if region.allowed is not None and occ.pattern not in region.allowed:
            return None, occ, DecodeReason.CODE_NOT_IN_MAP
        return occ.pattern, occ, DecodeReason.OK
    fits = [c for c in _pool(region.allowed) if _consistent(occ.pattern, c)]
    if len(fits) != 1:
        return None, occ, DecodeReason.OCCLUDED
    if "1" in fits[0] and "1" not in occ.pattern:
        # Every white slot of the code is erased: unless one of them shows
        # white in part (a conductor or a member's edge over it), nothing seen
        # says it is this sign rather than any dark disc with a centre and a
        # direction. On the independent scenes (1,000 per condition, seed
        # 2017) refusing them all took the wrong codes 9 -> 7 of 10,000
        # (member in front 3 -> 1) and the paper map's one-slot-unique
        # decodes 63.3 -> 46.1 % (its four one-white codes); the two wrong
        # readings it stops there showed the erased slot gray throughout.
        erased_white = [1 + k for k in range(1, N_BITS + 1) if fits[0][k - 1] == "1"]
        if not occlusion.shows_white(
            region.gray, image_H_sign, _PART_QUADS[erased_white], reading.black, reading.white
        ).any():
            return None, occ, DecodeReason.OCCLUDED
    return fits[0], occ, DecodeReason.OK


def _try_hypothesis(region: _Region, hyp: _Hypothesis, whitener: np.ndarray) -> DecodeResult:
    """Read the sign under one (location, directional) hypothesis and verify it."""
    g, settings = region.gray, region.settings
    slots = _assign_slots(region.holes, hyp)
    image_H_sign, major_px, failure = _initial_fit(region, hyp, slots, whitener)
    if failure is not None:
        return failure
    if _has_unexplained_holes(region, hyp, slots, image_H_sign):
        return _fail(DecodeReason.INCONSISTENT)
    if len(slots) < 2:
        # Too few parts for a homography: the rim gives the perspective.
        used = [hyp.location, hyp.direction] + [slots[s] for s in sorted(slots)]
        parts = [0, 1] + [1 + s for s in sorted(slots)]
        image_H_sign = _rim_view(region, image_H_sign, used, parts)
    reading = _read_slots(g, image_H_sign, settings)
    if reading.code is None:
        return _fail(reading.reason, quality=max(0.0, reading.margin))
    contour_code = "".join("1" if s in slots else "0" for s in range(1, N_BITS + 1))
    if not _consistent(reading.code, contour_code):
        return _fail(DecodeReason.INCONSISTENT, quality=reading.margin)
    # The occlusion evidence reads the face with the glow taken off too, and
    # a black-read slot under a band of the plain image stays erased.
    seen = region
    if reading.glow is not None:
        seen = replace(region, gray=_flattened(g, image_H_sign, reading.glow))
        reading = _erased_under_plain_bands(region, image_H_sign, reading)
    code, occ, reason = _accept_code(seen, image_H_sign, reading, major_px)
    if code is None:
        # A verdict about a sign read here carries where its disc is.
        ellipse = _safe_disc_ellipse(image_H_sign) if reason in _FINAL_REASONS else None
        unknown = occ.pattern if reason == DecodeReason.CODE_NOT_IN_MAP else None
        return _fail(reason, quality=reading.margin, ellipse=ellipse, unknown_code=unknown)
    erased = tuple(k for k in range(1, N_BITS + 1) if occ.pattern[k - 1] == "x")
    kp_parts = [p for p in _CODE_PARTS[code][0] if p not in occ.covered_parts]
    reported = [p for p in kp_parts if p not in occ.unreported]
    refined = _refine(region, image_H_sign, kp_parts, occ.pattern, reading, major_px)
    if refined is None:
        return _fail(DecodeReason.INCONSISTENT, quality=reading.margin)
    uv = _project(refined.image_H_sign, _PART_CENTRES[kp_parts])
    image_H_sign = refined.image_H_sign
    n_used = len(refined.used_parts)
    if 2 <= n_used < 4 and region.rim_contour is not None and settings.perspective_correction:
        uv, image_H_sign = _keypoints_from_rim(region, refined, kp_parts, uv)
    # A part a band beside it may pull stays in the fit (dropping it bent
    # the fit of the others more) but its keypoint is not reported.
    shown_uv = uv[[p in reported for p in kp_parts]]
    ellipse = _safe_disc_ellipse(image_H_sign)
    if ellipse is None:
        return _fail(DecodeReason.INCONSISTENT)
    return _reading_result(
        code,
        reported,
        shown_uv,
        image_H_sign,
        ellipse,
        reading,
        refined.residual_px,
        bool(occ.covered_parts),
        max(occ.disturbance, refined.fill_deficit),
        erased,
        _with_unfitted(
            measure_parts(
                g,
                refined.image_H_sign,
                [_PART_NAMES[p] for p in refined.used_parts],
                _PART_QUADS[refined.used_parts],
                refined.centroids_px,
                reading.black,
                reading.white,
            ),
            refined,
            kp_parts,
            uv,
            image_H_sign,
        ),
    )


def _with_unfitted(
    measured: PartMeasures,
    refined: _Refined,
    kp_parts: list[int],
    uv: np.ndarray,
    image_H_sign: np.ndarray,
) -> PartMeasures:
    """``measured`` with the two-part readings' unfitted residuals
    (``keypoint_noise.unfitted_residuals_px``: the keypoints ``uv`` of
    ``kp_parts`` under the final ``image_H_sign`` against the centroids)."""
    use = refined.used_parts
    if len(use) != 2:
        return measured
    used_uv = uv[[kp_parts.index(p) for p in use]]
    names = [_PART_NAMES[p] for p in use]
    r = unfitted_residuals_px(image_H_sign, names, _PART_QUADS[use], refined.centroids_px, used_uv)
    return replace(measured, unfitted_px=r)


def _reading_result(
    code: str,
    parts: list[int],
    uv: np.ndarray,
    image_H_sign: np.ndarray,
    ellipse: Ellipse,
    reading: _Reading,
    rms: float,
    crossed: bool,
    disturbance: float,
    erased: tuple[int, ...],
    measured: PartMeasures | None = None,
) -> DecodeResult:
    """An accepted reading as a ``DecodeResult``: quality from the reading's
    margin and the fit's residual ``rms`` [px], keypoints ``uv`` of ``parts``
    with their sigmas (``keypoint_sigmas``; ``measured``: what the image shows
    around each part, ``keypoint_noise.measure_parts``)."""
    quality = min(max(reading.margin / 0.5, 0.0), 1.0) * math.exp(
        -(rms if math.isfinite(rms) else 0.0) / 0.5
    )
    names = [_PART_NAMES[p] for p in parts]
    inputs = SigmaInputs(
        minor_px=float(ellipse[1][1]),
        spread=reading.spread,
        residual_px=rms,
        crossed=crossed,
        disturbance=disturbance,
    )
    if measured is not None:
        inputs = replace(
            inputs,
            part_residual_px=measured.residual_px,
            part_stray=measured.stray,
            part_inside=measured.inside,
            noise=measured.noise,
            part_pull_px=measured.pull_px,
            part_stray_pull_px=measured.stray_pull_px,
            part_fill=measured.fill,
            part_side_px=measured.side_px,
            part_unfitted_px=measured.unfitted_px,
        )
    sigmas = keypoint_sigmas(inputs, names)
    return DecodeResult(
        code=code,
        reason=DecodeReason.OK,
        keypoints_px={n: (float(p[0]), float(p[1])) for n, p in zip(names, uv, strict=True)},
        ellipse=ellipse,
        quality=float(quality),
        sigma_px=mean_sigma(sigmas),
        image_H_sign=image_H_sign,
        residual_px=rms,
        erased_slots=erased,
        keypoint_sigma_px=sigmas,
        sigma_inputs=inputs,
    )


def _consistent(a: str, b: str) -> bool:
    """Whether two bit patterns agree on every slot both know ("x": erased)."""
    return all(p == q or "x" in (p, q) for p, q in zip(a, b, strict=True))


def _homography_from_rim(
    rim_contour: np.ndarray, centre_px: np.ndarray, direction_px: np.ndarray
) -> np.ndarray | None:
    """image_H_sign from the disc's rim (an ellipse) and the images of two points.

    The polar of the centre's image with respect to the rim's image conic is
    the plane's vanishing line (pole-polar duality of a circle and its
    centre). Sending it to infinity leaves an affine view of the disc, fixed
    by the ellipse there and the direction to the directional rectangle.
    """
    if len(rim_contour) < 6:
        return None
    (ex, ey), (ea, eb), eang = cv2.fitEllipse(rim_contour)
    if min(ea, eb) <= 2:
        return None
    t = math.radians(eang)
    r = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    q = r @ np.diag([4.0 / ea**2, 4.0 / eb**2]) @ r.T  # (x-e)^T q (x-e) = 1
    e = np.array([ex, ey])
    conic = np.eye(3)
    conic[:2, :2] = q
    conic[:2, 2] = conic[2, :2] = -q @ e
    conic[2, 2] = e @ q @ e - 1.0
    c = np.array([centre_px[0], centre_px[1], 1.0])
    line = conic @ c
    if abs(line @ c) < 1e-12:
        return None
    line = line / (line @ c)
    p = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], line])
    ok, p_inv = cv2.invert(p)
    if not ok:
        return None
    rect = p_inv.T @ conic @ p_inv
    a2 = rect[:2, :2]
    det = a2[0, 0] * a2[1, 1] - a2[0, 1] ** 2
    if det <= 0:
        return None
    pc = _project(p, centre_px.reshape(1, 2))[0]
    pd = _project(p, direction_px.reshape(1, 2))[0]
    k = -(pc @ a2 @ pc + 2 * rect[:2, 2] @ pc + rect[2, 2])
    if k <= 0:
        return None
    # M maps the sign's disc (diameter 1, radius 1/2) onto the rectified
    # ellipse y^T (a2 / k) y = 1: M = 2 (a2 / k)^(-1/2).
    w = _whitener_sym(a2 / k)
    if w is None:
        return None
    m = 2.0 * w
    qd = np.linalg.solve(m, pd - pc)
    psi = math.atan2(qd[1], qd[0]) + math.pi / 2
    rot = np.array([[math.cos(psi), -math.sin(psi)], [math.sin(psi), math.cos(psi)]])
    a = np.eye(3)
    a[:2, :2] = m @ rot @ np.diag([1.0, -1.0])
    a[:2, 2] = pc
    h = p_inv @ a
    return h / h[2, 2]


def _whitener_sym(m: np.ndarray) -> np.ndarray | None:
    """Inverse square root of a symmetric positive definite 2x2 matrix."""
    a, b, c = float(m[0, 0]), float(m[0, 1]), float(m[1, 1])
    det = a * c - b * b
    if det <= 0 or a <= 0:
        return None
    sq = math.sqrt(det)
    t = math.sqrt(a + c + 2 * sq)
    return np.array([[c + sq, -b], [-b, a + sq]]) / (sq * t)


def _safe_disc_ellipse(image_H_sign: np.ndarray) -> Ellipse | None:
    try:
        return disc_ellipse(image_H_sign, 1.0)
    except (ValueError, ZeroDivisionError):
        return None


def _refit_fallback(image_H_sign: np.ndarray, cents: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """For two parts only: keep the current linear part, move it onto the new centre."""
    h = image_H_sign.copy()
    if valid[0]:
        shift = cents[0] - _project(image_H_sign, _PART_CENTRES[:1])[0]
        h = _translated(h, shift)
    return h


def _crop_bounds(
    bbox_px: tuple[float, float, float, float], margin: float, iw: int, ih: int
) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) [px] of the box grown by ``margin`` per side, clipped to the image."""
    x, y, bw, bh = bbox_px
    return (
        max(int(math.floor(x - margin * bw)), 0),
        max(int(math.floor(y - margin * bh)), 0),
        min(int(math.ceil(x + bw * (1 + margin))), iw),
        min(int(math.ceil(y + bh * (1 + margin))), ih),
    )


def _ellipse_box(ellipse: Ellipse) -> tuple[float, float, float, float]:
    """(x, y, w, h) [px] axis-aligned bounding box of a (full-axes, cv2 angle) ellipse."""
    (cx, cy), (major, minor), angle_deg = ellipse
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    half_u = 0.5 * math.hypot(major * c, minor * s)
    half_v = 0.5 * math.hypot(major * s, minor * c)
    return cx - half_u, cy - half_v, 2.0 * half_u, 2.0 * half_v


def _in_image(res: DecodeResult, x0: int, y0: int) -> DecodeResult:
    """A crop's reading moved to the pixels of the image the crop starts at (x0, y0) of."""
    ellipse = None
    if res.ellipse is not None:
        (cx, cy), axes, ang = res.ellipse
        ellipse = ((cx + x0, cy + y0), axes, ang)
    if res.code is None:
        return replace(res, ellipse=ellipse)
    return replace(
        res,
        keypoints_px={k: (u + x0, v + y0) for k, (u, v) in res.keypoints_px.items()},
        ellipse=ellipse,
        image_H_sign=_translated(res.image_H_sign, (x0, y0)),
    )


def _box_holds(bbox_px: tuple[float, float, float, float], uv_px: tuple[float, float]) -> bool:
    """Whether the point lies in the (x, y, w, h) box: a disc fitted beside the
    region is another sign's (the region's reading would carry a box off it)."""
    x, y, bw, bh = bbox_px
    return x <= uv_px[0] <= x + bw and y <= uv_px[1] <= y + bh


def _disc_inside_image(ellipse: Ellipse, iw: int, ih: int, margin_px: float) -> bool:
    """Whether the disc lies inside the (iw, ih) image: a rim the crop cut, not the image."""
    u, v, bw, bh = _ellipse_box(ellipse)
    return _inside(np.array([[u, v], [u + bw, v + bh]]), iw, ih, margin_px)


def decode_region(
    image_gray: np.ndarray,
    bbox_px: tuple[float, float, float, float],
    codes: Iterable[str] | None = None,
    settings: DecoderSettings = DecoderSettings(),
) -> DecodeResult:
    """Decode the sign in ``bbox_px`` of a full image; keypoints in full-image pixels.

    Args:
        image_gray: (H, W) uint8 image (BGR is converted).
        bbox_px: (x, y, w, h) detector box [px].
        codes: the map's codes (see ``decode_roi``).
        settings: tuning; the box grows by ``settings.region_margin`` per side.

    A crop that cuts the rim of the disc it fitted (``cut_by_edge``) is read
    once more around that disc when the disc is centred in the box and lies
    inside the image (``settings.recrop_cut_rim``). A refusal's ellipse (see
    ``DecodeResult.ellipse``) is in the image's pixels.
    """
    img = _as_gray(image_gray)
    ih, iw = img.shape[:2]
    box = tuple(float(v) for v in bbox_px)
    codes = None if codes is None else frozenset(codes)
    x0, y0, x1, y1 = _crop_bounds(box, settings.region_margin, iw, ih)
    if x1 - x0 < settings.min_sign_px or y1 - y0 < settings.min_sign_px:
        return _fail(DecodeReason.NO_SIGN)
    res = _in_image(decode_roi(img[y0:y1, x0:x1], codes, settings), x0, y0)
    if not (
        settings.recrop_cut_rim
        and res.reason == DecodeReason.CUT_BY_EDGE
        and res.ellipse is not None
        and _box_holds(box, res.ellipse[0])
        and _disc_inside_image(res.ellipse, iw, ih, settings.edge_margin_px)
    ):
        return res
    # The crop, not the image, cut the rim of the box's sign: decode once
    # more around the disc.
    bounds = _crop_bounds(_ellipse_box(res.ellipse), settings.region_margin, iw, ih)
    rx0, ry0, rx1, ry1 = bounds
    if bounds == (x0, y0, x1, y1) or min(rx1 - rx0, ry1 - ry0) < settings.min_sign_px:
        return res
    again = _in_image(decode_roi(img[ry0:ry1, rx0:rx1], codes, settings), rx0, ry0)
    # A verdict about the box's sign (read, occluded, not in the map) stands;
    # a second failure about the crop, or a sign beside the box, does not
    # replace the first.
    verdict = again.ok or again.reason in _FINAL_REASONS
    if verdict and again.ellipse is not None and _box_holds(box, again.ellipse[0]):
        return again
    return res
