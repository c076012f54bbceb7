"""Sign detection (paper §2.2): Haar cascade windows, the paper's merge, then the decoder.

Modes:

* ``paper``: the paper's procedure. Every window from 24 px up to half the
  image (``cv2.CascadeClassifier.detectMultiScale`` with ``minNeighbors=0``
  returns the raw windows), then merged.

Merges (``DetectorSettings.merge``): ``paper_merge`` is §2.2 (same-size
windows within R = half a window merged when at least T = 2 agree; merged
windows of different sizes that overlap enough become one);
``cv2.groupRectangles`` (T = 2) is the default, chosen on the evaluation.
* ``fast``: the same cascade and merge, searched only around candidates.
  A cheap stage on a half-size frame finds where a sign's black disc can be
  (pixels among the frame's darkest with bright ones next to them, i.e. the
  black disc with its white parts; lattice, sky and ground drop out); the
  cascade then runs on those regions only, at the window sizes that match
  the blob, magnified for signs smaller than the 24 px window
  (``fast_small_min_px``), which the paper's sliding window cannot see.
* tracking (``detect_tracked``): given each sign's predicted centre and
  diameter (from a previous pose), search only a region around it with the
  window size restricted to the predicted one; when signs are lost the full
  frame is searched in ``fast`` mode (``fell_back``). A predicted sign
  that neither verifies nor is found by the search is decoded in full on
  its predicted box, moved by the offset of the nearest sign found
  (``track_decode_predicted``; kept only when it reads the predicted code:
  the cascade does not fire on every sign a real lens and codec leave).
  The detector keeps no state between frames: the caller says when a
  partial find is not enough (``refresh``), so its results depend only on
  its arguments (and a flight's observations not on which thread ran which
  frame).

Each merged region goes to ``frontend.decoder.decode_region``; a region many
windows agree on that the decoder refuses for its crop (the rim cut, the
parts inconsistent, no location rectangle) is tried again with tighter and
wider crops (``retry_margins``: the decoder's verdict depends on how much
background the crop holds, most for signs near the 24 px window; full-frame
searches only); regions that still do not decode are dropped and counted
(``n_undecoded``). Decoded signs are
``frontend.observations.SignObservation``; ``Detector`` is the protocol the
pipeline calls (``SignDetector`` here, a replay of known answers in tests).
"""

from __future__ import annotations

import enum
import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import NamedTuple, Protocol

import cv2
import numpy as np
from signpose.frontend.decoder import (
    DecodeReason,
    DecodeResult,
    DecoderSettings,
    _translated,
    decode_region,
)
from signpose.frontend.observations import DEFAULT_SIGMA_PX, FrameObservations, SignObservation
from signpose.frontend.verify import VerifyOutcome, verify_sign

from signpose.core.errors import InputError

WINDOW_PX = 24
MAX_REASON_CHARS = 200  # of OpenCV's message, in an error naming a bad cascade file
# Refusals that are about the sign, not the crop: another crop of a region the
# decoder found occluded (or read as a code the map lacks) would only be a
# second guess at the same verdict (the decoder itself stops there too).
NOT_RETRIED = frozenset({DecodeReason.OCCLUDED, DecodeReason.CODE_NOT_IN_MAP})


# A region the decoder did not read: its box (x, y, w, h) [px] and why.
Refusal = tuple[tuple[float, float, float, float], DecodeReason]
# A region read as a code the map lacks: that code and the box (x, y, w, h) [px].
Unknown = tuple[str, tuple[float, float, float, float]]


class DetectorMode(enum.StrEnum):
    """How a frame was searched; the value is the token written to files."""

    FAST = "fast"  # full frame, cascade around dark-disc candidates
    PAPER = "paper"  # full frame, the paper's sliding window
    TRACK = "track"  # around predicted signs (full frame in fast mode when lost)


# The full-frame modes a user can ask for.
MODES: tuple[str, ...] = (DetectorMode.FAST.value, DetectorMode.PAPER.value)


class _Predicted(NamedTuple):
    code: str
    center_px: tuple[float, float]
    diameter_px: float


class PredictedSign(_Predicted):
    """Where a sign of the map should appear in the next image.

    A (code, center_px, diameter_px) tuple (it unpacks as three), with the
    predicted homography as an attribute beside it.

    Attributes:
        code: the sign's code.
        center_px: (u, v) predicted centre, raw image pixels.
        diameter_px: predicted disc diameter [px].
        image_H_sign: (3, 3) predicted homography from the sign plane (disc
            diameter units, x right, y up, origin at the centre) to raw
            pixels, or None. With it the sign is verified there
            (``frontend.verify``) before any search.
    """

    image_H_sign: np.ndarray | None

    def __new__(
        cls,
        code: str,
        center_px: tuple[float, float],
        diameter_px: float,
        image_H_sign: np.ndarray | None = None,
    ) -> PredictedSign:
        self = super().__new__(cls, code, center_px, diameter_px)
        self.image_H_sign = image_H_sign
        return self


# Sign-plane points [disc diameters] whose predicted images give a
# prediction's homography (``homography_from_points``): around the slot ring.
HOMOGRAPHY_POINTS = np.array([[-0.35, -0.35], [0.35, -0.35], [0.35, 0.35], [-0.35, 0.35]])


def homography_from_points(image_px: np.ndarray) -> np.ndarray | None:
    """image_H_sign from the (4, 2) raw pixels of ``HOMOGRAPHY_POINTS``, or None."""
    px = np.asarray(image_px, np.float32).reshape(4, 2)
    if not np.isfinite(px).all():
        return None
    h = cv2.getPerspectiveTransform(HOMOGRAPHY_POINTS.astype(np.float32), px)
    if not np.isfinite(h).all() or abs(h[2, 2]) < 1e-12:
        return None
    return h / h[2, 2]


def bundled_cascade_path() -> Path:
    """Path of the trained cascade shipped as package data."""
    return Path(str(resources.files("signpose.frontend") / "models" / "signs_cascade.xml"))


