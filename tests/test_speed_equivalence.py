"""The frontend's batched and cached forms give the very numbers of the plain ones (issue 14).

Each function made cheaper for issue 14 (fewer numpy calls, one projection or
one remap for several sets of points, cached geometry) is checked here
against a plain reference written the way the code read before, on random
inputs: bit for bit, not to a tolerance, as the decoder's outcomes on the
cached crops were checked when it was changed.
"""

import math

import cv2
import numpy as np
import pytest
from signpose.frontend import keypoint_noise, occlusion
from signpose.frontend.decoder import _PART_QUADS


def _reference_dark_runs(dark, level):
    n = len(dark)
    if not any(dark):
        return []
    if all(dark):
        return [(0.0, math.pi, sum(level) / n)]
    start = dark.index(False)
    d = dark[start:] + dark[:start]
    lv = level[start:] + level[:start]
    step = 2 * math.pi / n
    out = []
    b, acc = -1, 0.0
    for k in range(n + 1):
        on = k < n and d[k]
        if on and b < 0:
            b, acc = k, 0.0
        if on:
            acc += lv[k]
        elif b >= 0:
            out.append(
                ((start + b + (k - b - 1) / 2.0) * step, (k - b) * step / 2.0, acc / (k - b))
            )
            b = -1
    return out


def test_dark_runs_match_the_sample_by_sample_scan():
    rng = np.random.default_rng(3)
    for _ in range(500):
        n = int(rng.integers(1, 100))
        dark = (rng.random(n) < rng.random()).tolist()
        level = rng.standard_normal(n).tolist()
        assert occlusion._dark_runs(list(dark), level) == _reference_dark_runs(dark, level)


def test_pair_indices_are_triu_indices_and_read_only():
    for n in range(0, 12):
        ii, jj = occlusion._pair_indices(n)
        ri, rj = np.triu_indices(n, 1)
        assert np.array_equal(ii, ri) and np.array_equal(jj, rj)
        with pytest.raises(ValueError):
            ii[:1] = 0


def test_projection_by_columns_is_the_row_product_bit_for_bit():
    rng = np.random.default_rng(4)
    for n in [1, 2, 3, 7, 64, 500, 1999]:
        h = rng.standard_normal((3, 3))
        xy = rng.standard_normal((n, 2))
        p = xy @ h[:, :2].T + h[:, 2]
        assert np.array_equal(keypoint_noise._project(h, xy), p[:, :2] / p[:, 2:])


def test_stray_and_band_in_one_pass_equal_two_strays():
    rng = np.random.default_rng(5)
    for noise in (0.0, 0.03):
        p, s = 5, 20
        stray = np.clip(rng.standard_normal((p, s)), 0.0, 1.0)
        band = np.clip(rng.standard_normal((p, s)), -1.0, 0.0)
        stray[1, 3] = band[2, 0] = np.nan  # samples off the image
        uv = rng.random((2 * p, s, 2)) * 40
        mean, pull = keypoint_noise._stray_and_band(stray, band, uv, noise)
        ref_mean, ref_stray = keypoint_noise._stray(stray, uv[:p].copy(), noise)
        _, ref_band = keypoint_noise._stray(band, uv[p:].copy())
        assert np.array_equal(mean, ref_mean)
        assert np.array_equal(pull, ref_stray + ref_band)


def _gray(rng, size=80):
    g = rng.integers(0, 256, (size, size)).astype(np.uint8)
    return cv2.GaussianBlur(g, (5, 5), 1.5)


def _homography(rng, size=80):
    s = size * (0.55 + 0.2 * rng.random())
    return np.array(
        [
            [s, 0.1 * s * rng.standard_normal(), size / 2 + rng.standard_normal()],
            [0.1 * s * rng.standard_normal(), -s, size / 2 + rng.standard_normal()],
            [1e-3 * rng.standard_normal(), 1e-3 * rng.standard_normal(), 1.0],
        ]
    )


