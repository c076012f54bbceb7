"""Haar features on 24 x 24 windows, evaluated as OpenCV does (paper §2.1, Fig. 5), in numpy.

Windows are ``WINDOW_PX`` x ``WINDOW_PX`` grey images (row = y, column = x).
Feature values follow OpenCV's HAAR evaluator exactly so a trained cascade
runs unchanged in ``cv2.CascadeClassifier``:

* a feature is up to three rectangles ``(x, y, w, h, weight)`` in window
  pixels; its raw value is ``sum(weight * pixel_sum(rect))`` (the paper's
  five shapes written the way OpenCV writes them: the whole feature area with
  weight -1 plus the "positive" part with weight 2, 3 or 2+2);
* the raw value is divided by ``nf = sqrt(A * sum(p^2) - sum(p)^2)`` over the
  window inset by one pixel (A = 22 * 22), i.e. by A times the standard
  deviation of the window, so thresholds do not depend on lighting.

Vectorisation: every window becomes its flattened (25 * 25,) integral image
``ii``; a feature is a sparse corner-weight column ``c`` (at most 12 non-zeros,
stored dense for BLAS) with ``raw = ii @ c``, so one stage's all-feature
evaluation is a single (N, 625) x (625, F) matrix product.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

WINDOW_PX = 24
_SIDE = WINDOW_PX + 1  # integral image side
NORM_AREA = (WINDOW_PX - 2) ** 2  # OpenCV normalises over the window inset by 1 px
# OpenCV's HaarEvaluator rejects every window whose (inset) standard deviation is
# at most 10 grey levels (``area * varianceNormFactor < 0.1``); so do we.
MIN_WINDOW_STD = 10.0

# The paper's Fig. 5 shapes.
SHAPE_NAMES = ("two_horizontal", "two_vertical", "three_horizontal", "three_vertical", "four")


# --------------------------------------------------------------------------- features


@dataclass(frozen=True)
class HaarFeatureSet:
    """A list of Haar features on the base window.

    Attributes:
        rects: (F, 3, 5) float32 rows ``x, y, w, h, weight`` in window pixels;
            a rectangle with weight 0 is unused.
        shapes: (F,) int8 index into ``SHAPE_NAMES``.
    """

    rects: np.ndarray
    shapes: np.ndarray

    def __len__(self) -> int:
        return int(self.rects.shape[0])

    def subset(self, index: np.ndarray) -> HaarFeatureSet:
        return HaarFeatureSet(self.rects[index], self.shapes[index])


def all_features(window_px: int = WINDOW_PX) -> HaarFeatureSet:
    """Every feature of the five shapes at every position and size (162 336 for 24 px)."""
    rows: list[tuple] = []
    shapes: list[int] = []
    n = window_px
    # (shape, cells in x, cells in y)
    for shape, (cx, cy) in enumerate(((2, 1), (1, 2), (3, 1), (1, 3), (2, 2))):
        for cw in range(1, n // cx + 1):
            for ch in range(1, n // cy + 1):
                w, h = cw * cx, ch * cy
                for y in range(0, n - h + 1):
                    for x in range(0, n - w + 1):
                        whole = (x, y, w, h, -1.0)
                        if shape == 0:  # left/right halves
                            parts = [(x + cw, y, cw, h, 2.0)]
                        elif shape == 1:  # top/bottom halves
                            parts = [(x, y + ch, w, ch, 2.0)]
                        elif shape == 2:  # centre column minus the outer two
                            parts = [(x + cw, y, cw, h, 3.0)]
                        elif shape == 3:  # centre row minus the outer two
                            parts = [(x, y + ch, w, ch, 3.0)]
                        else:  # diagonal quarters
                            parts = [(x, y, cw, ch, 2.0), (x + cw, y + ch, cw, ch, 2.0)]
                        rect = [whole, *parts]
                        rect += [(0, 0, 0, 0, 0.0)] * (3 - len(rect))
                        rows.append(rect)
                        shapes.append(shape)
    return HaarFeatureSet(np.asarray(rows, np.float32), np.asarray(shapes, np.int8))


def corner_weights(rects: np.ndarray, window_px: int = WINDOW_PX) -> np.ndarray:
    """Corner-weight matrix: raw feature values are ``integrals @ C``.

    Args:
        rects: (F, 3, 5) feature rectangles as in ``HaarFeatureSet.rects``.

    Returns:
        (side * side, F) float32, side = window_px + 1; each column has at most
        12 non-zeros (+-weight at the four corners of each rectangle).
    """
    side = window_px + 1
    rects = np.asarray(rects, np.float64).reshape(-1, 3, 5)
    f = rects.shape[0]
    c = np.zeros((side * side, f), np.float64)
    cols = np.arange(f)
    for k in range(3):
        x, y, w, h, wt = (rects[:, k, i] for i in range(5))
        x, y, w, h = (v.astype(np.int64) for v in (x, y, w, h))
        for dx, dy, sgn in ((0, 0, 1), (1, 0, -1), (0, 1, -1), (1, 1, 1)):
            idx = (y + dy * h) * side + (x + dx * w)
            np.add.at(c, (idx, cols), sgn * wt)
    return c.astype(np.float32)


def window_integrals(windows: np.ndarray) -> np.ndarray:
    """Flattened zero-padded integral images.

    Args:
        windows: (N, S, S) grey windows (any real dtype, 0..255).

    Returns:
        (N, (S + 1)^2) float32; entry (y, x) is the sum of pixels above-left.
        Exact: sums of 8-bit pixels over 24 x 24 stay below 2^24.
    """
    w = np.asarray(windows, np.float64)
    n, s = w.shape[0], w.shape[1]
    ii = np.zeros((n, s + 1, s + 1), np.float64)
    ii[:, 1:, 1:] = w.cumsum(axis=1).cumsum(axis=2)
    return ii.reshape(n, -1).astype(np.float32)


def variance_norm(windows: np.ndarray) -> np.ndarray:
    """OpenCV's per-window normaliser ``sqrt(A * sum p^2 - (sum p)^2)`` (1 when flat).

    Args:
        windows: (N, S, S) grey windows.

    Returns:
        (N,) float64.
    """
    inner = np.asarray(windows, np.float64)[:, 1:-1, 1:-1]
    area = inner.shape[1] * inner.shape[2]
    s = inner.sum(axis=(1, 2))
    sq = (inner * inner).sum(axis=(1, 2))
    nf = area * sq - s * s
    return np.where(nf > 0, np.sqrt(np.maximum(nf, 0)), 1.0)


def feature_values(windows: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Normalised feature values of all windows for all features (one matmul).

    Args:
        windows: (N, S, S) grey windows.
        weights: (side^2, F) corner-weight matrix from ``corner_weights``.

    Returns:
        (N, F) float32 values as OpenCV computes them.
    """
    raw = window_integrals(windows) @ weights
    return (raw / variance_norm(windows)[:, None]).astype(np.float32)
