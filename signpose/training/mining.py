"""Hard negatives for the cascade: windows of sign-free images that the cascade so far accepts.

The first stage takes random windows at random scales. Later stages run the
cascade so far through ``cv2.CascadeClassifier.detectMultiScale`` (raw
windows, ``minNeighbors=0``) over the images at a random zoom, cut the
accepted windows out and keep those the numpy cascade accepts too: the hard
negatives a detector would report. Windows are (x, y, w, h) in image pixels.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Sequence

import cv2
import numpy as np

from signpose.training.cascade import Cascade
from signpose.training.cascade_xml import write_cascade_xml
from signpose.training.features import WINDOW_PX

IMAGES_PER_STAGE = 40  # the negatives of a stage are spread over at least this many images
MAGNIFIED_SHARE = 0.3  # share of images zoomed x3 (magnified texture), capped at 2x
MAX_ZOOM = 2.0
DETECTIONS_PER_IMAGE = 4  # at most this many x the per-image quota is cut out per image


def sliding_windows(image: np.ndarray, step: int, window_px: int = WINDOW_PX) -> np.ndarray:
    """(K, S, S) view of all windows of ``image`` on a ``step`` grid."""
    if image.shape[0] < window_px or image.shape[1] < window_px:
        return np.empty((0, window_px, window_px), image.dtype)
    v = np.lib.stride_tricks.sliding_window_view(image, (window_px, window_px))
    v = v[::step, ::step]
    return v.reshape(-1, window_px, window_px)


def _windows_scanned(h: int, w: int, scale_factor: float, window_px: int = WINDOW_PX) -> int:
    """Windows ``detectMultiScale`` visits on an (h, w) image (step 2 px below 2x)."""
    n, f = 0, 1.0
    while h / f >= window_px and w / f >= window_px:
        step = 1 if f > 2 else 2
        n += (int((w / f - window_px) // step) + 1) * (int((h / f - window_px) // step) + 1)
        f *= scale_factor
    return n


def _clear_of(rects: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(N,) bool: windows (x, y, w, h) that touch none of ``boxes`` (K, 4)."""
    if boxes.size == 0 or rects.size == 0:
        return np.ones(rects.shape[0], bool)
    r, b = rects[:, None, :].astype(float), boxes[None, :, :].astype(float)
    ix = (r[..., 0] < b[..., 0] + b[..., 2]) & (b[..., 0] < r[..., 0] + r[..., 2])
    iy = (r[..., 1] < b[..., 1] + b[..., 3]) & (b[..., 1] < r[..., 1] + r[..., 3])
    return ~(ix & iy).any(axis=1)


def _opencv_classifier(cascade: Cascade) -> cv2.CascadeClassifier | None:
    """``cascade`` loaded into OpenCV (through a temporary XML file), None without stages."""
    if not cascade.stages:
        return None
    fd, tmp = tempfile.mkstemp(suffix=".xml")
    os.close(fd)
    try:
        write_cascade_xml(tmp, cascade)
        return cv2.CascadeClassifier(tmp)
    finally:
        os.unlink(tmp)


