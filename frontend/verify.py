"""Tracked verification: read a sign whose code and homography are predicted.

In tracking the pipeline predicts, for each sign of the map in view, its code
and ``image_H_sign`` (the pose predicted from the previous frames, through
the map). Decoding such a sign from scratch (thresholds, contours, location
and directional hypotheses) repeats work whose answer is already known.
``verify_sign`` instead:

1. aligns the prediction: the location square's gray-level centroid, in a
   window around its predicted place, moves the homography (translation
   only, ``VerifySettings.align_passes`` times);
2. reads the five slot positions there (``decoder._read_slots``): the bits
   must agree with the predicted code;
3. measures the gray-level centroid of every white part of the code near its
   predicted place (``_part_centroids``: the decoder's
   ``_subpixel_centroids``, summed per part in one pass) and refits the
   homography once (``_refit``: a homography for four or more parts, an
   affine correction of the prediction for three);
4. checks at the refit homography what the full decoder checks before it
   accepts a reading: the slots read again the same code, the occlusion
   evidence erases nothing and covers no part, no white is left unexplained,
   the code is the map's (``decoder._accept_code``); nothing dark lies
   across a white part (``max_disturbance``); the refit's residual and the
   centre's move stay small.

Anything else (a slot reads differently, a keypoint not found, a large
residual, an occluder, fewer than three white parts, a sign cut by the image's
edge) is not an error but an ``outcome``: the caller then decodes the sign in
full. A verification therefore accepts only readings that pass every
gray-level test of the decoder at a geometry fitted to the image; occluded
signs (erased slots, dropped keypoints) are always left to the full decoder.
The result is a ``DecodeResult`` filled as the decoder fills it (keypoints,
ellipse, ``sigma_inputs`` and ``keypoint_sigma_px`` from the same
``keypoint_sigmas``), so the sigma calibration holds for verified signs too.

Cost: about 1.2 ms of CPU per verified sign on scripts/bench_frontend.py's
crops, most of it in what the decoder does for an accepted reading, called
here at the refit. Medians over the simulator flight's 357 verified crops
(40 frames, least of 5 runs each, on commit 59ae25e): ``verify_sign``
1173 us; ``_accept_code`` 318 us, ``keypoint_noise.measure_parts`` 208 us,
``_reading_result`` 111 us, ``_read_slots`` 29 us twice, ``_fill_deficit``
16 us; this module's own steps: ``_part_centroids`` 45 us, ``_refit`` 36 us,
``_align`` 34 us, two disc ellipses 11 us. A verification makes about 1,570
Python-level calls, 630 of them numpy's and 48 OpenCV's
(``bench_frontend.py --frames 40 --profile track``, sim; 6 of them
``np.median`` in ``keypoint_sigmas``, a tenth of the profile). Own copies of the decoder's checks
fed from one remap of every sample were not written: they would have to
follow each change of the decoder's acceptance by hand, and a copy that
lags behind accepts, silently, what the decoder refuses.

Tried and dropped (2026-12-02): ``measure_parts`` batched over a frame's
verified signs (checks per sign, then every sign's interior, outline and
ring samples in one remap, the statistics as per-row reductions). The
sigma model's owner changed ``measure_parts`` the same session (new pull,
fill and side measures), so the copy was stale before its equality test
ever passed; it was neither kept nor timed. Batching the own
steps over a frame's signs would change what each starts from: each
verification starts at the offset of the nearest sign already verified.

Tried and dropped (issue 14): reusing, per track, the checks and part
measures of the frame where every check last ran while the sign looks
unchanged (its disc warped through the sign plane onto this frame's refit,
no pixel departing by more than 5 noise sigmas plus 0.2 px times the local
gradient; the detector keeping a reference per code, dropped at ``detect``).
A tracked sign does not look the same from frame to frame: motion blur and
the resampling's phase move its edges by tens of gray levels.
``scripts/bench_frontend.py --frames 40 --repeat 1 --appearance``: that test
calls 2.4 % of the consecutive-frame pairs unchanged on the sim flight (338
pairs) and 3.4 % on the hard one (205), against 97.9 / 97.5 % of a still
sign (the earlier frame again with fresh noise); the largest change over
the disc is a quarter of the contrast at the median (0.247 sim, 0.249 hard;
still 0.046 / 0.062), 0.085 / 0.081 with both images smoothed by a 1 px
Gaussian (still 0.016 / 0.020). With the reuse (not committed),
``bench_frontend --frames 40`` reused 14 of 357 verifications (sim) and 10
of 220 (hard), and tracking cost more (sim 0.91x -> 1.05x ArUco: the
references' upkeep). A test loose enough to reuse half the verifications
would pass changes of a tenth of the contrast after smoothing, what a thin
conductor across a white part leaves.
"""

