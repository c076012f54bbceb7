"""Haar features, discrete Adaboost and the attentional cascade (paper §2.1), in numpy.

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

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

log = logging.getLogger(__name__)

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


# --------------------------------------------------------------------------- Adaboost


@dataclass(frozen=True)
class TrainSettings:
    """Cascade training settings (paper §2.1; Viola-Jones attentional cascade).

    Attributes:
        features_per_stage: candidate features drawn at random (fresh each
            stage) from the full set; 0 = all 162 336 (slow, memory heavy).
        min_hit_rate: fraction of training positives each stage must keep.
        max_false_alarm: fraction of the stage's negatives it may pass.
        max_stages, max_weak_per_stage: size limits.
        target_false_alarm: stop when mining finds negatives this rarely.
        max_mine_windows: windows to try per stage when mining negatives.
    """

    features_per_stage: int = 8000
    min_hit_rate: float = 0.995
    max_false_alarm: float = 0.5
    max_stages: int = 20
    max_weak_per_stage: int = 80
    target_false_alarm: float = 2e-6
    max_mine_windows: int = 400_000_000
    feature_block: int = 2000


class PresortedBlock:
    """Feature values of a block of features, presorted once per stage.

    Attributes:
        order: (F, N) int32 sample indices sorting each feature's values.
        sorted_vals: (F, N) float32 the sorted values.
        cuts: flat indices ``f * N + k`` of the ranks k < N - 1 after which a
            threshold fits (value k < value k + 1), feature by feature.
        has_cut: (F,) False for features constant over all samples.
        starts: offset of each feature's first cut in ``cuts`` (features with cuts).
    """

    def __init__(self, vals_t: np.ndarray) -> None:
        f, n = vals_t.shape
        self.order = np.argsort(vals_t, axis=1).astype(np.int32)
        self.sorted_vals = np.take_along_axis(vals_t, self.order, axis=1)
        ok = self.sorted_vals[:, :-1] < self.sorted_vals[:, 1:]
        rows, ks = np.nonzero(ok)
        self.cuts = (rows * n + ks).astype(np.int64 if f * n >= 2**31 else np.int32)
        counts = ok.sum(axis=1)
        self.has_cut = counts > 0
        self.starts = np.concatenate([[0], np.cumsum(counts)[:-1]])[self.has_cut]
        self._buf = np.empty((f, n), np.float32)

    def best(
        self, signed_w: np.ndarray, total_pos: float, total_neg: float
    ) -> tuple[int, float, int, float]:
        """Lowest weighted-error single-feature stump.

        With C = cumulative signed weight (positives +w, negatives -w) in value
        order, a threshold after rank k that calls values below it positive
        errs ``T+ - C_k``; calling them negative errs ``T- + C_k``.

        Args:
            signed_w: (N,) float32 weights, + for positives, - for negatives.

        Returns:
            (feature row, threshold, polarity (+1: positive below), error).
        """
        c = self._buf
        np.take(signed_w, self.order, out=c)
        np.cumsum(c, axis=1, out=c)
        at_cuts = c.ravel()[self.cuts]
        err_below = np.full(c.shape[0], np.inf)
        err_above = np.full(c.shape[0], np.inf)
        if at_cuts.size:
            err_below[self.has_cut] = total_pos - np.maximum.reduceat(at_cuts, self.starts)
            err_above[self.has_cut] = total_neg + np.minimum.reduceat(at_cuts, self.starts)
        f1, f2 = int(err_below.argmin()), int(err_above.argmin())
        pol = 1 if err_below[f1] <= err_above[f2] else -1
        f = f1 if pol == 1 else f2
        row = c[f, :-1]
        ok = self.sorted_vals[f, :-1] < self.sorted_vals[f, 1:]
        cand = np.flatnonzero(ok)
        k = int(cand[row[cand].argmax()] if pol == 1 else cand[row[cand].argmin()])
        err = float(total_pos - row[k]) if pol == 1 else float(total_neg + row[k])
        thr = 0.5 * (float(self.sorted_vals[f, k]) + float(self.sorted_vals[f, k + 1]))
        return f, thr, pol, err


def train_stage(
    pos: np.ndarray,
    neg: np.ndarray,
    features: HaarFeatureSet,
    settings: TrainSettings,
    progress: Callable[[str], None] | None = None,
) -> tuple[Stage, float, float]:
    """Discrete Adaboost (paper §2.1 steps (1)-(4)) grown until the stage goals hold.

    Args:
        pos: (P, S, S) positive windows; neg: (M, S, S) negative windows.
        features: the candidate features for this stage.

    Returns:
        (stage, hit rate, false-alarm rate) on the given windows.
    """
    n_pos, n_neg = pos.shape[0], neg.shape[0]
    windows = np.concatenate([pos, neg])
    y = np.concatenate([np.ones(n_pos, bool), np.zeros(n_neg, bool)])
    weights = corner_weights(features.rects)
    # Feature-major values and their presorting, in blocks to bound memory.
    vals_t = np.empty((len(features), windows.shape[0]), np.float32)
    ii = window_integrals(windows)
    inv_nf = (1.0 / variance_norm(windows)).astype(np.float32)
    for b in range(0, len(features), settings.feature_block):
        blk = slice(b, b + settings.feature_block)
        vals_t[blk] = (ii @ weights[:, blk]).T * inv_nf[None, :]
    blocks = [
        PresortedBlock(vals_t[b : b + settings.feature_block])
        for b in range(0, len(features), settings.feature_block)
    ]

    # (2) w = 1/2l for positives, 1/2m for negatives.
    w = np.where(y, 1.0 / (2 * n_pos), 1.0 / (2 * n_neg))
    score = np.zeros(windows.shape[0])
    stumps: list[Stump] = []
    hit = fa = 1.0
    thr_stage = 0.0
    for _t in range(settings.max_weak_per_stage):
        w = w / w.sum()  # (3)(1) normalise
        signed = np.where(y, w, -w).astype(np.float32)
        total_pos, total_neg = float(w[y].sum()), float(w[~y].sum())
        best = (None, 0.0, 1, np.inf)
        for j, blk in enumerate(blocks):
            f, thr, pol, err = blk.best(signed, total_pos, total_neg)
            if err < best[3]:
                best = (j * settings.feature_block + f, thr, pol, err)
        f, thr, pol, err = best
        err = min(max(err, 1e-10), 0.5 - 1e-10)
        alpha = 0.5 * math.log((1 - err) / err)  # (3)(4)
        h = vals_t[f] < thr if pol == 1 else vals_t[f] >= thr
        beta = err / (1 - err)
        w = w * np.where(h == y, beta, 1.0)  # (3)(5): w *= beta^(1 - e_i)
        left, right = (alpha, -alpha) if pol == 1 else (-alpha, alpha)
        stumps.append(Stump(features.rects[f].copy(), float(thr), left, right))
        score += np.where(vals_t[f] < thr, left, right)
        # Lower the stage threshold until it keeps min_hit_rate of positives.
        pos_scores = np.sort(score[:n_pos])
        k = int(math.floor((1.0 - settings.min_hit_rate) * n_pos))
        thr_stage = float(pos_scores[k]) - 1e-3
        hit = float((score[:n_pos] >= thr_stage).mean())
        fa = float((score[n_pos:] >= thr_stage).mean())
        if progress is not None:
            progress(f"weak {len(stumps)} err {err:.3f} hit {hit:.4f} fa {fa:.3f}")
        if fa <= settings.max_false_alarm:
            break
    return Stage(tuple(stumps), thr_stage), hit, fa


NegativeSource = Callable[[Cascade, int, np.random.Generator], tuple[np.ndarray, float]]


def train_cascade(
    positives: np.ndarray,
    mine_negatives: NegativeSource,
    n_neg: int,
    settings: TrainSettings,
    rng: np.random.Generator,
    feature_pool: HaarFeatureSet | None = None,
    progress: Callable[[str], None] | None = None,
    on_stage: Callable[[Cascade], None] | None = None,
) -> Cascade:
    """Train the attentional cascade stage by stage.

    Args:
        positives: (P, S, S) uint8 positive windows.
        mine_negatives: ``(cascade, n, rng) -> (windows (n', S, S), rate)``:
            windows the cascade so far accepts (hard negatives), n' <= n, and
            the fraction of scanned windows it accepted.
        n_neg: negatives per stage.
        feature_pool: candidate features (default: all five shapes).
        on_stage: called with the cascade after each new stage (checkpoints).

    Returns:
        The cascade (stops early when negatives become too rare to mine).
    """
    pool = feature_pool if feature_pool is not None else all_features(positives.shape[1])
    cascade = Cascade(())
    pos = positives
    for s in range(settings.max_stages):
        neg, rate = mine_negatives(cascade, n_neg, rng)
        if progress is not None:
            progress(
                f"stage {s + 1}: {neg.shape[0]} negatives (false-alarm rate so far {rate:.2e})"
            )
        if neg.shape[0] < max(50, n_neg // 20) or rate < settings.target_false_alarm:
            break
        # Keep only the positives the cascade still accepts (as a detector would).
        pos = pos[cascade.accepts(pos)]
        n_feat = settings.features_per_stage or len(pool)
        idx = rng.choice(len(pool), size=min(n_feat, len(pool)), replace=False)
        stage, hit, fa = train_stage(pos, neg, pool.subset(np.sort(idx)), settings, progress)
        cascade = Cascade((*cascade.stages, stage), cascade.window_px)
        if on_stage is not None:
            on_stage(cascade)
        if progress is not None:
            progress(f"stage {s + 1}: {len(stage.stumps)} weak, hit {hit:.4f}, fa {fa:.3f}")
    return cascade


# --------------------------------------------------------------------------- mining


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


def make_miner(
    images: Sequence[np.ndarray | tuple[np.ndarray, np.ndarray]],
    max_windows: int,
    scale_range: tuple[float, float] = (0.15, 1.0),
    scale_factor: float = 1.2,
) -> NegativeSource:
    """Negative source: windows of sign-free images that the cascade so far accepts.

    The first stage takes random windows at random scales. Later stages run
    the cascade so far through ``cv2.CascadeClassifier.detectMultiScale``
    (raw windows, ``minNeighbors=0``) over the images at a random zoom, cut
    the accepted windows out and keep those the numpy cascade accepts too:
    the hard negatives a detector would report.

    An image may come with the (K, 4) boxes (x, y, w, h) of signs in it (a
    simulated frame): windows touching a sign are never taken.
    """
    import os
    import tempfile

    import cv2

    imgs, masks = [], []
    for item in images:
        im, boxes = item if isinstance(item, tuple) else (item, np.zeros((0, 4)))
        if min(im.shape[:2]) >= 2 * WINDOW_PX:
            imgs.append(np.asarray(im, np.uint8))
            masks.append(np.asarray(boxes, float).reshape(-1, 4))

    def mine(cascade: Cascade, n: int, rng: np.random.Generator) -> tuple[np.ndarray, int]:
        from signpose.training.cascade_xml import write_cascade_xml

        found: list[np.ndarray] = []
        n_found = tried = n_accepted = 0
        per_image = n // 40 + 1  # spread the negatives over many images
        clf = None
        if cascade.stages:
            fd, tmp = tempfile.mkstemp(suffix=".xml")
            os.close(fd)
            try:
                write_cascade_xml(tmp, cascade)
                clf = cv2.CascadeClassifier(tmp)
            finally:
                os.unlink(tmp)
        while n_found < n and tried < max_windows:
            pick = int(rng.integers(len(imgs)))
            im, boxes = imgs[pick], masks[pick]
            lo = max(scale_range[0], 3 * WINDOW_PX / min(im.shape[:2]))
            zoom = math.exp(rng.uniform(math.log(lo), math.log(max(lo, scale_range[1]))))
            if rng.random() < 0.3:
                zoom = min(2.0, zoom * 3)  # magnified texture too
            small = cv2.resize(im, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_LINEAR)
            if clf is None:
                ys = rng.integers(0, small.shape[0] - WINDOW_PX + 1, per_image)
                xs = rng.integers(0, small.shape[1] - WINDOW_PX + 1, per_image)
                keep = np.stack(
                    [
                        small[y : y + WINDOW_PX, x : x + WINDOW_PX]
                        for y, x in zip(ys, xs, strict=True)
                    ]
                )
                win = np.stack(
                    [xs, ys, np.full_like(xs, WINDOW_PX), np.full_like(xs, WINDOW_PX)], 1
                )
                clear = _clear_of(win / zoom, boxes)
                keep = keep[cascade.accepts(keep) & clear]  # OpenCV's contrast gate only
                tried += per_image
                n_accepted += keep.shape[0]
            else:
                tried += _windows_scanned(*small.shape, scale_factor)
                rects = clf.detectMultiScale(
                    small, scaleFactor=scale_factor, minNeighbors=0, minSize=(WINDOW_PX, WINDOW_PX)
                )
                if len(rects) == 0:
                    continue
                rects = np.asarray(rects)
                rects = rects[_clear_of(rects / zoom, boxes)]
                n_raw = len(rects)
                if n_raw == 0:
                    continue
                if len(rects) > 4 * per_image:
                    rects = rects[rng.choice(len(rects), 4 * per_image, replace=False)]
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
                n_accepted += n_raw * ok.mean()
                keep = wins[ok]
                if keep.shape[0] > per_image:
                    keep = keep[rng.choice(keep.shape[0], per_image, replace=False)]
            found.append(np.ascontiguousarray(keep))
            n_found += keep.shape[0]
        out = np.concatenate(found) if found else np.empty((0, WINDOW_PX, WINDOW_PX), np.uint8)
        return out[:n], n_accepted / max(tried, 1)

    return mine


# --------------------------------------------------------------------------- training data


def square_from_ellipse(
    ellipse: tuple[tuple[float, float], tuple[float, float], float],
) -> tuple[float, float, float]:
    """(cx, cy, side) of the square bounding a ``cv2.RotatedRect``-style ellipse [px]."""
    (cx, cy), (a, b), ang = ellipse
    t = math.radians(ang)
    hx = math.sqrt((a / 2 * math.cos(t)) ** 2 + (b / 2 * math.sin(t)) ** 2)
    hy = math.sqrt((a / 2 * math.sin(t)) ** 2 + (b / 2 * math.cos(t)) ** 2)
    return cx, cy, 2 * max(hx, hy)


def crop_square(image: np.ndarray, cx: float, cy: float, side: float, out_px: int) -> np.ndarray:
    """Resample the square of ``side`` px centred at (cx, cy) to ``out_px`` (bilinear).

    Downscaling goes through ``cv2.INTER_AREA`` first when strong, then
    ``INTER_LINEAR`` like the detector's pyramid.
    """
    import cv2

    s = out_px / side
    m = np.array([[s, 0, out_px / 2 - 0.5 - s * cx], [0, s, out_px / 2 - 0.5 - s * cy]])
    return cv2.warpAffine(
        image, m, (out_px, out_px), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )


def render_positives(
    n: int,
    rng: np.random.Generator,
    codes: Sequence[str] | None = None,
    window_px: int = WINDOW_PX,
    progress: Callable[[int], None] | None = None,
) -> np.ndarray:
    """``n`` positive windows: signs of all codes from ``frontend.synth``, randomly disturbed.

    Each sign is rendered at 22-90 px with random in-plane rotation, view angle
    up to 65 degrees, motion blur, noise, exposure, dirt and power lines on
    every background kind, then cut to the disc's bounding square (with a
    little position/size jitter, as a detector window sees it) and resampled
    to ``window_px``.

    Returns:
        (n, window_px, window_px) uint8.
    """
    from signpose.frontend.sign import ALL_CODES
    from signpose.sim.crops import BACKGROUNDS, render_crop

    codes = tuple(codes or ALL_CODES)
    out = np.empty((n, window_px, window_px), np.uint8)
    for i in range(n):
        sign_px = float(math.exp(rng.uniform(math.log(22), math.log(90))))
        crop = render_crop(
            codes[i % len(codes)],
            rng,
            sign_px=sign_px,
            rotation_deg=rng.uniform(0, 360),
            tilt_deg=rng.uniform(0, 65) if rng.random() < 0.8 else 0.0,
            tilt_axis_deg=rng.uniform(0, 180),
            blur_px=rng.uniform(0, 0.08 * sign_px) if rng.random() < 0.4 else 0.0,
            noise_sigma=rng.uniform(0, 10),
            dirt=bool(rng.random() < 0.15),
            power_line=bool(rng.random() < 0.3),
            background=BACKGROUNDS[int(rng.integers(len(BACKGROUNDS)))],
            contrast=rng.uniform(0.45, 1.15),
            brightness=rng.uniform(-50, 50),
            margin=0.4,
            psf_sigma_px=rng.uniform(0.3, 0.9),
            supersample=4,
        )
        cx, cy, side = square_from_ellipse(crop.ellipse)
        side *= math.exp(rng.uniform(-0.07, 0.07))
        cx += rng.uniform(-0.05, 0.05) * side
        cy += rng.uniform(-0.05, 0.05) * side
        out[i] = crop_square(crop.image, cx, cy, side, window_px)
        if progress is not None:
            progress(1)
    return out


def photo_images() -> list[np.ndarray]:
    """Grey photographs shipped by installed packages (no downloads).

    matplotlib's sample_data always; scikit-image's ``skimage.data`` images
    when the optional ``train`` extra is installed.
    """
    import os

    import cv2

    out: list[np.ndarray] = []
    try:
        import matplotlib

        folder = os.path.join(matplotlib.get_data_path(), "sample_data")
        for name in ("grace_hopper.jpg", "Minduka_Present_Blue_Pack.png", "logo2.png"):
            im = cv2.imread(os.path.join(folder, name), cv2.IMREAD_GRAYSCALE)
            if im is not None:
                out.append(im)
    except ImportError:  # pragma: no cover - matplotlib is a dependency
        pass
    try:
        import skimage.data as skd  # optional `train` extra

        for name in (
            "astronaut",
            "camera",
            "coffee",
            "chelsea",
            "rocket",
            "brick",
            "grass",
            "gravel",
            "moon",
            "page",
            "text",
            "coins",
            "clock",
            "hubble_deep_field",
        ):
            try:
                im = np.asarray(getattr(skd, name)())
            except Exception:  # noqa: BLE001 - some images need optional data files
                continue
            if im.ndim == 3:
                im = cv2.cvtColor(im[..., :3].astype(np.uint8), cv2.COLOR_RGB2GRAY)
            out.append(im.astype(np.uint8))
    except ImportError:
        pass
    return out


def background_images(rng: np.random.Generator, per_kind: int = 6) -> list[np.ndarray]:
    """Sign-free negative images: procedural backgrounds of every kind plus photographs."""
    from signpose.sim.crops import BACKGROUNDS, render_background

    out = []
    for kind in BACKGROUNDS:
        for _ in range(per_kind):
            h, w = int(rng.integers(240, 720)), int(rng.integers(240, 960))
            out.append(render_background(rng, h, w, kind))
    photos = photo_images()
    out += photos
    out += [np.ascontiguousarray(p[:, ::-1]) for p in photos]  # mirrored copies
    return out


def train_sign_cascade(
    seed: int,
    n_pos: int = 4000,
    n_neg: int = 4000,
    settings: TrainSettings | None = None,
    progress: Callable[[str], None] | None = None,
    pos_progress: Callable[[int], None] | None = None,
    scene_negatives: Sequence[tuple[np.ndarray, np.ndarray]] = (),
    on_stage: Callable[[Cascade], None] | None = None,
) -> Cascade:
    """The bundled detector's recipe: synthetic positives, mined background negatives.

    Everything is drawn from ``np.random.default_rng(seed)``.

    Args:
        scene_negatives: (grey image, (K, 4) sign boxes) pairs, e.g. simulated
            frames; their sign-free regions are mined for negatives too.
    """
    settings = settings or TrainSettings()
    rng = np.random.default_rng(seed)
    positives = render_positives(n_pos, rng, progress=pos_progress)
    images: list = list(background_images(rng))
    images += list(scene_negatives)
    miner = make_miner(images, settings.max_mine_windows)
    return train_cascade(
        positives, miner, n_neg, settings, rng, progress=progress, on_stage=on_stage
    )
