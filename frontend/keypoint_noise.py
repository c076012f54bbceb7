"""Keypoint noise of one decoded sign: ``sigma_px`` per keypoint and axis (issue 11, item 3).

The decoder measures what it saw of a sign (``SigmaInputs``); ``keypoint_sigmas``
turns that into per-keypoint (sigma_u, sigma_v) under a ``SigmaModel``, whose
constants scripts/calibrate_sigma.py fits against the simulator's truth (and
scripts/eval_decoder.py --independent checks on scenes the fit never saw).

Each keypoint kind (the centre, the directional rectangle, a coded slot) has
its own ``KindNoise``; the variance is a sum of terms, each a constant times
the square of one thing the decoder measured (``variance_terms``):

    sigma_a^2 = floor^2 + (size / minor)^2 + (noise_px * noise)^2
              + (spread_px * [spread - 3 noise]+ [nothing crosses])^2 + (residual * rms)^2
              + (disturbance * [disturbance_in - 5 noise]+ * minor)^2
              + (stray * [stray_k - 5 noise]+ * minor)^2
              + (inside * [1 - inside_k - 5 noise]+ * minor)^2
              + (own_residual * own_k,a)^2
              + (crossed_px^2 + (crossed * minor)^2) [an occluder crosses the face]

``a`` is the image axis (u or v) and ``k`` the keypoint's own part:
``own_k,a`` is its measured centroid minus the homography's prediction along
that axis (only when more than four parts over-determine the fit), so a part
pulled by a line or dirt makes its own keypoint's sigma larger along the
pull; ``stray_k`` is the white just outside its centroid window (glare, blur
beyond it) and ``inside_k`` the least white inside it (a line across it). The
image noise (``noise``, the black's high-pass noise over the contrast) is
taken off the spread, the disturbance, the stray white and the inside
deficit first ([x]+ = max(x, 0)): a minimum over noisy samples falls short
of white by a few noise sigmas on a clean sign, and renderers and cameras
differ in their noise while the centroids barely feel it. The spread stands
for uneven shading of the face (glare); with an occluder across the face it
is the occluder's own gray and does not count.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np
from signpose.frontend import occlusion
from signpose.frontend.homography import polygon_centroids

# The names of the variance terms, in the order of ``variance_terms``' columns
# and of ``KindNoise``'s fields.
TERMS: tuple[str, ...] = (
    "floor_px",
    "size_px2",
    "spread_px",
    "residual",
    "disturbance",
    "own_residual",
    "crossed_px",
    "noise_px",
    "stray",
    "inside",
    "crossed",
)
# Multiples of the noise taken off the spread and off the other shortfalls.
_SPREAD_NOISE = 3.0
_SHORTFALL_NOISE = 5.0


@dataclass(frozen=True)
class KindNoise:
    """Constants of one keypoint kind's variance (see the module docstring).

    Attributes:
        floor_px: error left on large clean signs [px].
        size_px2: size term [px^2], over the disc's minor axis [px].
        spread_px: error per unit of the black samples' spread beyond the noise [px].
        residual: factor on the homography fit's RMS residual.
        disturbance: error as a fraction of the disc's minor axis per unit
            of ``SigmaInputs.disturbance`` beyond the noise.
        own_residual: factor on the keypoint's own part's residual, per axis.
        crossed_px: error added when a thin line crosses the face [px].
        noise_px: error per unit of the image noise (over the contrast) [px].
        stray: error as a fraction of the minor axis per unit of stray white
            beyond the noise outside the keypoint's own part.
        inside: the same per unit of the part's inside shortfall of white.
        crossed: error as a fraction of the minor axis when an occluder
            crosses the face (a band's edges pull the parts it leaves).
    """

    floor_px: float
    size_px2: float = 0.0
    spread_px: float = 0.0
    residual: float = 0.0
    disturbance: float = 0.0
    own_residual: float = 0.0
    crossed_px: float = 0.0
    noise_px: float = 0.0
    stray: float = 0.0
    inside: float = 0.0
    crossed: float = 0.0

    def coefficients(self) -> np.ndarray:
        """(len(TERMS),) the constants, in ``TERMS`` order."""
        return np.array([getattr(self, n) for n in TERMS], dtype=float)


@dataclass(frozen=True)
class SigmaModel:
    """Keypoint noise from what the decoder sees, one ``KindNoise`` per keypoint kind.

    Calibrated by scripts/calibrate_sigma.py.
    """

    center: KindNoise
    direction: KindNoise
    slot: KindNoise

    def kind(self, name: str) -> KindNoise:
        """The constants of keypoint ``name`` (``slotK`` share the slot's)."""
        if name == "center":
            return self.center
        return self.direction if name == "direction" else self.slot


def kind_of(name: str) -> str:
    """The keypoint kind of ``name``: "center", "direction" or "slot"."""
    return name if name in ("center", "direction") else "slot"


# Calibrated by `.venv/bin/python scripts/calibrate_sigma.py --n 150 --seed 11`
# against the simulator's truth (signpose.sim.crops, 12 conditions), the
# constants as it prints them (rounded to 3 digits). Terms the fit drove to
# ~0 stay in the model, a later calibration may need them.
SIGMA_MODEL = SigmaModel(
    center=KindNoise(
        floor_px=0.0251,
        size_px2=0.000367,
        spread_px=4.3,
        residual=3.24e-07,
        disturbance=0.0121,
        own_residual=0.419,
        crossed_px=7.42e-05,
        noise_px=0.00935,
        stray=0.0181,
        inside=0.0107,
        crossed=6.29e-08,
    ),
    direction=KindNoise(
        floor_px=0.027,
        size_px2=0.429,
        spread_px=1.95,
        residual=0.309,
        disturbance=0.0278,
        own_residual=0.0425,
        crossed_px=0.376,
        noise_px=0.0684,
        stray=0.0437,
        inside=0.0229,
        crossed=2.06e-09,
    ),
    slot=KindNoise(
        floor_px=0.0242,
        size_px2=4.71e-08,
        spread_px=2.57,
        residual=0.113,
        disturbance=0.0122,
        own_residual=0.313,
        crossed_px=0.000306,
        noise_px=0.0106,
        stray=0.0189,
        inside=0.00811,
        crossed=1.67e-06,
    ),
)


@dataclass(frozen=True)
class SigmaInputs:
    """What the decoder saw of one sign, the inputs of ``keypoint_sigmas``.

    Attributes:
        minor_px: the disc's minor axis [px].
        spread: interquartile spread of the disc's black samples, as a
            fraction of white - black.
        residual_px: RMS residual of the homography fit [px] (NaN: exact fit).
        crossed: an occluder crosses the face (its parts are dropped, or a
            thin line was closed away before reading).
        disturbance: the larger of 1 - the least white fraction inside the
            parts kept and their largest fill deficit (``_Refined``).
        part_residual_px: part name -> (du, dv) [px], the part's measured
            centroid minus the fitted homography's prediction of it (only
            for fits of more than four parts; see ``part_residuals_px``).
        part_stray: part name -> mean white fraction just outside the part's
            centroid window (glare, blur or a bright line beyond it pull the
            centroid; ``measure_parts``).
        part_inside: part name -> the least white fraction inside the part
            (a line or dirt across it).
        noise: robust high-pass noise of the disc's black, as a fraction of
            white - black (NaN: not measured).
    """

    minor_px: float
    spread: float
    residual_px: float
    crossed: bool
    disturbance: float = 0.0
    part_residual_px: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    part_stray: Mapping[str, float] = field(default_factory=dict)
    part_inside: Mapping[str, float] = field(default_factory=dict)
    noise: float = float("nan")


def part_residuals_px(
    image_H_sign: np.ndarray,
    names: list[str],
    quads: np.ndarray,
    centroids_px: np.ndarray,
) -> dict[str, tuple[float, float]]:
    """Each part's measured centroid minus its predicted one [px] (more than four parts).

    Args:
        image_H_sign: (3, 3) the fitted homography [sign units -> px].
        names: the parts' keypoint names.
        quads: (P, 4, 2) the parts' corners in the sign plane (``image_H_sign``'s units).
        centroids_px: (P, 2) their measured centroids [px].

    Returns:
        name -> (du, dv); empty for four or fewer parts (an exact fit leaves
        no residual to see).
    """
    if len(names) <= 4:
        return {}
    flat = np.asarray(quads, dtype=float).reshape(-1, 2)
    p = np.c_[flat, np.ones(len(flat))] @ np.asarray(image_H_sign, dtype=float).T
    proj = (p[:, :2] / p[:, 2:]).reshape(-1, 4, 2)
    r = np.asarray(centroids_px, dtype=float) - polygon_centroids(proj)
    return {n: (float(du), float(dv)) for n, (du, dv) in zip(names, r, strict=True)}


# Black sample rings [diameters]: between the location square's corners
# (0.127) and the slots (0.168), and just inside the rim (0.5).
_RING_ANGLES = np.linspace(0.0, 2 * math.pi, 64, endpoint=False)
_BLACK_RINGS = [
    r * np.stack([np.cos(_RING_ANGLES), np.sin(_RING_ANGLES)], axis=1) for r in (0.148, 0.46)
]
_RINGS_XY = np.concatenate(_BLACK_RINGS)
_EDGE_T = np.linspace(0.1, 0.9, 5)
# Where the stray samples lie outside a part: beyond the decoder's centroid
# window (1.5 px), at most this far in diameters (the gaps between parts).
_STRAY_PX = 2.5
_STRAY_MAX = 0.04


@dataclass(frozen=True)
class PartMeasures:
    """Per-part measurements of one reading for ``SigmaInputs`` (see its attributes)."""

    residual_px: dict[str, tuple[float, float]]
    stray: dict[str, float]
    inside: dict[str, float]
    noise: float


def _project(h: np.ndarray, xy: np.ndarray) -> np.ndarray:
    p = np.c_[np.asarray(xy, dtype=float).reshape(-1, 2), np.ones(len(xy))] @ h.T
    return p[:, :2] / p[:, 2:]


def _sample(gray: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(N,) bilinear gray levels at (N, 2) pixels, NaN outside the image."""
    h, w = gray.shape
    u, v = uv[:, 0], uv[:, 1]
    ok = (u >= 0) & (v >= 0) & (u <= w - 1) & (v <= h - 1)
    out = np.full(len(uv), np.nan)
    if ok.any():
        m = uv[ok].astype(np.float32).reshape(1, -1, 2)
        g = cv2.remap(gray, m, None, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        out[ok] = g.reshape(-1)
    return out


def _noise(gray: np.ndarray, image_H_sign: np.ndarray, contrast: float) -> float:
    """Robust noise of the black rings over ``contrast``: second differences
    along each ring cancel smooth shading (glare, vignetting)."""
    g = _sample(gray, _project(image_H_sign, _RINGS_XY)).reshape(len(_BLACK_RINGS), -1)
    d = np.roll(g, 1, axis=1) - 2 * g + np.roll(g, -1, axis=1)
    d = d[np.isfinite(d)]
    if len(d) < 16:
        return float("nan")
    return float(1.4826 * np.median(np.abs(d)) / math.sqrt(6.0) / max(contrast, 1e-6))


@functools.cache
def _outline_geometry(quads_key: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Each part's outline samples and outward unit normals in the sign plane,
    (P * 4 * len(_EDGE_T), 2) each, for ``quads`` flattened as ``quads_key``."""
    quads = np.array(quads_key).reshape(-1, 4, 2)
    base, normals = [], []
    for q in quads:
        c = q.mean(axis=0)
        for i in range(4):
            a, b = q[i], q[(i + 1) % 4]
            n = np.array([b[1] - a[1], a[0] - b[0]]) / max(float(np.hypot(*(b - a))), 1e-12)
            if n @ ((a + b) / 2 - c) < 0:
                n = -n
            base.append(a + np.outer(_EDGE_T, b - a))
            normals.append(np.tile(n, (len(_EDGE_T), 1)))
    return np.concatenate(base), np.concatenate(normals)


def _stray(gray, image_H_sign, quads, black, white) -> np.ndarray:
    """(P,) mean white fraction on each part's outline grown by ``_STRAY_PX``
    (one projection and one sampling for all parts)."""
    steps = _project(image_H_sign, np.array([[0.0, 0.0], [0.01, 0.0], [0.0, 0.01]]))
    scale = math.sqrt(abs(np.linalg.det(steps[1:] - steps[0]))) / 0.01  # px per diameter
    grow = min(_STRAY_PX / max(scale, 1e-9), _STRAY_MAX)
    base, normals = _outline_geometry(tuple(np.asarray(quads, dtype=float).ravel().tolist()))
    g = _sample(gray, _project(image_H_sign, base + grow * normals))
    frac = np.clip((g - black) / max(white - black, 1e-6), 0.0, 1.0).reshape(len(quads), -1)
    ok = np.isfinite(frac)
    count = ok.sum(axis=1)
    total = np.where(ok, frac, 0.0).sum(axis=1)
    return np.where(count > 0, total / np.maximum(count, 1), 0.0)


def measure_parts(
    gray: np.ndarray,
    image_H_sign: np.ndarray,
    names: list[str],
    quads: np.ndarray,
    centroids_px: np.ndarray,
    black: float,
    white: float,
) -> PartMeasures:
    """What the image shows around each measured part, for its keypoint's sigma.

    Args:
        gray: (H, W) the crop the centroids were measured in.
        image_H_sign: (3, 3) the fitted homography [sign units -> px].
        names: the parts' keypoint names.
        quads: (P, 4, 2) the parts' corners in the sign plane.
        centroids_px: (P, 2) their measured centroids [px].
        black, white: the reading's gray levels.
    """
    h = np.asarray(image_H_sign, dtype=float)
    quads = np.asarray(quads, dtype=float)
    thin = np.array([n == "direction" for n in names], dtype=bool)
    inside = occlusion.interior_min_white(gray, h, quads, black, white, thin)
    stray = _stray(gray, h, quads, black, white)
    return PartMeasures(
        residual_px=part_residuals_px(h, names, quads, centroids_px),
        stray={n: float(v) for n, v in zip(names, stray, strict=True)},
        inside={n: float(v) for n, v in zip(names, inside, strict=True)},
        noise=_noise(gray, h, white - black),
    )


def variance_terms(inputs: SigmaInputs, name: str) -> np.ndarray:
    """(2, len(TERMS)) the squared measured quantities of keypoint ``name``, per axis (u, v).

    ``sigma_a^2 = variance_terms(...)[a] @ kind.coefficients() ** 2``.
    """
    minor = max(inputs.minor_px, 1.0)
    rms = inputs.residual_px if math.isfinite(inputs.residual_px) else 0.0
    # Unmeasured noise (a reading built without ``measure_parts``) takes
    # nothing off: the shortfalls count in full.
    noise = inputs.noise if math.isfinite(inputs.noise) else 0.0
    short = _SHORTFALL_NOISE * noise
    own = inputs.part_residual_px.get(name, (0.0, 0.0))
    stray = max(inputs.part_stray.get(name, 0.0) - short, 0.0)
    inside = max(1.0 - inputs.part_inside.get(name, 1.0) - short, 0.0)
    head = [
        1.0,
        1.0 / minor**2,
        0.0 if inputs.crossed else max(inputs.spread - _SPREAD_NOISE * noise, 0.0) ** 2,
        rms**2,
        (max(inputs.disturbance - short, 0.0) * minor) ** 2,
    ]
    crossed = 1.0 if inputs.crossed else 0.0
    tail = [
        crossed,
        noise**2,
        (stray * minor) ** 2,
        (inside * minor) ** 2,
        crossed * minor**2,
    ]
    return np.array([head + [own[0] ** 2] + tail, head + [own[1] ** 2] + tail])


def keypoint_sigmas(
    inputs: SigmaInputs, names: Iterable[str], model: SigmaModel = SIGMA_MODEL
) -> dict[str, tuple[float, float]]:
    """Per keypoint (sigma_u, sigma_v) [px] under ``model``.

    The axes differ only through the keypoint's own part's residual (a pull
    along one axis); every other term is isotropic.
    """
    out = {}
    for name in names:
        c2 = model.kind(name).coefficients() ** 2
        su2, sv2 = variance_terms(inputs, name) @ c2
        out[name] = (math.sqrt(su2), math.sqrt(sv2))
    return out


def mean_sigma(sigmas: dict[str, tuple[float, float]]) -> float:
    """One sigma for all keypoints [px]: the geometric mean of the axes' sigmas."""
    return float(np.sqrt(np.mean([su * sv for su, sv in sigmas.values()])))
