"""The bundled detector's training recipe (paper §2.1): synthetic positives, mined negatives.

The parts, bottom-up: ``features`` (Haar features as OpenCV evaluates them),
``cascade`` (stumps, stages, the cascade), ``adaboost`` (boosting a stage,
training the cascade), ``mining`` (hard negatives), ``data`` (positives and
sign-free images) and ``cascade_xml`` (OpenCV's XML, read and written).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from signpose.training.adaboost import TrainSettings, train_cascade
from signpose.training.cascade import Cascade
from signpose.training.data import background_images, render_positives
from signpose.training.mining import NegativeMiner


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
    miner = NegativeMiner(images, settings.max_mine_windows)
    return train_cascade(
        positives, miner, n_neg, settings, rng, progress=progress, on_stage=on_stage
    )