@dataclass(frozen=True)
class DetectorSettings:
    """Detector tuning.

    Attributes:
        scale_factor: window growth between pyramid levels (paper mode and the
            full-frame part of fast mode).
        max_size_frac: largest window as a fraction of the smaller image side
            (the paper: half the image), paper mode.
        fast_max_size_frac: the same in fast mode: a drone 2 m from a 0.8 m
            sign sees it 650 px across at 1080p (found up to about 950 px).
        merge: "paper" (§2.2, ``paper_merge``) or "group"
            (``cv2.groupRectangles``). Default "group": on the held-out
            evaluation (scripts/eval_detector.py) both find the same signs
            (within 0.1 %), and "group" leaves 40 % fewer regions for the
            decoder to reject.
        merge_radius_frac: R, as a fraction of the window size (paper: 1/2).
        merge_min_count: T, windows that must agree (paper: 2).
        merge_overlap: overlap (intersection over union) above which windows
            of different sizes are one sign.
        group_eps: ``cv2.groupRectangles`` eps for merge="group".
        fast_dark_margin: candidate pixels are at most this much brighter than
            the frame's 0.5th percentile [grey levels] (a sign's black is
            among the darkest things in view).
        fast_local_tiles: (columns, rows) of tiles in which the dark threshold
            is also taken locally (tile's 0.5th percentile + ``fast_dark_margin``,
            interpolated between tile centres), so that a sign in front of a
            bright part of a photograph is a candidate even when a darker
            region elsewhere sets the frame's percentile; (0, 0) = global only.
        fast_local_raise: the local threshold is at most this much above the
            frame's [grey levels] (a sign's black stays dark; busy mid-grey
            texture does not become candidates).
        fast_dark_mass_share: the local threshold and the grey discs are used
            only when pixels at the frame's dark level cover more than this
            share of it (signs' paint alone covers a few per cent).
        fast_grey_discs: also take compact grey blobs with white parts inside,
            standing out of pixels at most ``fast_black_margin`` above the
            darkest, as candidates (a sign in front of a black sky, darker
            than its paint).
        fast_min_range: ...in blobs with pixels this much brighter in or
            next to them (a sign spans black to white) [grey levels].
        fast_roi_grow: a candidate blob's box grows by this fraction of its
            size (plus 8 px) on each side before the cascade searches it.
        fast_scale: (lo, hi) window sizes searched around a candidate,
            relative to its blob's longest side.
        fast_scale_dark: ``fast_scale`` in frames with a dark mass
            (``dark_threshold``: a photograph's shadows, a black sky), where
            the dark background joins the signs' blobs and their sizes say
            less (scripts/eval_detector.py --photo-flights: detection of
            the decodable signs 80 -> 94 % on four photo flights, 0 wrong).
        fast_small_min_px: smallest sign fast mode looks for (windows below
            24 px via magnified candidate areas); 0 disables.
        track_margin: tracking ROI half-side, in predicted diameters, beyond
            the predicted radius.
        track_anchor_margin: the same for the one sign searched to learn a
            frame's prediction offset when the first verification fails
            (the camera's rotation since the predicted pose moves every
            sign alike, often by more than ``track_margin``).
        track_scale: (lo, hi) window size range relative to the predicted
            diameter.
        track_scale_factor: window growth between sizes when tracking.
        track_decode_predicted: a predicted sign that neither verifies nor
            is found by the tracked search is decoded in full on its
            predicted box (moved by the offset of the nearest sign found;
            ``retry_thresholds``), and kept when the decoder reads the
            predicted code there. On scripts/eval_flight.py's quick flights
            (a real lens, JPEG, vibration) every unhidden sign a run missed
            although the decoder reads it on its true box (27) had been
            predicted, and the cascade fired on none of them, in the tracked
            region nor in the full-frame search that followed; with this,
            2 are missed (their predictions more than 0.4 diameters off
            after the offset). It costs a decode per sign left unverified
            and unfound in a tracked frame: bench_frontend's hard flight
            (members across the signs) about 5 ms per tracked frame.
        track_min_found_frac: tracking searches the full frame when it finds
            fewer than this fraction of the predicted signs (with ``refresh``:
            when it misses any).
        retry_margins: a refused region is decoded again with these crop
            margins (``DecoderSettings.region_margin``, fractions of the box
            per side), in turn until one reads; () disables. A tight crop
            drops the background that joins a small sign's disc, a wide one
            holds a rim the box cut (scripts/eval_detector.py --frames 60:
            recall 88.9 -> 91.8 %, 0 wrong; photo flights +12 signs of 480).
        retry_small_margins: regions at most ``retry_small_px`` are then tried
            with these margins too (+14 of the orbit's 1020 signs of 18-30 px
            in the 300-frame evaluation, nothing elsewhere; for all regions
            it cost bench_frontend's hard flight 20 % of fast mode's time).
        retry_thresholds: the decoder's binarisations tried on a retry
            (``DecoderSettings.thresholds``): on the evaluation's flights
            (held-out, photo, hard) these read every sign that all five
            read, for 70-80 % of the time ("otsu" and "open" read none).
        retry_min_windows: only regions at least this many cascade windows
            agree on are retried (every region that read on a retry in the
            evaluation had >= 20 in 9 of 10 cases; the weak regions of
            photographs' textures do not pay for two more decodes each).
            Full-frame searches only: tracking's searched regions are signs
            its verification refused (mostly occluded ones, which a retry
            does not read: scripts/bench_frontend.py's hard flight, 0 more
            found for +25 % of tracking's time).
        retry_small_px: regions at most this big [px] are retried whatever
            their window count: the sliding window's smallest (24 px)
            windows fit a sign near that size only a few times, and such
            crops are cheap to decode (paper mode's 18-30 px signs).
        retry_max_regions: at most this many regions of a frame are retried,
            those most windows agree on first: a frame full of sign-like
            texture (a photograph of galaxies: 200 refused regions) does not
            pay for two more decodes of each (on eval_detector's flights at
            most 12 in a frame (a blurred orbit frame), 10 on the photo
            flights, 65-80 in front of the galaxies).
        decode: run the decoder (False: return raw merged regions, for tests).
    """

    scale_factor: float = 1.1
    max_size_frac: float = 0.5
    fast_max_size_frac: float = 0.9
    merge: str = "group"
    merge_radius_frac: float = 0.5
    merge_min_count: int = 2
    merge_overlap: float = 0.4
    group_eps: float = 0.2
    fast_dark_margin: float = 25.0
    fast_local_tiles: tuple[int, int] = (8, 6)
    fast_local_raise: float = 20.0
    fast_dark_mass_share: float = 0.08
    fast_grey_discs: bool = True
    fast_black_margin: float = 10.0
    fast_min_range: int = 50
    fast_roi_grow: float = 0.6
    fast_scale: tuple[float, float] = (0.6, 1.9)
    fast_scale_dark: tuple[float, float] = (0.4, 2.5)
    fast_small_min_px: int = 16
    track_margin: float = 0.4
    track_anchor_margin: float = 3.0
    track_scale: tuple[float, float] = (0.8, 1.4)
    track_scale_factor: float = 1.12
    track_decode_predicted: bool = True
    track_min_found_frac: float = 0.5
    retry_margins: tuple[float, ...] = (0.05, 0.5)
    retry_small_margins: tuple[float, ...] = (0.1,)
    retry_thresholds: tuple[str, ...] = ("mean", "high", "adaptive")
    retry_min_windows: int = 20
    retry_small_px: float = 28.0
    retry_max_regions: int = 12
    decode: bool = True


@dataclass(frozen=True)
class DetectionResult:
    """All signs found in one image.

    Attributes:
        detections: the decoded signs (``bbox_px`` is the merged detector
            region, ``score`` in [0, 1] from agreeing windows and decoder
            quality), ordered by code then position. One per sign: regions
            that decode to the same code within a sign's radius of each other
            are one sign (the best reading is kept); the same code at two
            places is reported twice, for the caller to settle.
        n_regions: merged regions the cascade found.
        n_undecoded: regions dropped because they did not decode.
        timing: stage name -> milliseconds ("cascade", "merge", "decode", "total";
            "retry", the crop retries' part of "decode", when there were any).
        mode: how the frame was searched.
        fell_back: tracking lost a predicted sign and searched the full frame.
        regions: (n_regions, 4) merged regions (x, y, w, h) before decoding.
        verifications: tracking only: the outcome of each prediction that
            carried a homography (``frontend.verify``), in prediction order;
            the verified ones are in ``detections`` without a search.
        unknown: (code read, region box (x, y, w, h) [px]) of each region the
            decoder refused only because the map has no sign of its code
            (``code_not_in_map``, after the crop retries; the code is the
            decoder's ``unknown_code``), ordered by code then position. One
            entry per sign: regions of one code centred within half a region
            of each other (overlapping regions of one sign; tracking's and
            the full frame's search) are one. Not in ``detections``, which
            do not depend on it.
    """

    detections: tuple[SignObservation, ...]
    n_regions: int
    n_undecoded: int
    timing: dict[str, float] = field(default_factory=dict)
    mode: DetectorMode = DetectorMode.FAST
    fell_back: bool = False
    regions: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    verifications: tuple[VerifyOutcome, ...] = ()
    unknown: tuple[Unknown, ...] = ()