def test_interior_minima_equal_the_per_part_loop():
    rng = np.random.default_rng(6)
    for _ in range(50):
        g, h = _gray(rng), _homography(rng)
        parts = sorted(rng.choice(6, int(rng.integers(1, 7)), replace=False).tolist())
        quads, thin = _PART_QUADS[parts], np.equal(parts, 1)
        got = occlusion.interior_min_white(g, h, quads, 30.0, 200.0, thin)
        pts = [
            (occlusion._THIN_WEIGHTS if t else occlusion._GRID_WEIGHTS) @ q
            for q, t in zip(quads, thin, strict=True)
        ]
        frac = (occlusion._sample(g, occlusion._project(h, np.concatenate(pts))) - 30.0) / 170.0
        ref, start = [], 0
        for p in pts:
            ref.append(float(frac[start : start + len(p)].min()))
            start += len(p)
        assert np.array_equal(got, np.array(ref))


def _reference_bar_beyond(gray, image_H_sign, band, black, contrast, level_in):
    d = band.p1 - band.p0
    d = d / max(float(np.hypot(*d)), 1e-12)
    n = np.array([-d[1], d[0]])
    side = band.half_width + occlusion._BAR_SIDE_GAP
    body = occlusion._SINGLE_BODY * band.half_width
    offsets = (0.0, body, -body, side, -side)
    pts = [band.p0 - t * d + o * n for t in occlusion._SINGLE_BEYOND for o in offsets]
    uv = occlusion._project(image_H_sign, np.asarray(pts))
    h, w = gray.shape
    seen = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] <= h - 1)
    seen = seen.reshape(-1, 5).all(axis=1)
    pts = np.asarray(pts).reshape(-1, 5, 2)
    off_disc = np.hypot(pts[..., 0], pts[..., 1])[:, 3:] > occlusion._OFF_DISC
    frac = ((occlusion._sample(gray, uv) - black) / contrast).reshape(-1, 5)
    inner = frac[:, :3].max(axis=1)
    lower = np.where(off_disc, frac[:, 3:], np.inf).min(axis=1)
    evidence = seen & off_disc.any(axis=1)
    if not evidence[0]:
        return False
    edged = (inner <= occlusion._DARK_FRAC) & (lower - inner >= occlusion._BAR_EDGE_STEP)
    if not (edged | ~evidence).all():
        return False
    level_out = occlusion._median(frac[evidence, :3].ravel().tolist())
    return abs(level_out - level_in) < occlusion._BEHIND_GAP


def _bar_image(h, p0, p1, half_width, size=60):
    """A light crop with one dark bar along the sign-plane line p0 -> p1."""
    _, sign_H_image = cv2.invert(h)
    vv, uu = np.mgrid[0:size, 0:size]
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)
    xy = occlusion._project(sign_H_image, uv)
    d = (p1 - p0) / np.hypot(*(p1 - p0))
    dist = np.abs((xy - p0) @ np.array([-d[1], d[0]]))
    return np.where(dist < half_width, 60, 220).astype(np.uint8).reshape(size, size)


def test_bars_beyond_the_rim_all_at_once_equal_one_at_a_time():
    rng = np.random.default_rng(7)
    hits = 0
    for _ in range(40):
        h = _homography(rng, 60)
        ang = rng.random((6, 2)) * 2 * math.pi
        bands = [
            occlusion.Band(
                0.5 * np.array([math.cos(a), math.sin(a)]),
                0.5 * np.array([math.cos(b), math.sin(b)]),
                float(0.06 + 0.08 * rng.random()),
                in_front=False,
            )
            for a, b in ang
        ]
        # The first band is a real bar (the others cross it or not).
        g = _bar_image(h, bands[0].p0, bands[0].p1, bands[0].half_width)
        bar_level = (60.0 - 40.0) / 150.0
        levels = [bar_level + 0.05 * rng.standard_normal() for _ in bands]
        got = occlusion._bars_beyond(g, h, bands, 40.0, 150.0, levels)
        ref = [
            _reference_bar_beyond(g, h, b, 40.0, 150.0, lv)
            for b, lv in zip(bands, levels, strict=True)
        ]
        assert got == ref
        hits += sum(ref)
    assert hits > 0  # the comparison saw bands that pass
