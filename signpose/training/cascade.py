"""The attentional cascade's data: stumps, stages and the cascade (paper §2.1, Viola-Jones).

A stump adds ``left`` to its stage's sum when the normalised feature value is
below its threshold, else ``right``; a window passes a stage when the sum is
>= the stage threshold, and the cascade when it passes every stage (after
OpenCV's contrast gate, ``features.MIN_WINDOW_STD``). ``signpose.training.adaboost``
builds cascades, ``signpose.training.cascade_xml`` reads and writes them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from signpose.training.features import (
    MIN_WINDOW_STD,
    WINDOW_PX,
    corner_weights,
    variance_norm,
    window_integrals,
)

# --------------------------------------------------------------------------- cascade


@dataclass(frozen=True)
class Stump:
    """One weak classifier: ``left`` if value < threshold else ``right``.

    Attributes:
        rects: (3, 5) the feature's rectangles (``x, y, w, h, weight``).
        threshold: on the normalised feature value.
        left, right: leaf values added to the stage sum (+-alpha).
    """

    rects: np.ndarray
    threshold: float
    left: float
    right: float


@dataclass(frozen=True)
class Stage:
    """A strong classifier: a window passes when the sum of leaves >= threshold."""

    stumps: tuple[Stump, ...]
    threshold: float


@dataclass(frozen=True)
class Cascade:
    """Attentional cascade on ``window_px`` square windows (paper §2.1, Viola-Jones)."""

    stages: tuple[Stage, ...]
    window_px: int = WINDOW_PX
    _weights: list = field(default_factory=list, repr=False, compare=False)

    def _stage_weights(self) -> list[np.ndarray]:
        if len(self._weights) != len(self.stages):
            self._weights.clear()
            for st in self.stages:
                rects = np.stack([s.rects for s in st.stumps])
                self._weights.append(corner_weights(rects, self.window_px))
        return self._weights

    def stage_sums(self, windows: np.ndarray) -> np.ndarray:
        """(N, n_stages) float64 stage sums of every window (no early exit)."""
        windows = np.asarray(windows)
        ii = window_integrals(windows)
        nf = variance_norm(windows)
        out = np.zeros((windows.shape[0], len(self.stages)))
        for k, (st, wts) in enumerate(zip(self.stages, self._stage_weights(), strict=True)):
            vals = (ii @ wts) / nf[:, None]
            thr = np.array([s.threshold for s in st.stumps])
            left = np.array([s.left for s in st.stumps])
            right = np.array([s.right for s in st.stumps])
            out[:, k] = np.where(vals < thr, left, right).sum(axis=1)
        return out

    def accepts(self, windows: np.ndarray) -> np.ndarray:
        """(N,) bool: windows that pass every stage (and OpenCV's contrast gate)."""
        windows = np.asarray(windows)
        if windows.shape[0] == 0:
            return np.zeros(0, bool)
        nf = variance_norm(windows)
        area = (windows.shape[1] - 2) * (windows.shape[2] - 2)
        alive = nf > MIN_WINDOW_STD * area
        if not self.stages:
            return alive
        ii = window_integrals(windows)
        for st, wts in zip(self.stages, self._stage_weights(), strict=True):
            idx = np.flatnonzero(alive)
            if idx.size == 0:
                break
            vals = (ii[idx] @ wts) / nf[idx, None]
            thr = np.array([s.threshold for s in st.stumps])
            left = np.array([s.left for s in st.stumps])
            right = np.array([s.right for s in st.stumps])
            score = np.where(vals < thr, left, right).sum(axis=1)
            alive[idx[score < st.threshold]] = False
        return alive

    @property
    def n_weak(self) -> int:
        return sum(len(s.stumps) for s in self.stages)