class Detector(Protocol):
    """What the pipeline needs of a detector (``SignDetector``; a replay in tests)."""

    def detect(
        self, image: np.ndarray, codes: Iterable[str] | None = None, mode: str = "fast"
    ) -> DetectionResult:
        """Every sign of a whole image (``mode``: one of ``MODES``)."""
        ...

    def detect_tracked(
        self,
        image: np.ndarray,
        predictions: Sequence[PredictedSign],
        codes: Iterable[str] | None = None,
        refresh: bool = False,
    ) -> DetectionResult:
        """The signs around their predicted places (full frame when lost)."""
        ...


# --------------------------------------------------------------------------- merge


def _components(adjacent: np.ndarray) -> list[np.ndarray]:
    """Connected components of a symmetric boolean adjacency matrix."""
    n = adjacent.shape[0]
    label = -np.ones(n, int)
    comps = []
    for i in range(n):
        if label[i] >= 0:
            continue
        stack, members = [i], []
        label[i] = len(comps)
        while stack:
            j = stack.pop()
            members.append(j)
            for k in np.flatnonzero(adjacent[j] & (label < 0)):
                label[k] = len(comps)
                stack.append(k)
        comps.append(np.array(members))
    return comps


def paper_merge(
    rects: np.ndarray,
    radius_frac: float = 0.5,
    min_count: int = 2,
    overlap: float = 0.4,
) -> tuple[np.ndarray, np.ndarray]:
    """The paper's §2.2 merge of raw detector windows.

    Same-size windows whose centres lie within R = ``radius_frac`` x size of
    each other (chained) form a group; a group of at least T = ``min_count``
    windows becomes one window at their mean position, smaller groups are
    dropped. Then groups of different sizes whose overlap (intersection over
    union) exceeds ``overlap`` are one sign: their average position and size
    (weighted by their window counts) is the result.

    Args:
        rects: (N, 4) raw windows (x, y, w, h) [px].

    Returns:
        ((M, 4) merged windows as float (x, y, w, h), (M,) window counts).
    """
    rects = np.asarray(rects, float).reshape(-1, 4)
    if rects.shape[0] == 0:
        return np.zeros((0, 4)), np.zeros(0, int)
    merged, counts = [], []
    for size in np.unique(rects[:, 2]):
        r = rects[rects[:, 2] == size]
        c = r[:, :2] + r[:, 2:] / 2
        for comp in _radius_components(c, radius_frac * size):
            if comp.size >= min_count:
                merged.append(r[comp].mean(axis=0))
                counts.append(comp.size)
    if not merged:
        return np.zeros((0, 4)), np.zeros(0, int)
    m = np.array(merged)
    n = np.array(counts)
    # Different sizes: greedily, strongest group first, join a group to the first
    # kept sign it overlaps by more than ``overlap`` (intersection over union);
    # a sign's box is the count-weighted average of its groups.
    out = np.zeros((len(m), 4))
    out_n = np.zeros(len(m))
    k = 0
    for i in np.argsort(-n, kind="stable"):
        hit = np.flatnonzero(_iou(out[:k], m[i]) > overlap)
        if hit.size:
            j = hit[0]
            out[j] = (out[j] * out_n[j] + m[i] * n[i]) / (out_n[j] + n[i])
            out_n[j] += n[i]
        else:
            out[k], out_n[k] = m[i], n[i]
            k += 1
    return out[:k], out_n[:k].astype(int)