class NegativeMiner:
    """A ``NegativeSource`` (``signpose.training.adaboost``) over sign-free images.

    Args:
        images: grey images, each optionally paired with the (K, 4) boxes
            (x, y, w, h) of signs in it (a simulated frame): windows touching
            a sign are never taken. Images under two windows across are dropped.
        max_windows: windows to try per stage.
        scale_range: (min, max) zoom applied to an image before scanning.
        scale_factor: ``detectMultiScale``'s pyramid step.
    """

    def __init__(
        self,
        images: Sequence[np.ndarray | tuple[np.ndarray, np.ndarray]],
        max_windows: int,
        scale_range: tuple[float, float] = (0.15, 1.0),
        scale_factor: float = 1.2,
    ) -> None:
        self.images: list[np.ndarray] = []
        self.boxes: list[np.ndarray] = []
        for item in images:
            im, boxes = item if isinstance(item, tuple) else (item, np.zeros((0, 4)))
            if min(im.shape[:2]) >= 2 * WINDOW_PX:
                self.images.append(np.asarray(im, np.uint8))
                self.boxes.append(np.asarray(boxes, float).reshape(-1, 4))
        self.max_windows = max_windows
        self.scale_range = scale_range
        self.scale_factor = scale_factor

    def __call__(
        self, cascade: Cascade, n: int, rng: np.random.Generator
    ) -> tuple[np.ndarray, float]:
        """(up to ``n`` windows (n', S, S) uint8 the cascade accepts, their rate among tried)."""
        found: list[np.ndarray] = []
        n_found = tried = 0
        n_accepted = 0.0
        per_image = n // IMAGES_PER_STAGE + 1
        clf = _opencv_classifier(cascade)
        while n_found < n and tried < self.max_windows:
            pick = int(rng.integers(len(self.images)))
            small, zoom = self._zoomed(self.images[pick], rng)
            if clf is None:
                keep, n_tried, n_ok = self._random_windows(
                    cascade, small, zoom, self.boxes[pick], per_image, rng
                )
            else:
                keep, n_tried, n_ok = self._detected_windows(
                    cascade, clf, small, zoom, self.boxes[pick], per_image, rng
                )
            tried += n_tried
            n_accepted += n_ok
            if keep is None:
                continue
            found.append(np.ascontiguousarray(keep))
            n_found += keep.shape[0]
        out = np.concatenate(found) if found else np.empty((0, WINDOW_PX, WINDOW_PX), np.uint8)
        return out[:n], n_accepted / max(tried, 1)

    def _zoomed(self, im: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, float]:
        lo = max(self.scale_range[0], 3 * WINDOW_PX / min(im.shape[:2]))
        zoom = math.exp(rng.uniform(math.log(lo), math.log(max(lo, self.scale_range[1]))))
        if rng.random() < MAGNIFIED_SHARE:
            zoom = min(MAX_ZOOM, zoom * 3)
        return cv2.resize(im, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_LINEAR), zoom

    @staticmethod
    def _random_windows(
        cascade: Cascade,
        small: np.ndarray,
        zoom: float,
        boxes: np.ndarray,
        per_image: int,
        rng: np.random.Generator,
    ) -> tuple[np.ndarray, int, float]:
        """First stage: random windows past OpenCV's contrast gate; (kept, tried, accepted)."""
        ys = rng.integers(0, small.shape[0] - WINDOW_PX + 1, per_image)
        xs = rng.integers(0, small.shape[1] - WINDOW_PX + 1, per_image)
        keep = np.stack(
            [small[y : y + WINDOW_PX, x : x + WINDOW_PX] for y, x in zip(ys, xs, strict=True)]
        )
        win = np.stack([xs, ys, np.full_like(xs, WINDOW_PX), np.full_like(xs, WINDOW_PX)], 1)
        clear = _clear_of(win / zoom, boxes)
        keep = keep[cascade.accepts(keep) & clear]  # OpenCV's contrast gate only
        return keep, per_image, keep.shape[0]

    def _detected_windows(
        self,
        cascade: Cascade,
        clf: cv2.CascadeClassifier,
        small: np.ndarray,
        zoom: float,
        boxes: np.ndarray,
        per_image: int,
        rng: np.random.Generator,
    ) -> tuple[np.ndarray | None, int, float]:
        """Later stages: OpenCV's raw detections that the numpy cascade accepts too."""
        tried = _windows_scanned(*small.shape, self.scale_factor)
        rects = clf.detectMultiScale(
            small, scaleFactor=self.scale_factor, minNeighbors=0, minSize=(WINDOW_PX, WINDOW_PX)
        )
        if len(rects) == 0:
            return None, tried, 0.0
        rects = np.asarray(rects)
        rects = rects[_clear_of(rects / zoom, boxes)]
        n_raw = len(rects)
        if n_raw == 0:
            return None, tried, 0.0
        if len(rects) > DETECTIONS_PER_IMAGE * per_image:
            rects = rects[rng.choice(len(rects), DETECTIONS_PER_IMAGE * per_image, replace=False)]
        wins = np.stack(
            [
                cv2.resize(
                    small[y : y + h, x : x + w],
                    (WINDOW_PX, WINDOW_PX),
                    interpolation=cv2.INTER_LINEAR,
                )
                for x, y, w, h in rects
            ]
        )
        ok = cascade.accepts(wins)
        keep = wins[ok]
        if keep.shape[0] > per_image:
            keep = keep[rng.choice(keep.shape[0], per_image, replace=False)]
        return keep, tried, n_raw * ok.mean()
