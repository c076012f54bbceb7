"""Keypoint noise of one decoded sign: ``sigma_px`` per keypoint and axis (issue 11, item 3).

The decoder measures what it saw of a sign (``SigmaInputs``); ``keypoint_sigmas``
turns that into per-keypoint (sigma_u, sigma_v) under a ``SigmaModel``, whose
constants scripts/calibrate_sigma.py fits against the simulator's truth (and
scripts/eval_decoder.py --independent checks on scenes the fit never saw).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SigmaModel:
    """Keypoint noise from what the decoder sees, calibrated by scripts/calibrate_sigma.py.

    ``sigma^2 = floor^2 + (size / minor)^2 + (spread_px2 * spread / minor)^2
    + (residual * rms)^2 + (disturbance * disturbance_in * minor)^2``, times the
    ``direction`` or ``slot`` factor for those keypoints and ``occluded`` when
    an occluder crosses the face (its parts are dropped, but a band's edge
    still pulls the neighbours' centroids).

    Attributes:
        floor_px: error left on large clean signs [px].
        size_px2: size term [px^2]: sampling and blur, over the disc's minor axis [px].
        spread_px2: noise term [px^2], per unit of the black samples' spread.
        residual: factor on the homography fit's RMS residual (more than four parts).
        disturbance: error, as a fraction of the disc's minor axis, per unit
            of ``SigmaInputs.disturbance`` (a line or dirt across a part kept
            pulls its centroid by a share of the part's size).
        direction, slot: factors for those keypoint kinds (the centre's is 1).
        direction_size_px2: the directional keypoint's own size term [px^2].
        occluded: factor when the face shows an occluder.
    """

    floor_px: float = 0.0207
    size_px2: float = 0.0
    spread_px2: float = 0.0
    residual: float = 0.234
    disturbance: float = 0.0131
    direction: float = 2.02
    direction_size_px2: float = 0.0
    slot: float = 0.909
    occluded: float = 40.0


# Calibrated by scripts/calibrate_sigma.py --n 150 (seed 11) against the
# simulator's truth (signpose.sim.crops); its fit drove the size and spread
# terms to zero (the disturbance and residual terms carry what they would).
SIGMA_MODEL = SigmaModel()


@dataclass(frozen=True)
class SigmaInputs:
    """What the decoder saw of one sign, the inputs of ``keypoint_sigmas``.

    Attributes:
        minor_px: the disc's minor axis [px].
        spread: interquartile spread of the disc's black samples, as a
            fraction of white - black.
        residual_px: RMS residual of the homography fit [px] (NaN: exact fit).
        crossed: an occluder crosses the face (its parts are dropped).
        disturbance: the larger of 1 - the least white fraction inside the
            parts kept and their largest fill deficit (``_Refined``).
    """

    minor_px: float
    spread: float
    residual_px: float
    crossed: bool
    disturbance: float = 0.0


def keypoint_sigmas(
    inputs: SigmaInputs, names: Iterable[str], model: SigmaModel = SIGMA_MODEL
) -> dict[str, tuple[float, float]]:
    """Per keypoint (sigma_u, sigma_v) [px] under ``model``.

    The two axes are equal: on the calibration sets the measured u and v
    errors differ by less than the model's own spread across conditions.
    """
    m = model
    minor = max(inputs.minor_px, 1.0)
    rms = inputs.residual_px if math.isfinite(inputs.residual_px) else 0.0
    base2 = (
        m.floor_px**2
        + (m.size_px2 / minor) ** 2
        + (m.spread_px2 * inputs.spread / minor) ** 2
        + (m.residual * rms) ** 2
        + (m.disturbance * inputs.disturbance * minor) ** 2
    )
    base = math.sqrt(base2) * (m.occluded if inputs.crossed else 1.0)
    out = {}
    for name in names:
        if name == "direction":
            # The thin rectangle is a few pixels wide: its size term is its own.
            s = math.hypot(base * m.direction, m.direction_size_px2 / minor)
        else:
            s = base * (1.0 if name == "center" else m.slot)
        out[name] = (s, s)
    return out


def mean_sigma(sigmas: dict[str, tuple[float, float]]) -> float:
    """One sigma for all keypoints [px]: the geometric mean of the axes' sigmas."""
    return float(np.sqrt(np.mean([su * sv for su, sv in sigmas.values()])))