def _iou(boxes: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(K,) intersection over union of (K, 4) boxes with box ``b`` (x, y, w, h)."""
    iw = np.minimum(boxes[:, 0] + boxes[:, 2], b[0] + b[2]) - np.maximum(boxes[:, 0], b[0])
    ih = np.minimum(boxes[:, 1] + boxes[:, 3], b[1] + b[3]) - np.maximum(boxes[:, 1], b[1])
    inter = np.clip(iw, 0, None) * np.clip(ih, 0, None)
    return inter / (boxes[:, 2] * boxes[:, 3] + b[2] * b[3] - inter)


def _radius_components(centers: np.ndarray, radius: float) -> list[np.ndarray]:
    """Groups of points chained by distances <= ``radius`` (index arrays).

    Small sets use the exact distance matrix; large ones (thousands of raw
    windows from a weak cascade) a raster of discs (exact up to a pixel of
    the raster, i.e. about a sixth of the radius).
    """
    n = centers.shape[0]
    if n <= 400:
        d2 = ((centers[:, None, :] - centers[None, :, :]) ** 2).sum(-1)
        return _components(d2 <= radius * radius)
    # Discs of radius R/2 touch when their centres are within R: label the
    # connected blobs of a raster of such discs (3 px radius).
    scale = 3.0 / max(radius / 2, 1e-9)
    p = np.round((centers - centers.min(axis=0)) * scale).astype(int) + 4
    mask = np.zeros((p[:, 1].max() + 5, p[:, 0].max() + 5), np.uint8)
    for x, y in p.tolist():
        cv2.circle(mask, (x, y), 3, 255, -1)
    _, labels = cv2.connectedComponents(mask, connectivity=8)
    roots = labels[p[:, 1], p[:, 0]]
    return [np.flatnonzero(roots == r) for r in np.unique(roots)]


def group_merge(
    rects: np.ndarray, min_count: int = 2, eps: float = 0.2
) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV's ``groupRectangles`` (clusters of >= ``min_count`` windows) for comparison."""
    rects = np.asarray(rects).reshape(-1, 4)
    if rects.shape[0] == 0:
        return np.zeros((0, 4)), np.zeros(0, int)
    out, weights = cv2.groupRectangles(rects.astype(int).tolist(), min_count - 1, eps)
    if len(out) == 0:
        return np.zeros((0, 4)), np.zeros(0, int)
    return np.asarray(out, float), np.asarray(weights, int).ravel()


# --------------------------------------------------------------------------- detector

# Fast mode's openings of the dark pixels: square kernels' sides [half-frame px].
_OPENINGS = (5, 11)


def _opened_blobs(mask: np.ndarray, k: int) -> list[list[int]]:
    """(x, y, w, h, area) of the 8-connected blobs of ``mask`` opened by a k x k square.

    Computed on the box of ``mask``'s nonzero pixels grown by ``k // 2`` (the
    opening is 0 beyond it: an eroded pixel is a nonzero one), so opening
    and labelling cost what the dark pixels' box costs, not the whole half
    frame's; the same blobs, in the same order, as on the whole mask.
    With ``_blobs``, fast mode's candidate stage on scripts/bench_frontend.py's
    frames (median of 40): sim 9.0 -> 5.5 ms, hard 9.4 -> 5.2 ms.
    """
    x, y, w, h = cv2.boundingRect(mask)
    if w == 0 or h == 0:
        return []
    g = k // 2
    x0, y0 = max(x - g, 0), max(y - g, 0)
    x1, y1 = min(x + w + g, mask.shape[1]), min(y + h + g, mask.shape[0])
    opened = cv2.morphologyEx(mask[y0:y1, x0:x1], cv2.MORPH_OPEN, np.ones((k, k), np.uint8))
    return [[bx + x0, by + y0, bw, bh, a] for bx, by, bw, bh, a in _blobs(opened)]


def _blobs(mask: np.ndarray) -> list[list[int]]:
    """(x, y, w, h, area) of the 8-connected blobs of ``mask``, background left out.

    Grana's block-based labelling (``CCL_GRANA``): the same blobs in the same
    order as ``connectedComponentsWithStats``' default (Bolelli's Spaghetti)
    on tests/test_detector.py's masks and the 40 opened masks of 20 of the
    bench's frames, where it took 0.9 against 2.4 ms per 960 x 540 half frame
    (one thread: the statistics, not the labels, cost the default its time).
    """
    _, _, stats, _ = cv2.connectedComponentsWithStatsWithAlgorithm(
        mask, 8, cv2.CV_32S, cv2.CCL_GRANA
    )
    return stats[1:].tolist()


def _as_gray(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
    if img.dtype != np.uint8:
        img = np.clip(np.round(img), 0, 255).astype(np.uint8)
    return img


class SignDetector:
    """The trained cascade plus the paper's merge and the decoder.

    Args:
        cascade_path: OpenCV cascade XML; None = the bundled model.
        settings: tuning.
    """

    def __init__(
        self, cascade_path: str | Path | None = None, settings: DetectorSettings | None = None
    ) -> None:
        path = Path(cascade_path) if cascade_path is not None else bundled_cascade_path()
        if not path.is_file():
            raise InputError(f"{path}: cascade file not found")
        self.cascade_path = path
        self.settings = settings or DetectorSettings()
        try:
            self._cascade = cv2.CascadeClassifier(str(path))
        except (cv2.error, SystemError) as exc:  # OpenCV's XML parser on a malformed file
            why = " ".join(str(exc.__cause__ or exc).split("error: ", 1)[-1].split())
            raise InputError(
                f"{path}: not a readable OpenCV cascade XML ({why[:MAX_REASON_CHARS]})"
            ) from None
        if self._cascade.empty():
            raise InputError(f"{path}: not an OpenCV cascade classifier XML")
        self._retry_settings = tuple(
            DecoderSettings(region_margin=m, thresholds=self.settings.retry_thresholds)
            for m in self.settings.retry_margins
        )
        self._predicted_settings = DecoderSettings(thresholds=self.settings.retry_thresholds)
        self._retry_small_settings = self._retry_settings + tuple(
            DecoderSettings(region_margin=m, thresholds=self.settings.retry_thresholds)
            for m in self.settings.retry_small_margins
        )
        w, h = self._cascade.getOriginalWindowSize()
        if w != h:  # signs are discs: a cascade of w x h windows was trained on something else
            raise InputError(
                f"{path}: the cascade's window is {w}x{h} px, not square; not a sign detector "
                "(train one with 'signpose train-detector')"
            )

    # -- raw windows -----------------------------------------------------------

    def _raw(
        self,
        gray: np.ndarray,
        min_px: float,
        max_px: float,
        scale_factor: float | None = None,
    ) -> np.ndarray:
        """(N, 4) raw windows of sizes in [min_px, max_px] (sizes in ``gray`` pixels)."""
        sf = scale_factor or self.settings.scale_factor
        lo = max(WINDOW_PX, int(math.floor(min_px)))
        hi = min(int(math.ceil(max_px)), min(gray.shape[:2]))
        if hi < lo:
            return np.zeros((0, 4), int)
        rects = self._cascade.detectMultiScale(
            gray, scaleFactor=sf, minNeighbors=0, minSize=(lo, lo), maxSize=(hi, hi)
        )
        return np.asarray(rects, int).reshape(-1, 4)

    def _raw_scaled(
        self, gray: np.ndarray, zoom: float, min_px: float, max_px: float, sf: float | None = None
    ) -> np.ndarray:
        """Raw windows of ``gray`` resized by ``zoom``, in ``gray`` pixels (float)."""
        if abs(zoom - 1.0) < 1e-6:
            return self._raw(gray, min_px, max_px, sf).astype(float)
        interp = cv2.INTER_AREA if zoom < 1 else cv2.INTER_LINEAR
        small = cv2.resize(gray, None, fx=zoom, fy=zoom, interpolation=interp)
        r = self._raw(small, min_px * zoom, max_px * zoom, sf).astype(float)
        return r / zoom

    def raw_windows(self, gray: np.ndarray, mode: str = "paper") -> np.ndarray:
        """(N, 4) raw cascade windows (x, y, w, h) [px] of a whole image."""
        gray = _as_gray(gray)
        if mode not in MODES:
            raise InputError(f"unknown detection mode {mode!r}: use one of {', '.join(MODES)}")
        if mode == "paper" or min(gray.shape) < 96:
            max_px = max(WINDOW_PX, self.settings.max_size_frac * min(gray.shape))
            # OpenCV's worker threads append windows in the order they finish:
            # sorted, the merge (and so the output) does not depend on it.
            return np.unique(self._raw(gray, WINDOW_PX, max_px), axis=0)
        return self._fast_raw(gray)

    def candidate_rois(self, gray: np.ndarray) -> list[tuple[int, int, int, int, float]]:
        """Fast mode's candidates (see ``_candidates``)."""
        return self._candidates(gray)[0]

    def _candidates(self, gray: np.ndarray) -> tuple[list[tuple[int, int, int, int, float]], bool]:
        """Fast mode's candidates: where a sign's black disc can be, and its size.

        On a half-size frame, pixels whose 3 x 3 minimum is among the darkest
        of the frame or of their part of it (``dark_threshold``) are opened
        (conductors and thin bars vanish) and grouped into blobs;
        compact blobs with bright pixels in or next to them (grey range >=
        ``fast_min_range``) are candidate discs. In front of a black
        background (a night sky, a deep shadow) the disc is the brighter
        thing: compact dark grey blobs with white parts inside are
        candidates too (``fast_grey_discs``).

        Returns:
            (x, y, w, h, blob_px) per candidate: the region to search [px]
            (the blob's box grown by ``fast_roi_grow`` of its size + 8 px) and
            the blob's longest side [px], which sets the window sizes; and
            whether the frame has a dark mass (``dark_threshold``).
        """
        s = self.settings
        h, w = gray.shape
        half = cv2.resize(gray, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
        low = cv2.erode(half, np.ones((3, 3), np.uint8))
        high = cv2.dilate(half, np.ones((7, 7), np.uint8))
        thr, dark_mass = self.dark_threshold(low)
        dark = (low <= thr).astype(np.uint8)
        rois: list[tuple[int, int, int, int, float]] = []
        # Opening removes conductors and thin bars, also where they touch a
        # sign; a wider opening frees big signs from thicker (near) conductors.
        for k in _OPENINGS:
            for bx, by, bw, bh, area in _opened_blobs(dark, k):
                # A disc's blob is compact: it fills its box and is at most ~3:1
                # (65 degree view); conductors and lattice bars are long and thin.
                if area < 0.3 * bw * bh or max(bw, bh) > 3 * min(bw, bh) or max(bw, bh) < 3:
                    continue
                # Its white parts (or the background) are bright next to the
                # black: its own black (its dark pixels' median), not the
                # threshold, which a backlit or dim frame puts far above it.
                dark_thr = float(thr[by + bh // 2, bx + bw // 2])
                box = (slice(by, by + bh), slice(bx, bx + bw))
                black = min(dark_thr, float(np.median(low[box][dark[box] > 0])))
                if int(high[box].max()) - black < s.fast_min_range:
                    continue
                self._add_roi(rois, (bx, by, bw, bh), (h, w))
        if s.fast_grey_discs and dark_mass:
            # A black sky is darker than the paint: the disc stands out of the
            # pixels barely above the darkest.
            black_thr = thr - s.fast_dark_margin + s.fast_black_margin
            for box in self._grey_discs(low, half, high, black_thr):
                self._add_roi(rois, box, (h, w))
        return rois, dark_mass

    def _add_roi(
        self,
        rois: list[tuple[int, int, int, int, float]],
        box: tuple[int, int, int, int],
        shape: tuple[int, int],
    ) -> None:
        """Append the search region of a candidate disc (``box``: half-size x, y, w, h)."""
        s = self.settings
        h, w = shape
        x0, y0, bw, bh = (2 * v for v in box)
        size = float(max(bw, bh))
        if size > s.fast_max_size_frac * min(h, w) * 1.5:
            return  # a dark mass far bigger than any sign we look for
        grow = s.fast_roi_grow * size + 8
        x1, y1 = int(min(x0 + bw + grow, w)), int(min(y0 + bh + grow, h))
        x0, y0 = int(max(x0 - grow, 0)), int(max(y0 - grow, 0))
        roi = (x0, y0, x1 - x0, y1 - y0, size)
        if roi not in rois:
            rois.append(roi)

    def _grey_discs(
        self, low: np.ndarray, half: np.ndarray, high: np.ndarray, thr: np.ndarray
    ) -> list[tuple[int, int, int, int]]:
        """Half-size boxes of grey discs with white inside, on pixels darker than ``thr``.

        The pixels above ``thr`` are opened (lattice bars and conductors in
        front of the black vanish, as they do from the dark pixels) and
        grouped; compact groups whose median is dark grey (a star or a lit
        window is bright all over) with white parts inside are candidates.
        A bright frame is one group, far bigger than a sign, and gives none.
        """
        s = self.settings
        min_px = max(3, s.fast_small_min_px // 2)
        max_px = s.fast_max_size_frac * min(half.shape) * 0.75
        lit = cv2.morphologyEx(
            (low > thr).astype(np.uint8), cv2.MORPH_OPEN, np.ones((5, 5), np.uint8)
        )
        boxes = []
        for bx, by, bw, bh, area in _blobs(lit):
            if not min_px <= max(bw, bh) <= max_px or max(bw, bh) > 3 * min(bw, bh):
                continue
            if area < 0.5 * bw * bh:
                continue  # not a disc's outline
            level = float(thr[by + bh // 2, bx + bw // 2])
            # The disc's paint is dark grey and its white parts are bright.
            if float(np.median(half[by : by + bh, bx : bx + bw])) > level + s.fast_min_range:
                continue
            if int(high[by : by + bh, bx : bx + bw].max()) - level < 2 * s.fast_min_range:
                continue
            boxes.append((bx, by, bw, bh))
        return boxes

    def dark_threshold(self, low: np.ndarray) -> tuple[np.ndarray, bool]:
        """Grey level at or below which a pixel of ``low`` may be a sign's black.

        The frame's 0.5th percentile + ``fast_dark_margin``. When pixels that
        dark cover more than ``fast_dark_mass_share`` of the frame, the darkest
        thing in view is not (only) signs' paint but a photograph's shadow or
        a black sky: the threshold is then raised (by at most
        ``fast_local_raise``) where a tile's own 0.5th percentile is brighter,
        so that the signs in front of the frame's bright parts stay candidates.

        Returns:
            ((H, W) float32 threshold, whether the frame has such a dark mass).
        """
        s = self.settings
        sub = low[::4, ::4]
        p_dark, median = (float(v) for v in np.percentile(sub, (0.5, 50.0)))
        # A frame whose darkest 0.5 % is its own background (a plain sky behind
        # a sign smaller than 0.5 % of it) would mark the background dark and
        # join the disc to it: never above the frame's median less the margin,
        # unless that is below its darkest pixel plus the margin (a dark frame).
        cap = max(median - s.fast_dark_margin, float(low.min()) + s.fast_dark_margin)
        frame_thr = min(p_dark + s.fast_dark_margin, cap)
        nx, ny = s.fast_local_tiles
        dark_mass = float(np.mean(sub <= frame_thr)) > s.fast_dark_mass_share
        if not dark_mass or nx <= 0 or ny <= 0:
            return np.full(low.shape, frame_thr, np.float32), dark_mass
        th, tw = sub.shape[0] // ny, sub.shape[1] // nx
        tiles = sub[: ny * th, : nx * tw].reshape(ny, th, nx, tw).transpose(0, 2, 1, 3)
        tile_p = np.percentile(tiles.reshape(ny, nx, th * tw), 0.5, axis=-1).astype(np.float32)
        local = np.clip(tile_p + s.fast_dark_margin, frame_thr, frame_thr + s.fast_local_raise)
        size = (low.shape[1], low.shape[0])
        return cv2.resize(local, size, interpolation=cv2.INTER_LINEAR), dark_mass

    def _fast_raw(self, gray: np.ndarray) -> np.ndarray:
        s = self.settings
        h, w = gray.shape
        max_px = max(WINDOW_PX, s.fast_max_size_frac * min(h, w))
        rois, dark_mass = self._candidates(gray)
        # Where dark background joins the blobs, a blob's size says less about
        # the sign's: a wider range of window sizes.
        lo_f, hi_f = s.fast_scale_dark if dark_mass else s.fast_scale
        parts = [np.zeros((0, 4))]
        for x0, y0, rw, rh, size in rois:
            roi = gray[y0 : y0 + rh, x0 : x0 + rw]
            lo, hi = lo_f * size, min(hi_f * size, max_px)
            if hi >= WINDOW_PX and min(rw, rh) >= WINDOW_PX:
                r = self._raw(roi, max(lo, WINDOW_PX), hi).astype(float)
                r[:, :2] += (x0, y0)
                parts.append(r)
            if s.fast_small_min_px and lo < WINDOW_PX:
                # Signs below the 24 px window: the region magnified.
                up = WINDOW_PX / max(s.fast_small_min_px, lo)
                r = self._raw_scaled(roi, up, max(s.fast_small_min_px, lo), WINDOW_PX)
                r[:, :2] += (x0, y0)
                parts.append(r)
        # Overlapping regions report the same window twice: count it once.
        return np.unique(np.round(np.concatenate(parts), 3), axis=0)

    # -- merge + decode ----------------------------------------------------------

    def merge(self, rects: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Merged regions and their window counts (settings.merge)."""
        s = self.settings
        if s.merge == "group":
            return group_merge(np.round(rects), s.merge_min_count, s.group_eps)
        return paper_merge(rects, s.merge_radius_frac, s.merge_min_count, s.merge_overlap)

    def _finish(
        self,
        gray: np.ndarray,
        raw: np.ndarray,
        codes: Iterable[str] | None,
        mode: str,
        timing: dict[str, float],
        t0: float,
        fell_back: bool = False,
        retry: bool = True,
        refused: list[Refusal] | None = None,
    ) -> DetectionResult:
        t1 = time.perf_counter()
        regions, counts = self.merge(raw)
        t2 = time.perf_counter()
        timing["merge"] = timing.get("merge", 0.0) + (t2 - t1) * 1e3
        unknown: list[Unknown] = []
        dets, undecoded = self._decode(
            gray, regions, counts, codes, retry, refused, timing, unknown
        )
        t3 = time.perf_counter()
        timing["decode"] = timing.get("decode", 0.0) + (t3 - t2) * 1e3
        timing["total"] = (t3 - t0) * 1e3
        return DetectionResult(
            dets,
            len(regions),
            undecoded,
            timing,
            DetectorMode(mode),
            fell_back,
            regions,
            unknown=_one_per_region(unknown),
        )

    def _decode(
        self,
        gray: np.ndarray,
        regions: np.ndarray,
        counts: np.ndarray,
        codes: Iterable[str] | None,
        retry: bool = True,
        refused: list[Refusal] | None = None,
        timing: dict[str, float] | None = None,
        unknown: list[Unknown] | None = None,
    ) -> tuple[tuple[SignObservation, ...], int]:
        """(readings, one per sign; regions that did not read), with crop retries if
        ``retry``; each region that did not read appended to ``refused`` with its reason,
        each read as a code the map lacks to ``unknown`` with that code;
        the retries' time added to ``timing["retry"]`` [ms] (a part of the decoding's)."""
        codes = tuple(codes) if codes is not None else None
        if not self.settings.decode:
            raw = tuple(
                SignObservation(
                    code="",
                    keypoints_px={"center": (float(x + w / 2), float(y + h / 2))},
                    bbox_px=(float(x), float(y), float(w), float(h)),
                    sigma_px=float("inf"),
                    score=_window_score(n),
                )
                for (x, y, w, h), n in zip(regions, counts, strict=True)
            )
            return raw, 0
        boxes = [(float(x), float(y), float(w), float(h)) for x, y, w, h in regions]
        results = [decode_region(gray, box, codes) for box in boxes]
        if retry and any(
            self._retryable(r, b, n) for r, b, n in zip(results, boxes, counts, strict=True)
        ):
            t0 = time.perf_counter()
            results = self._retried(gray, boxes, counts, results, codes)
            if timing is not None:
                timing["retry"] = timing.get("retry", 0.0) + (time.perf_counter() - t0) * 1e3
        if refused is not None:
            refused += [
                (box, res.reason) for box, res in zip(boxes, results, strict=True) if not res.ok
            ]
        if unknown is not None:
            read = (_unknown(res, box) for box, res in zip(boxes, results, strict=True))
            unknown += [u for u in read if u is not None]
        found = [
            _observation(res, box, n)
            for res, box, n in zip(results, boxes, counts, strict=True)
            if res.ok
        ]
        return one_per_sign(found), sum(not res.ok for res in results)

    def _retried(
        self,
        gray: np.ndarray,
        boxes: list[tuple[float, float, float, float]],
        counts: np.ndarray,
        results: list[DecodeResult],
        codes: tuple[str, ...] | None,
    ) -> list[DecodeResult]:
        """``results`` with the refused regions read again (``_retry``): the
        strongest (most windows) first, at most ``retry_max_regions`` of them."""
        wanted = [i for i, r in enumerate(results) if self._retryable(r, boxes[i], counts[i])]
        wanted.sort(key=lambda i: (-float(counts[i]), i))
        out = list(results)
        for i in wanted[: self.settings.retry_max_regions]:
            out[i] = self._retry(gray, boxes[i], codes, results[i])
        return out

    def _retryable(
        self, res: DecodeResult, box: tuple[float, float, float, float], n_windows: float
    ) -> bool:
        """Whether a refused region is worth another crop (see ``retry_min_windows``)."""
        s = self.settings
        if res.ok or res.reason in NOT_RETRIED:
            return False
        return n_windows >= s.retry_min_windows or max(box[2], box[3]) <= s.retry_small_px

    def _retry(
        self,
        gray: np.ndarray,
        box: tuple[float, float, float, float],
        codes: tuple[str, ...] | None,
        res: DecodeResult,
    ) -> DecodeResult:
        """The first reading with the ``retry_margins`` crops in turn (a small region's
        then with ``retry_small_margins``), else the first retry's ``code_not_in_map``
        refusal (the sign read, as a code the map lacks), else ``res``."""
        small = max(box[2], box[3]) <= self.settings.retry_small_px
        unknown = None
        for settings in self._retry_small_settings if small else self._retry_settings:
            again = decode_region(gray, box, codes, settings)
            if again.ok:
                return again
            if unknown is None and again.reason == DecodeReason.CODE_NOT_IN_MAP:
                unknown = again
        return res if unknown is None else unknown

    def decode_box(
        self,
        gray: np.ndarray,
        box: tuple[float, float, float, float],
        n_windows: float,
        codes: Iterable[str] | None = None,
    ) -> DecodeResult:
        """The decoder's reading of one merged region, with the crop retries.

        Args:
            gray: (H, W) uint8 image.
            box: (x, y, w, h) region [px].
            n_windows: cascade windows merged into it (``retry_min_windows``).
            codes: the map's codes; None = all 16.

        Returns:
            The first reading (default crop, then ``retry_margins`` in turn);
            when none reads, the default crop's refusal.
        """
        codes = tuple(codes) if codes is not None else None
        gray = _as_gray(gray)
        box = tuple(float(v) for v in box)
        res = decode_region(gray, box, codes)
        return self._retry(gray, box, codes, res) if self._retryable(res, box, n_windows) else res

    # -- public ------------------------------------------------------------------

    def detect(
        self, image: np.ndarray, codes: Iterable[str] | None = None, mode: str = "fast"
    ) -> DetectionResult:
        """Detect and decode every sign in a whole image.

        Args:
            image: (H, W) uint8 grey image (BGR is converted).
            codes: the codes that may appear (the map's); None = all 16.
            mode: "fast" or "paper" (see the module docstring).
        """
        if mode not in MODES:
            raise InputError(f"unknown detection mode {mode!r}: use one of {', '.join(MODES)}")
        return self._search(_as_gray(image), codes, mode)

    def _search(
        self,
        gray: np.ndarray,
        codes: Iterable[str] | None,
        mode: str,
        refused: list[Refusal] | None = None,
    ) -> DetectionResult:
        """``detect`` on a grey image; the refused regions appended to ``refused``."""
        t0 = time.perf_counter()
        raw = self.raw_windows(gray, mode)
        timing = {"cascade": (time.perf_counter() - t0) * 1e3}
        return self._finish(gray, raw, codes, mode, timing, t0, refused=refused)

    def detect_tracked(
        self,
        image: np.ndarray,
        predictions: Sequence[PredictedSign],
        codes: Iterable[str] | None = None,
        refresh: bool = False,
    ) -> DetectionResult:
        """Search only around predicted signs; fall back to a full frame when they are lost.

        A prediction with a homography is first verified there
        (``frontend.verify.verify_sign``); only the others, and those whose
        verification disagrees, are searched with the cascade and decoded
        in full; the predicted signs still missing are decoded on their
        predicted boxes (``_read_at_predictions``), after the full-frame
        search too when there is one. The full frame is searched (fast mode) when fewer than
        ``track_min_found_frac`` of the predicted signs inside the image are
        found, or, with ``refresh``, when any of them is missing (the caller
        asks for that every few frames, so an occluded sign does not cost a
        full search every frame).

        Args:
            image: (H, W) uint8 grey image.
            predictions: the signs expected in view.
            codes: the codes that may appear; None = all 16.
            refresh: a missing predicted sign is enough to search the full frame.

        Returns:
            The detections; ``mode`` track, ``fell_back`` True when the full
            frame was searched.
        """
        t0 = time.perf_counter()
        gray = _as_gray(image)
        codes = tuple(codes) if codes is not None else None
        predictions = [
            p if isinstance(p, PredictedSign) else PredictedSign(*p) for p in predictions
        ]
        unknown: list[Unknown] = []  # the anchors' and the predicted boxes' readings
        verified, outcomes, rest = self._verify_predicted(gray, predictions, codes, unknown)
        t1 = time.perf_counter()
        raw = self._tracked_raw(gray, rest)
        timing = {"verify": (t1 - t0) * 1e3, "cascade": (time.perf_counter() - t1) * 1e3}
        refused: list[Refusal] = []
        res = self._finish(gray, raw, codes, "track", timing, t0, retry=False, refused=refused)
        t2 = time.perf_counter()
        tried: set[tuple[float, float, float, float]] = set()  # boxes decoded at predictions
        verified += self._read_at_predictions(
            gray, predictions, verified + list(res.detections), codes, refused, tried, unknown
        )
        timing["decode"] += timing["verify"] + (time.perf_counter() - t2) * 1e3
        res = replace(
            res,
            detections=one_per_sign(verified + list(res.detections)),
            verifications=outcomes,
            unknown=_one_per_region(unknown + list(res.unknown)),
        )
        if self._tracking_held(res, predictions, gray.shape, refresh):
            return res
        refused = []
        full = self._search(gray, codes, "fast", refused)
        t3 = time.perf_counter()
        verified += self._read_at_predictions(
            gray, predictions, verified + list(full.detections), codes, refused, tried, unknown
        )
        full.timing["decode"] += (time.perf_counter() - t3) * 1e3
        # Every stage of both searches (the verification's time kept too).
        timing = {
            k: res.timing.get(k, 0.0) + full.timing.get(k, 0.0) for k in res.timing | full.timing
        }
        timing["total"] = (time.perf_counter() - t0) * 1e3
        return DetectionResult(
            one_per_sign(verified + list(full.detections)),
            full.n_regions,
            full.n_undecoded,
            timing,
            DetectorMode.TRACK,
            True,
            full.regions,
            outcomes,
            _one_per_region(unknown + list(res.unknown) + list(full.unknown)),
        )

    def _verify_predicted(
        self,
        gray: np.ndarray,
        predictions: Sequence[PredictedSign],
        codes: tuple[str, ...] | None,
        unknown: list[Unknown] | None = None,
    ) -> tuple[list[SignObservation], tuple[VerifyOutcome, ...], list[PredictedSign]]:
        """(observations found, verification outcomes, predictions left to search);
        an anchor's regions read as codes the map lacks appended to ``unknown``.

        The predictions of one frame come from one predicted pose, so they are
        off by nearly the same image shift (mostly the camera's rotation since
        the pose): largest predicted sign first, each verification uses the
        offset of the nearest sign found so far. When none verifies at the
        predicted places, the region around the largest that failed
        (``track_anchor_margin``) is searched and decoded in full (an
        anchor): the predicted signs read there are found, and the others
        are verified again with their offsets. The predictions left to
        search carry the median offset.

        The anchor waits until every prediction has been tried: a failed
        first verification is as often the sign's own occluder as a shift
        of the whole frame (bench_frontend's hard flight: an anchor in 19 of
        38 tracked frames, most of them needless once the next sign verified).
        """
        order = [
            i
            for i in sorted(
                range(len(predictions)),
                key=lambda i: (-predictions[i].diameter_px, predictions[i].code, i),
            )
            if predictions[i].image_H_sign is not None and self.settings.decode
        ]
        found, offsets, outcomes, done = _verify_in_turn(gray, predictions, order, codes, [], [])
        if order and not offsets:
            anchor = self._anchor(gray, predictions[order[0]], predictions, done, codes, unknown)
            for j, obs in anchor:
                found.append(obs)
                offsets.append(_offset(obs, predictions[j]))
                done.add(j)
            if offsets:
                again = [i for i in order if i not in done]
                found, offsets, more, newly = _verify_in_turn(
                    gray, predictions, again, codes, found, offsets
                )
                outcomes |= more
                done |= newly
        shift = tuple(np.median(offsets, axis=0)) if offsets else (0.0, 0.0)
        left = [
            _shifted_prediction(predictions[i], shift)
            for i in range(len(predictions))
            if i not in done
        ]
        return found, tuple(outcomes[i] for i in sorted(outcomes)), left

    def _read_at_predictions(
        self,
        gray: np.ndarray,
        predictions: Sequence[PredictedSign],
        found: Sequence[SignObservation],
        codes: tuple[str, ...] | None,
        refused: Sequence[Refusal] = (),
        tried: set[tuple[float, float, float, float]] | None = None,
        unknown: list[Unknown] | None = None,
    ) -> list[SignObservation]:
        """The predicted signs the tracked search did not find, decoded in full on
        their predicted boxes (``track_decode_predicted``).

        The cascade does not fire on every sign a real lens and codec leave
        (scripts/eval_flight.py), but where the pose puts a sign the decoder
        often reads it. Only a reading of the predicted code counts: the
        decoder is given every code of the map, so another sign's code or an
        ambiguous reading is refused, never taken for the predicted one.
        Boxes not wholly inside the image are not tried (the decoder refuses
        a cut rim), nor the signs the decoder has already found occluded (or
        read as a code the map lacks) on a searched region centred within
        half a diameter (``refused``; as for the crop retries, another crop
        would be a second guess at the same verdict): on bench_frontend's
        hard flight (20 frames) 38 of the 70 boxes tried, one read, and on
        eval_flight's quick flights 2 of the 55 that read.
        A box in ``tried`` is not decoded again (a frame that falls back to the
        full-frame search reads its predictions twice: the box, crop and
        settings the same, so is the verdict); each box read is added. A box read
        as a code the map lacks is appended to ``unknown``.
        """
        if not self.settings.decode or not self.settings.track_decode_predicted:
            return []
        h, w = gray.shape
        predicted = {p.code: p for p in predictions}
        anchors = [o for o in found if o.code in predicted]
        offsets = [_offset(o, predicted[o.code]) for o in anchors]
        have = {d.code for d in found}
        out = []
        for p in predictions:
            du, dv = _offset_near(p, anchors, offsets)
            (u, v), d = (p.center_px[0] + du, p.center_px[1] + dv), p.diameter_px
            box = (u - 0.5 * d, v - 0.5 * d, d, d)
            inside = box[0] >= 0 and box[1] >= 0 and box[0] + d <= w and box[1] + d <= h
            if p.code in have or not (math.isfinite(u) and math.isfinite(v) and d > 0 and inside):
                continue
            if any(
                why in NOT_RETRIED and math.dist((x + 0.5 * bw, y + 0.5 * bh), (u, v)) < 0.5 * d
                for (x, y, bw, bh), why in refused
            ):
                continue
            if tried is not None:  # a box read before gives the same verdict again
                if box in tried:
                    continue
                tried.add(box)
            res = decode_region(gray, box, codes, self._predicted_settings)
            if unknown is not None and (u := _unknown(res, box)) is not None:
                unknown.append(u)
            if res.ok and res.code == p.code:
                # No cascade window vouches for it: scored as a verified sign is.
                out.append(_observation(res, box, math.inf))
        return out

    def _anchor(
        self,
        gray: np.ndarray,
        p: PredictedSign,
        predictions: Sequence[PredictedSign],
        done: set[int],
        codes: tuple[str, ...] | None,
        unknown: list[Unknown] | None = None,
    ) -> list[tuple[int, SignObservation]]:
        """(prediction index, reading) of the predicted signs read around ``p``.

        The region around ``p`` (``track_anchor_margin``) is searched and each
        of its regions decoded in full; a reading of a predicted code not yet
        found is that sign (the nearest of that code's readings).
        """
        regions, counts = self.merge(
            self._tracked_raw(gray, [p], self.settings.track_anchor_margin)
        )
        dets, _ = self._decode(gray, regions, counts, codes, retry=False, unknown=unknown)
        out = []
        for j, q in enumerate(predictions):
            mine = [d for d in dets if d.code == q.code]
            if j not in done and mine:
                out.append((j, min(mine, key=lambda d: math.dist(d.center_px, q.center_px))))
        return out

    def _tracking_held(
        self,
        res: DetectionResult,
        predictions: Sequence[PredictedSign],
        shape: tuple[int, ...],
        refresh: bool,
    ) -> bool:
        """Whether the tracked search found enough of the predicted signs."""
        h, w = shape[:2]
        # Signs predicted (partly) outside the image cannot be required.
        wanted = {p[0] for p in predictions if 0 <= p[1][0] < w and 0 <= p[1][1] < h}
        found = {d.code for d in res.detections} & wanted
        enough = len(found) >= max(1.0, self.settings.track_min_found_frac * len(wanted))
        return bool(wanted) and (found == wanted or (enough and not refresh))

    def _tracked_raw(
        self, gray: np.ndarray, predictions: Sequence[PredictedSign], margin: float | None = None
    ) -> np.ndarray:
        """(N, 4) raw windows around the predicted signs, at their predicted sizes.

        ``margin``: the search region's half-side beyond the predicted radius,
        in predicted diameters (default ``track_margin``).
        """
        h, w = gray.shape
        s = self.settings
        margin = s.track_margin if margin is None else margin
        parts = []
        for p in predictions:
            (u, v), diam = p[1], p[2]
            if not (math.isfinite(u) and math.isfinite(v) and diam > 0):
                continue
            half = diam * (0.5 + margin) + 4
            x0, y0 = int(max(u - half, 0)), int(max(v - half, 0))
            x1, y1 = int(min(u + half + 1, w)), int(min(v + half + 1, h))
            if x1 - x0 < 8 or y1 - y0 < 8:
                continue
            roi = gray[y0:y1, x0:x1]
            lo, hi = s.track_scale[0] * diam, s.track_scale[1] * diam
            zoom = 1.0 if lo >= WINDOW_PX else WINDOW_PX / max(lo, 8.0)
            r = self._raw_scaled(roi, zoom, lo, hi, sf=s.track_scale_factor)
            r[:, :2] += (x0, y0)
            parts.append(r)
        if not parts:
            return np.zeros((0, 4))
        # Sorted, the merge does not depend on the order OpenCV's threads found them.
        raw = np.concatenate(parts)
        return raw[np.lexsort(raw.T[::-1])]


def _window_score(n_windows: float) -> float:
    """Confidence in [0, 1] from the number of agreeing cascade windows (inf: 1)."""
    if math.isinf(n_windows):
        return 1.0
    return float(n_windows / (n_windows + 2.0))


def _observation(
    res: DecodeResult, box: tuple[float, float, float, float], n_windows: float
) -> SignObservation:
    """The decoder's reading of the region ``box`` (x, y, w, h) [px] as an observation."""
    sigma = float(res.sigma_px)
    return SignObservation(
        code=res.code,
        keypoints_px={k: (float(u), float(v)) for k, (u, v) in res.keypoints_px.items()},
        bbox_px=box,
        sigma_px=sigma if math.isfinite(sigma) and sigma > 0 else DEFAULT_SIGMA_PX,
        score=min(max(_window_score(n_windows) * (0.5 + 0.5 * float(res.quality)), 0.0), 1.0),
        erased_slots=tuple(int(s) for s in res.erased_slots),
        keypoint_sigma_px={
            k: (float(su), float(sv))
            for k, (su, sv) in res.keypoint_sigma_px.items()
            if k in res.keypoints_px
        },
    )


def _unknown(res: DecodeResult, box: tuple[float, float, float, float]) -> Unknown | None:
    """(code read, box) when the region was refused only for a code the map lacks."""
    if res.reason != DecodeReason.CODE_NOT_IN_MAP or res.unknown_code is None:
        return None
    return res.unknown_code, tuple(float(v) for v in box)


def _one_per_region(found: Sequence[Unknown]) -> tuple[Unknown, ...]:
    """``found`` without repeats: an entry of a code centred within half a region
    of an earlier one of that code is the same sign read again (another search)."""
    kept: list[Unknown] = []
    for code, box in found:
        centre = (box[0] + 0.5 * box[2], box[1] + 0.5 * box[3])
        if not any(
            k_code == code
            and math.dist(centre, (kb[0] + 0.5 * kb[2], kb[1] + 0.5 * kb[3]))
            <= 0.5 * max(box[2], box[3], kb[2], kb[3])
            for k_code, kb in kept
        ):
            kept.append((code, box))
    return tuple(
        sorted(kept, key=lambda u: (u[0], u[1][0] + 0.5 * u[1][2], u[1][1] + 0.5 * u[1][3]))
    )


def _offset(obs: SignObservation, p: PredictedSign) -> tuple[float, float]:
    """Where ``obs`` was read relative to where ``p`` predicted it [px]."""
    return (obs.center_px[0] - p.center_px[0], obs.center_px[1] - p.center_px[1])


def _offset_near(
    p: PredictedSign, found: list[SignObservation], offsets: list[tuple[float, float]]
) -> tuple[float, float]:
    """The prediction offset of the found sign nearest to ``p`` ((0, 0) when none).

    A roll of the camera moves signs differently across the image; the
    nearest one's offset is the best guess of this one's.
    """
    if not found:
        return (0.0, 0.0)
    k = min(range(len(found)), key=lambda j: math.dist(found[j].center_px, p.center_px))
    return offsets[k]


def _verify_in_turn(
    gray: np.ndarray,
    predictions: Sequence[PredictedSign],
    order: list[int],
    codes: tuple[str, ...] | None,
    found: list[SignObservation],
    offsets: list[tuple[float, float]],
) -> tuple[list[SignObservation], list[tuple[float, float]], dict[int, VerifyOutcome], set[int]]:
    """Verify ``predictions[order]`` in turn, each at the offset of the nearest
    sign found so far (``found`` and their ``offsets``, then those verified here).

    Returns:
        (found, offsets) with the verified signs appended (new lists), the
        outcome of each prediction tried, and the indices verified.
    """
    found, offsets = list(found), list(offsets)
    outcomes: dict[int, VerifyOutcome] = {}
    done: set[int] = set()
    for i in order:
        p = predictions[i]
        shift = _offset_near(p, found, offsets)
        v = verify_sign(gray, _translated(p.image_H_sign, shift), p.code, codes)
        outcomes[i] = v.outcome
        if v.ok:
            found.append(_verified_observation(v.result))
            offsets.append(_offset(found[-1], p))
            done.add(i)
    return found, offsets, outcomes, done


def _shifted_prediction(p: PredictedSign, shift: tuple[float, float]) -> PredictedSign:
    """``p`` moved by an image shift (du, dv) [px]."""
    if shift == (0.0, 0.0):
        return p
    h = None if p.image_H_sign is None else _translated(p.image_H_sign, shift)
    centre = (p.center_px[0] + shift[0], p.center_px[1] + shift[1])
    return PredictedSign(p.code, centre, p.diameter_px, h)


def _verified_observation(res: DecodeResult) -> SignObservation:
    """A verified reading as an observation; its box is the disc's (the ellipse's)."""
    (cx, cy), (major, minor), ang = res.ellipse
    c, s = math.cos(math.radians(ang)), math.sin(math.radians(ang))
    hw = 0.5 * math.hypot(major * c, minor * s)
    hh = 0.5 * math.hypot(major * s, minor * c)
    box = (float(cx - hw), float(cy - hh), float(2 * hw), float(2 * hh))
    # No cascade windows vouch for it: the score is the decoder quality's share.
    return _observation(res, box, math.inf)


def one_per_sign(found: list[SignObservation]) -> tuple[SignObservation, ...]:
    """One reading per sign, ordered by code then position.

    Regions of one sign often overlap and decode alike: readings of a code
    whose centres lie within half a region of a stronger reading are that
    sign again (the strongest is kept, and they do not count as undecoded).
    The same code farther away is kept: which one is the sign is for the
    caller to settle (with the frame's pose).
    """
    kept: list[SignObservation] = []
    for obs in sorted(found, key=lambda o: (-o.score, o.code, o.center_px)):
        radius = 0.5 * max(obs.bbox_px[2], obs.bbox_px[3])
        same = any(
            k.code == obs.code
            and math.dist(k.center_px, obs.center_px) <= max(radius, 0.5 * max(k.bbox_px[2:]))
            for k in kept
        )
        if not same:
            kept.append(obs)
    return tuple(sorted(kept, key=lambda o: (o.code, o.center_px)))


def to_frame_observations(
    result: DetectionResult, frame: int, stamp_ns: int, image_size: tuple[int, int]
) -> FrameObservations:
    """One frame's decoded signs (raw regions without a code are left out).

    Args:
        image_size: (width, height) [px].
    """
    signs = tuple(d for d in result.detections if d.code)
    return FrameObservations(
        int(frame), int(stamp_ns), (int(image_size[0]), int(image_size[1])), signs
    )
