"""Discrete Adaboost over Haar stumps and the stage-by-stage cascade training (paper §2.1).

Each stage is boosted (steps (1)-(4) of the paper) until it keeps
``min_hit_rate`` of the positives and passes at most ``max_false_alarm`` of
its negatives; the negatives of each new stage are windows the cascade so
far accepts, from a ``NegativeSource`` (``signpose.training.mining``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from signpose.training.cascade import Cascade, Stage, Stump
from signpose.training.features import (
    HaarFeatureSet,
    all_features,
    corner_weights,
    variance_norm,
    window_integrals,
)

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
