"""Per-frame imaging conditions of a simulated flight: JPEG quality, vibration, exposure.

Each condition is switchable (``ConditionSettings``; all off by default) and
drawn for the whole flight at once from its own seeded stream, so a burst or
an exposure step spans consecutive frames as it does on a real UAV:

    jpeg_range      JPEG round trip with a quality drawn per frame, uniform in
                    [lo, hi] (e.g. (70, 90)); None keeps ``SimSettings.jpeg_quality``.
    vibration       expected vibration bursts per second: a burst lasts 0.1-0.4 s
                    and adds to every motion blur of each of its frames a segment
                    of 3-12 px (at 1920 px width, scaled with the width) in a
                    random direction.
    exposure_steps  expected auto-exposure steps per second: the gain jumps by a
                    factor 0.6-1.5 (log-uniform) and relaxes back with a 0.8 s
                    time constant, on top of ``flight.lighting_at``'s slow drift
                    (both need ``SimSettings.lighting``; vibration needs ``blur``).

What each frame got is written to ``boxes.jsonl`` (``signpose.io.boxes.FrameConditions``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

BURST_S = (0.1, 0.4)
BURST_PX_AT_1920 = (3.0, 12.0)
STEP_FACTOR = (0.6, 1.5)
STEP_RELAX_S = 0.8


@dataclass(frozen=True)
class ConditionSettings:
    """Per-frame conditions (see the module docstring)."""

    jpeg_range: tuple[int, int] | None = None
    vibration: float = 0.0
    exposure_steps: float = 0.0


@dataclass(frozen=True)
class FrameDraw:
    """One frame's draw: JPEG quality (None: the flight's), vibration [px], gain factor."""

    jpeg_quality: int | None
    vibration_px: tuple[float, float]
    gain_factor: float


def _jpeg(settings: ConditionSettings, n: int, seed: int) -> list[int | None]:
    if settings.jpeg_range is None:
        return [None] * n
    lo, hi = settings.jpeg_range
    return [int(q) for q in np.random.default_rng([seed, 8080]).integers(lo, hi + 1, n)]


def _vibration(
    settings: ConditionSettings, n: int, fps: float, width: int, seed: int
) -> list[tuple[float, float]]:
    out = [(0.0, 0.0)] * n
    if settings.vibration <= 0:
        return out
    rng = np.random.default_rng([seed, 8181])
    scale = width / 1920.0
    i = 0
    while i < n:
        if rng.random() < settings.vibration / fps:
            length = max(1, int(round(rng.uniform(*BURST_S) * fps)))
            amplitude = rng.uniform(*BURST_PX_AT_1920) * scale
            for k in range(i, min(n, i + length)):
                a = rng.uniform(0, 2 * math.pi)
                out[k] = (amplitude * math.cos(a), amplitude * math.sin(a))
            i += length
        else:
            i += 1
    return out


def _gain_factors(settings: ConditionSettings, n: int, fps: float, seed: int) -> list[float]:
    out = [1.0] * n
    if settings.exposure_steps <= 0:
        return out
    rng = np.random.default_rng([seed, 8282])
    step, since = 1.0, 0.0
    lo, hi = (math.log(v) for v in STEP_FACTOR)
    for i in range(n):
        if rng.random() < settings.exposure_steps / fps:
            step, since = math.exp(rng.uniform(lo, hi)), 0.0
        out[i] = 1.0 + (step - 1.0) * math.exp(-since / STEP_RELAX_S)
        since += 1.0 / fps
    return out


def frame_draws(
    settings: ConditionSettings, n_frames: int, fps: float, width: int, seed: int
) -> list[FrameDraw]:
    """The conditions of every frame of a flight of ``n_frames`` at ``fps``, ``width`` px wide."""
    jpeg = _jpeg(settings, n_frames, seed)
    vib = _vibration(settings, n_frames, fps, width, seed)
    gain = _gain_factors(settings, n_frames, fps, seed)
    return [FrameDraw(q, v, g) for q, v, g in zip(jpeg, vib, gain, strict=True)]
