"""Plane-to-image homographies for the sign: mapping, fitting, disc ellipse.

Shared by the decoder (fitting the sign's homography to its rectangles) and the
synthetic crop generator (ground truth). A homography here is a (3, 3) array
``image_H_sign`` mapping sign-plane points (x, y, 1) to image pixels (u, v, 1),
normalised so that ``H[2, 2] == 1`` where possible.
"""

from __future__ import annotations

import functools
import math

import cv2
import numpy as np

Ellipse = tuple[tuple[float, float], tuple[float, float], float]


def apply_homography(h: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Map (N, 2) points through the (3, 3) homography ``h``; returns (N, 2)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 1, 2)
    return cv2.perspectiveTransform(xy, np.asarray(h, dtype=np.float64)).reshape(-1, 2)


def prepare_source(src: np.ndarray) -> tuple:
    """The ``src``-only part of ``fit_homography`` (for fits to fixed source points).

    Returns an opaque tuple to pass as ``fit_homography(..., prepared=)``.
    """
    src = np.asarray(src, float)
    n = len(src)
    cs = src.mean(axis=0)
    s = src - cs
    ks = math.sqrt(2.0 * n / max(float((s * s).sum()), 1e-24))
    s *= ks
    a = np.zeros((2 * n, 8))
    a[0::2, 0:2] = s
    a[0::2, 2] = 1.0
    a[1::2, 3:5] = s
    a[1::2, 5] = 1.0
    ts = np.array([[ks, 0.0, -ks * cs[0]], [0.0, ks, -ks * cs[1]], [0.0, 0.0, 1.0]])
    flags = cv2.DECOMP_QR if n > 4 else cv2.DECOMP_LU
    return n, s, a, ts, flags


def fit_homography(
    src: np.ndarray, dst: np.ndarray, prepared: tuple | None = None
) -> np.ndarray | None:
    """Least-squares homography with ``dst ~ H src`` (linear, h33 = 1).

    Both point sets are shifted to their centroids and scaled to unit spread
    first (Hartley), which keeps the linear system well conditioned.

    Args:
        src: (N, 2) points, N >= 4, no three on a line.
        dst: (N, 2) corresponding points.
        prepared: ``prepare_source(src)`` when fitting the same ``src`` often.

    Returns:
        (3, 3) homography, or None when the points are degenerate.
    """
    if prepared is None:
        if len(src) < 4:
            return None
        prepared = prepare_source(src)
    n, s, a, ts, flags = prepared
    dst = np.asarray(dst, float)
    cd = dst.mean(axis=0)
    d = dst - cd
    kd = math.sqrt(2.0 * n / max(float((d * d).sum()), 1e-24))
    d *= kd
    a = a.copy()
    a[0::2, 6:8] = -d[:, :1] * s
    a[1::2, 6:8] = -d[:, 1:2] * s
    ok, x = cv2.solve(a, d.reshape(-1, 1), flags=flags)
    if not ok:
        return None
    hn = np.append(x.ravel(), 1.0).reshape(3, 3)
    cu, cv = cd.tolist()
    td_inv = np.array([[1.0 / kd, 0.0, cu], [0.0, 1.0 / kd, cv], [0.0, 0.0, 1.0]])
    h = td_inv @ hn @ ts
    h22 = float(h[2, 2])
    if not np.isfinite(h).all() or abs(h22) < 1e-12:
        return None
    return h / h22


def affine_design(src: np.ndarray) -> np.ndarray:
    """The (N, 3) design matrix [src, 1] of ``fit_affine`` (for fits to fixed source points)."""
    src = np.asarray(src, float)
    return np.column_stack([src, np.ones(len(src))])


def fit_affine(
    src: np.ndarray, dst: np.ndarray, design: np.ndarray | None = None
) -> np.ndarray | None:
    """Least-squares affine map (as a (3, 3) homography) with ``dst ~ A src``; N >= 3.

    ``design``: ``affine_design(src)`` when fitting the same ``src`` often.
    """
    dst = np.asarray(dst, float)
    if len(src) < 3:
        return None
    a = affine_design(src) if design is None else design
    ok, sol = cv2.solve(a, dst, flags=cv2.DECOMP_QR if len(src) > 3 else cv2.DECOMP_LU)
    if not ok:
        return None
    h = np.eye(3)
    h[:2, :] = sol.T
    return h


@functools.cache
def _next_vertex(m: int) -> np.ndarray:
    """Index of each vertex's successor in an m-gon (np.roll costs 3x more per call)."""
    return np.arange(1, m + 1) % m


def polygon_centroids(polys: np.ndarray) -> np.ndarray:
    """Area centroids of (K, M, 2) polygons; returns (K, 2)."""
    x, y = polys[..., 0], polys[..., 1]
    nxt = _next_vertex(x.shape[1])
    xn, yn = x[:, nxt], y[:, nxt]
    cross = x * yn - xn * y  # (K, M): twice the signed area of each edge's triangle
    area6 = 3.0 * cross.sum(axis=1)
    return (
        np.stack([((x + xn) * cross).sum(axis=1), ((y + yn) * cross).sum(axis=1)], axis=1)
        / (area6[:, None])
    )


def ellipse_from_conic(c: np.ndarray) -> Ellipse:
    """Centre, full axes (major, minor) and angle [deg] of the ellipse x^T c x = 0.

    Angle: of the major axis, from the u axis toward +v, in [0, 180)
    (cv2.RotatedRect convention, axes given major first), in closed form.

    Raises:
        ValueError: the conic is not a real ellipse (e.g. the image of a disc
            that the horizon line crosses).
    """
    a, b, d = float(c[0, 0]), float(c[0, 1]), float(c[1, 1])
    e, f, g = float(c[0, 2]), float(c[1, 2]), float(c[2, 2])
    det = a * d - b * b
    if det <= 0:
        raise ValueError("conic is not an ellipse")
    cx = (b * f - d * e) / det
    cy = (b * e - a * f) / det
    k = -(a * cx * cx + 2 * b * cx * cy + d * cy * cy + 2 * e * cx + 2 * f * cy + g)
    m = 0.5 * (a + d)
    r = math.sqrt(0.25 * (a - d) ** 2 + b * b)
    lo, hi = (m - r) / k, (m + r) / k
    if not (lo > 0 and hi > 0):
        raise ValueError("conic is not a real ellipse")
    # Major axis: eigenvector of the smaller eigenvalue (m - r).
    angle = 0.5 * math.degrees(math.atan2(2 * b, a - d)) + 90.0
    return (cx, cy), (2.0 / math.sqrt(lo), 2.0 / math.sqrt(hi)), angle % 180.0


def disc_ellipse(image_H_sign: np.ndarray, diameter: float) -> Ellipse:
    """Exact image of the rim of a disc of ``diameter`` centred at the sign origin."""
    r = diameter / 2.0
    _, hinv = cv2.invert(np.asarray(image_H_sign, dtype=np.float64))
    # The rim x^2 + y^2 = r^2 as a conic, carried to the image.
    return ellipse_from_conic(hinv.T @ (np.array([[1.0], [1.0], [-r * r]]) * hinv))


def px_per_diameter(image_H_sign: np.ndarray) -> float:
    """Pixels per sign unit at the sign's centre: sqrt |det| of the homography's
    Jacobian at the sign frame's origin."""
    (a, b, c), (d, e, f), (g, k, w) = np.asarray(image_H_sign, float).tolist()
    ja, jb, jc, jd = (a * w - c * g), (b * w - c * k), (d * w - f * g), (e * w - f * k)
    return math.sqrt(abs(ja * jd - jb * jc)) / (w * w)