from __future__ import annotations

import enum
import functools
import math
from collections.abc import Iterable
from dataclasses import dataclass, replace

import cv2
import numpy as np
from signpose.frontend.decoder import (
    _CODE_PARTS,
    _LOCATION_SIDE,
    _PART_CENTRES,
    _PART_NAMES,
    _PART_QUADS,
    _RIM,
    _UNIT_STEPS,
    DecodeReason,
    DecodeResult,
    DecoderSettings,
    _accept_code,
    _as_gray,
    _consistent,
    _fill_deficit,
    _inside,
    _LazyFlag,
    _parts_geometry,
    _project,
    _read_slots,
    _reading_result,
    _Region,
    _safe_disc_ellipse,
)
from signpose.frontend.homography import fit_homography, polygon_centroids
from signpose.frontend.keypoint_noise import measure_parts, unfitted_residuals_px


class VerifyOutcome(enum.StrEnum):
    """How a verification ended; the value is the token written to files."""

    VERIFIED = "verified"
    NOT_VERIFIABLE = "not_verifiable"  # fewer than three white parts, or an implausible view
    OUTSIDE = "outside"  # the predicted disc is not wholly inside the image
    NOT_FOUND = "not_found"  # the location square or a white part is not where predicted
    SLOT_DIFFERS = "slot_differs"  # a slot reads differently from the predicted code
    RESIDUAL = "residual"  # the refit's residual or the centre's move is too large
    REFUSED = "refused"  # a decoder check refuses it (occluder, unexplained white, ...)


@dataclass(frozen=True)
class VerifySettings:
    """Verification tuning.

    Attributes:
        align_grow: the location square's alignment window: the square grown
            by this many diameters on each side (half the gap to the ring).
        align_passes: alignment iterations (each recentres the window).
        max_shift: largest total alignment shift [diameters].
        max_residual_px: largest RMS residual of the refit [px], plus
            ``max_residual_frac`` of the disc's major axis.
        max_residual_frac: see ``max_residual_px``.
        max_moved: largest move of the centre or directional keypoint by the
            refit, as a fraction of the disc's major axis (the decoder's 0.1).
        edge_margin_px: the disc's rim stays this far inside the image [px].
        min_major_px: smallest disc verified [px] (smaller: full decode).
        max_disturbance: largest shortfall from white inside any white part
            (``decoder._Occlusion.disturbance``; the decoder calls a part
            clean above 0.7 white): more leaves the sign to the full decoder.
    """

    align_grow: float = 0.05
    align_passes: int = 2
    max_shift: float = 0.15
    max_residual_px: float = 0.35
    max_residual_frac: float = 0.01
    max_moved: float = 0.1
    edge_margin_px: float = 1.0
    min_major_px: float = 14.0
    max_disturbance: float = 0.3


@dataclass(frozen=True)
class Verification:
    """A verification's outcome and, when verified, the reading.

    Attributes:
        outcome: how it ended.
        result: the reading (``code`` set) when verified; otherwise a
            failed ``DecodeResult`` naming the decoder's reason where one
            applies.
    """

    outcome: VerifyOutcome
    result: DecodeResult

    @property
    def ok(self) -> bool:
        return self.outcome is VerifyOutcome.VERIFIED


_HALF_SQUARE = _LOCATION_SIDE / 2
# The disc's rim (radius 0.5) [diameters]: it must lie inside the image.
_DISC_RIM = _RIM / 0.46 * 0.5
_DECODER_SETTINGS = DecoderSettings()


def _miss(outcome: VerifyOutcome, reason: DecodeReason = DecodeReason.INCONSISTENT) -> Verification:
    return Verification(outcome, DecodeResult(code=None, reason=reason))


def _align(
    gray: np.ndarray, image_H_sign: np.ndarray, s: VerifySettings
) -> tuple[np.ndarray | None, float]:
    """The homography moved so the location square sits on its gray-level centroid.

    The window is the predicted square grown by ``align_grow`` (a polygon
    mask: the directional rectangle stays out); a pixel weighs its gray
    level above the window's midpoint, capped at half the range (the
    square's white, not the black ring): min(max(I - mid, 0), cap), as a
    truncation at mid + cap and a saturating subtraction, in whole-array
    OpenCV calls on uint8. The four corners and the homography's rows are
    Python floats in between (the same IEEE operations as numpy's, without
    its per-call cost: 47 against 60 us per alignment).

    Returns (homography or None when the square is not found, shift [px]).
    """
    h, w = gray.shape
    rows = np.array(image_H_sign, float).tolist()
    corners = _align_corners(s.align_grow)
    total_u = total_v = 0.0
    for _ in range(s.align_passes):
        quad = _project(np.array(rows), corners).tolist()
        us, vs = [q[0] for q in quad], [q[1] for q in quad]
        u0, v0 = math.floor(min(us)), math.floor(min(vs))
        u1, v1 = math.ceil(max(us)) + 1, math.ceil(max(vs)) + 1
        if not (u0 >= 0 and v0 >= 0 and u1 <= w and v1 <= h) or u1 - u0 < 3 or v1 - v0 < 3:
            return None, 0.0
        win = gray[v0:v1, u0:u1]
        mask = np.zeros(win.shape, np.uint8)
        # Python's round, like np.round, rounds half to even.
        pts = np.array([[round((u - u0) * 16), round((v - v0) * 16)] for u, v in quad], np.int32)
        cv2.fillConvexPoly(mask, pts, 255, lineType=cv2.LINE_8, shift=4)
        lo, hi, _, _ = cv2.minMaxLoc(win, mask)
        if hi - lo < 25.0:
            return None, 0.0
        mid, cap = int(round(0.5 * (lo + hi))), int((hi - lo) // 2)
        _, wt = cv2.threshold(win, min(mid + cap, 255), 255, cv2.THRESH_TRUNC)
        mo = cv2.moments(cv2.bitwise_and(cv2.subtract(wt, mid), mask))
        if mo["m00"] <= 0:
            return None, 0.0
        # The square's centre under the homography is its translation column.
        r0, r1, r2 = rows
        du = u0 + mo["m10"] / mo["m00"] - r0[2] / r2[2]
        dv = v0 + mo["m01"] / mo["m00"] - r1[2] / r2[2]
        rows = [
            [a + du * c for a, c in zip(r0, r2, strict=True)],
            [b + dv * c for b, c in zip(r1, r2, strict=True)],
            r2,
        ]
        total_u += du
        total_v += dv
    return np.array(rows), math.hypot(total_u, total_v)


@functools.cache
def _align_corners(grow: float) -> np.ndarray:
    """(4, 2) corners of the location square grown by ``grow`` [diameters]."""
    half = _HALF_SQUARE + grow
    return np.array([[-half, -half], [half, -half], [half, half], [-half, half]])


def verify_sign(
    image_gray: np.ndarray,
    image_H_sign: np.ndarray,
    code: str,
    codes: Iterable[str] | None = None,
    settings: VerifySettings = VerifySettings(),
    decoder_settings: DecoderSettings = _DECODER_SETTINGS,
) -> Verification:
    """Verify the predicted sign ``code`` at ``image_H_sign`` in a whole image.

    Args:
        image_gray: (H, W) uint8 image (BGR is converted).
        image_H_sign: (3, 3) predicted homography from the sign plane (disc
            diameter units, x right, y up, origin at the centre) to raw pixels.
        code: the predicted code.
        codes: the map's codes (None: all 16).
        settings: verification tuning.
        decoder_settings: the decoder's tuning (its reading thresholds).

    Returns:
        The outcome; when verified, the reading in the image's pixels.
    """
    g = _as_gray(image_gray)
    allowed = None if codes is None else frozenset(codes)
    parts = _CODE_PARTS[code][0]
    if len(parts) < 3 or (allowed is not None and code not in allowed):
        return _miss(VerifyOutcome.NOT_VERIFIABLE)
    h, w = g.shape
    predicted = np.asarray(image_H_sign, float)
    ell = _safe_disc_ellipse(predicted)
    if ell is None:
        return _miss(VerifyOutcome.NOT_VERIFIABLE)
    (_, _), (major, minor), _ = ell
    ds = decoder_settings
    if major < max(settings.min_major_px, ds.min_sign_px) or minor < ds.min_axis_ratio * major:
        return _miss(VerifyOutcome.NOT_VERIFIABLE)
    if not _inside(_project(predicted, _DISC_RIM), w, h, settings.edge_margin_px):
        return _miss(VerifyOutcome.OUTSIDE)
    aligned, shift = _align(g, predicted, settings)
    if aligned is None or shift > settings.max_shift * major:
        return _miss(VerifyOutcome.NOT_FOUND)
    first = _read_slots(g, aligned, ds)
    if first.code is None:
        return _miss(VerifyOutcome.SLOT_DIFFERS, first.reason)
    if not _consistent(first.code, code) or "x" in first.code:
        return _miss(VerifyOutcome.SLOT_DIFFERS)
    return _refit_and_check(g, aligned, code, parts, first, major, allowed, settings, ds)


def _refit(
    aligned: np.ndarray, parts: list[int], cents: np.ndarray, ds: DecoderSettings
) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
    """One refit to the measured centroids ``cents`` (P, 2) [px].

    A rectangle's image centroid is not the image of its centre: the offset
    between the two, predicted by the aligned homography (already within a
    pixel or so, and the offset is second order in the part's size), is
    taken off the measured centroids before one linear fit, as the decoder's
    ``_fit_parts`` does with its own first fit. Four or more parts: a
    homography. Three (codes with one white slot): too few for a
    homography, so the prediction keeps the perspective and an affine map,
    exact on the three, moves the parts' predicted centroids onto the
    measured ones.

    Returns:
        (image_H_sign or None, the centroid offsets taken off (P, 2) [px],
        the parts' corners and centres under ``aligned`` (5P, 2) [px]:
        corners first, 4 per part).
    """
    src, _, _, prepared, _ = _parts_geometry(parts)
    n = len(parts)
    # Corners and centres in one projection.
    aligned_px = _project(aligned, _corners_and_centres(tuple(parts)))
    predicted = polygon_centroids(aligned_px[: 4 * n].reshape(n, 4, 2))
    if n < 4:
        a = cv2.getAffineTransform(predicted.astype(np.float32), cents.astype(np.float32))
        if not np.isfinite(a).all():
            return None, 0.0, aligned_px
        return np.vstack([a, [0.0, 0.0, 1.0]]) @ aligned, 0.0, aligned_px
    offset = predicted - aligned_px[4 * n :] if ds.perspective_correction else 0.0
    return fit_homography(src, cents - offset, prepared), offset, aligned_px


@functools.cache
def _corners_and_centres(parts: tuple[int, ...]) -> np.ndarray:
    """(5P, 2) the parts' corners (4 per part, in order) then their centres [diameters]."""
    return np.concatenate([_PART_QUADS[list(parts)].reshape(-1, 2), _PART_CENTRES[list(parts)]])


def _refit_and_check(
    g: np.ndarray,
    aligned: np.ndarray,
    code: str,
    parts: list[int],
    first,
    major: float,
    allowed: frozenset[str] | None,
    settings: VerifySettings,
    ds: DecoderSettings,
) -> Verification:
    """Steps 3-4 of the module docstring, from the aligned prediction."""
    found = _part_centroids(g, aligned, parts, first.black, first.white, 1.5)
    if found is None:
        return _miss(VerifyOutcome.NOT_FOUND)
    cents, white_area = found
    h_ref, offset, aligned_px = _refit(aligned, parts, cents, ds)
    if h_ref is None:
        return _miss(VerifyOutcome.NOT_FOUND)
    n = len(parts)
    # The keypoints; the first two parts are the centre and the directional one.
    uv = _project(h_ref, _PART_CENTRES[parts])
    rms = float("nan")  # an exact fit (four parts) or the affine one has no residual
    if n > 4:
        rms = float(np.sqrt(((uv + offset - cents) ** 2).sum(axis=1).mean()))
    limit = settings.max_residual_px + settings.max_residual_frac * major
    moved = float(np.abs(uv[:2] - aligned_px[4 * n : 4 * n + 2]).max())
    if (math.isfinite(rms) and rms > limit) or moved > settings.max_moved * major:
        return _miss(VerifyOutcome.RESIDUAL)
    reading = _read_slots(g, h_ref, ds)
    if reading.code is None or reading.code != code:
        return _miss(VerifyOutcome.SLOT_DIFFERS, reading.reason)
    region = _Region(
        gray=g,
        holes=[],
        centroids_px=np.zeros((0, 2)),
        cut=_LazyFlag(lambda: False),
        rim_contour=None,  # no contour: every dark band counts as evidence (stricter)
        disc_area_px=None,
        disc_centre_px=None,
        allowed=allowed,
        settings=ds,
    )
    accepted, occ, reason = _accept_code(region, h_ref, reading, major)
    if accepted != code or occ is None or occ.covered_parts or "x" in occ.pattern:
        return _miss(VerifyOutcome.REFUSED, reason if accepted is None else DecodeReason.OCCLUDED)
    if occ.disturbance > settings.max_disturbance:
        # Something dark across a white part (a conductor, dirt): the decoder's
        # contours may see it split, and it may refuse the sign; so does this.
        return _miss(VerifyOutcome.REFUSED, DecodeReason.OCCLUDED)
    ellipse = _safe_disc_ellipse(h_ref)
    if ellipse is None:
        return _miss(VerifyOutcome.NOT_VERIFIABLE)
    deficit = _fill_deficit(aligned, parts, white_area, np.ones(n, bool))
    # What the image shows around each part, for its keypoint's sigma, as the
    # decoder measures it for an accepted reading (no part is covered here).
    names = [_PART_NAMES[p] for p in parts]
    measured = measure_parts(g, h_ref, names, _PART_QUADS[parts], cents, first.black, first.white)
    measured = replace(
        measured, unfitted_px=unfitted_residuals_px(h_ref, names, _PART_QUADS[parts], cents, uv)
    )
    disturbance = max(occ.disturbance, deficit)
    result = _reading_result(
        code, parts, uv, h_ref, ellipse, first, rms, False, disturbance, (), measured
    )
    return Verification(VerifyOutcome.VERIFIED, result)


def _part_centroids(
    gray: np.ndarray,
    image_H_sign: np.ndarray,
    parts: list[int],
    black: float,
    white: float,
    pad_px: float,
) -> tuple[np.ndarray, np.ndarray] | None:
    """``decoder._subpixel_centroids`` for a verification, which needs every part.

    The same windows, labels and weights; the sums per part (area, first
    moments) as three weighted ``np.bincount`` over the labels instead of a
    masked ``cv2.moments`` per part (same sums in double precision, another
    order: centroids equal to 1e-13 px; 67 against 103 us on the bench's
    crops).

    Returns:
        (P, 2) centroids [px] and (P,) white areas [px^2], or None when a
        part's window leaves the image or holds no white (the decoder's
        "not measured").
    """
    h, w = gray.shape
    n = len(parts)
    steps = _project(image_H_sign, _UNIT_STEPS).tolist()
    (ax, ay), (bx, by) = [(u - steps[0][0], v - steps[0][1]) for u, v in steps[1:]]
    scale = math.sqrt(abs(ax * by - ay * bx)) / 0.01  # px per diameter
    grow = min(pad_px / max(scale, 1e-9), 0.035)
    _, _, flat_quads, _, flat_grow = _parts_geometry(parts)
    corners = _project(image_H_sign, flat_quads + grow * flat_grow)
    # The union of the parts' windows (floor and ceil commute with min and max).
    (u0, v0), (u1, v1) = corners.min(axis=0).tolist(), corners.max(axis=0).tolist()
    # floor(u0) >= 0 and ceil(u1) + 1 <= w, as the decoder tests each window
    # (NaN compares false: not measured).
    if not (u0 >= 0 and v0 >= 0 and u1 <= w - 1 and v1 <= h - 1):
        return None
    x0, y0, x1, y1 = math.floor(u0), math.floor(v0), math.ceil(u1) + 1, math.ceil(v1) + 1
    polys = corners.reshape(n, 4, 2)
    labels = np.zeros((y1 - y0, x1 - x0), np.uint8)
    pts = np.round((polys - (x0, y0)) * 16).astype(np.int32)
    for i in range(n):
        cv2.fillConvexPoly(labels, pts[i], i + 1, lineType=cv2.LINE_8, shift=4)
    wt = gray[y0:y1, x0:x1] - np.float32(black)
    wt *= np.float32(1.0 / max(white - black, 1e-6))
    np.clip(wt, 0.0, 1.0, out=wt)
    lab = labels.ravel()
    m00 = np.bincount(lab, wt.ravel(), n + 1)[1:]
    if not (m00 > 0).all():
        return None
    # Pixel indices in float64: the products are exact, as in cv2.moments.
    m10 = np.bincount(lab, (wt * np.arange(x1 - x0, dtype=float)).ravel(), n + 1)[1:]
    m01 = np.bincount(lab, (wt * np.arange(y1 - y0, dtype=float)[:, None]).ravel(), n + 1)[1:]
    cents = np.empty((n, 2))
    cents[:, 0] = x0 + m10 / m00
    cents[:, 1] = y0 + m01 / m00
    return cents, m00
