"""frontend.verify's fast path against a slow reference built from the decoder's own pieces.

``_reference_verify_sign`` is verify_sign as it was before it was made
cheaper (commit 23ed9e8; with the decoder's per-part measurements for the
sigmas, ``keypoint_noise.measure_parts``, added as the fast path follows
them since 9a5b26e): the alignment with numpy scalar images, the decoder's
``_subpixel_centroids`` and ``_fill_deficit``, one projection per use. The
fast path must give the same outcome and the same reading (code, reason,
keypoints to 1e-9 px, sigmas, ellipse, homography, erased slots).
scripts/bench_frontend.py --check-verify runs the same comparison on the
bench's frames.
"""

import math

import cv2
import numpy as np
from signpose.frontend import decoder as dec
from signpose.frontend import verify as ver
from signpose.frontend.decoder import _CODE_PARTS
from signpose.frontend.homography import fit_homography, polygon_centroids
from signpose.frontend.keypoint_noise import measure_parts
from signpose.frontend.verify import VerifyOutcome, verify_sign

from signpose.sim.crops import render_crop


def _reference_align(gray, image_H_sign, s):
    h, w = gray.shape
    half = ver._HALF_SQUARE + s.align_grow
    corners = np.array([[-half, -half], [half, -half], [half, half], [-half, half]])
    hom = np.array(image_H_sign, float)
    total_u = total_v = 0.0
    for _ in range(s.align_passes):
        quad = dec._project(hom, corners)
        us, vs = quad[:, 0].tolist(), quad[:, 1].tolist()
        u0, v0 = math.floor(min(us)), math.floor(min(vs))
        u1, v1 = math.ceil(max(us)) + 1, math.ceil(max(vs)) + 1
        if not (u0 >= 0 and v0 >= 0 and u1 <= w and v1 <= h) or u1 - u0 < 3 or v1 - v0 < 3:
            return None, 0.0
        win = gray[v0:v1, u0:u1]
        mask = np.zeros(win.shape, np.uint8)
        pts = np.round((quad - (u0, v0)) * 16).astype(np.int32)
        cv2.fillConvexPoly(mask, pts, 255, lineType=cv2.LINE_8, shift=4)
        lo, hi, _, _ = cv2.minMaxLoc(win, mask)
        if hi - lo < 25.0:
            return None, 0.0
        wt = cv2.subtract(win, np.full_like(win, int(round(0.5 * (lo + hi)))))
        wt = cv2.bitwise_and(cv2.min(wt, np.full_like(win, int((hi - lo) // 2))), mask)
        mo = cv2.moments(wt)
        if mo["m00"] <= 0:
            return None, 0.0
        du = u0 + mo["m10"] / mo["m00"] - hom[0, 2] / hom[2, 2]
        dv = v0 + mo["m01"] / mo["m00"] - hom[1, 2] / hom[2, 2]
        hom[0] += du * hom[2]
        hom[1] += dv * hom[2]
        total_u += du
        total_v += dv
    return hom, math.hypot(total_u, total_v)


def _reference_refit(aligned, parts, cents, ds):
    src, quads, flat_quads, prepared, _ = dec._parts_geometry(parts)
    predicted = polygon_centroids(dec._project(aligned, flat_quads).reshape(quads.shape))
    if len(parts) < 4:
        a = cv2.getAffineTransform(predicted.astype(np.float32), cents.astype(np.float32))
        if not np.isfinite(a).all():
            return None, float("nan")
        return np.vstack([a, [0.0, 0.0, 1.0]]) @ aligned, float("nan")
    offset = predicted - dec._project(aligned, src) if ds.perspective_correction else 0.0
    h = fit_homography(src, cents - offset, prepared)
    if h is None or len(parts) == 4:
        return h, float("nan")
    resid = dec._project(h, src) + offset - cents
    return h, float(np.sqrt((resid**2).sum(axis=1).mean()))


def _reference_verify_sign(image, image_H_sign, code, codes=None):
    s, ds, miss = ver.VerifySettings(), ver._DECODER_SETTINGS, ver._miss
    g = dec._as_gray(image)
    allowed = None if codes is None else frozenset(codes)
    parts = _CODE_PARTS[code][0]
    if len(parts) < 3 or (allowed is not None and code not in allowed):
        return miss(VerifyOutcome.NOT_VERIFIABLE)
    h, w = g.shape
    predicted = np.asarray(image_H_sign, float)
    ell = dec._safe_disc_ellipse(predicted)
    if ell is None:
        return miss(VerifyOutcome.NOT_VERIFIABLE)
    (_, _), (major, minor), _ = ell
    if major < max(s.min_major_px, ds.min_sign_px) or minor < ds.min_axis_ratio * major:
        return miss(VerifyOutcome.NOT_VERIFIABLE)
    if not dec._inside(dec._project(predicted, ver._DISC_RIM), w, h, s.edge_margin_px):
        return miss(VerifyOutcome.OUTSIDE)
    aligned, shift = _reference_align(g, predicted, s)
    if aligned is None or shift > s.max_shift * major:
        return miss(VerifyOutcome.NOT_FOUND)
    first = dec._read_slots(g, aligned, ds)
    if first.code is None:
        return miss(VerifyOutcome.SLOT_DIFFERS, first.reason)
    if not dec._consistent(first.code, code) or "x" in first.code:
        return miss(VerifyOutcome.SLOT_DIFFERS)
    cents, valid, white_area = dec._subpixel_centroids(
        g, aligned, parts, first.black, first.white, 1.5
    )
    if not bool(valid.all()):
        return miss(VerifyOutcome.NOT_FOUND)
    h_ref, rms = _reference_refit(aligned, parts, cents, ds)
    if h_ref is None:
        return miss(VerifyOutcome.NOT_FOUND)
    limit = s.max_residual_px + s.max_residual_frac * major
    centres = dec._PART_CENTRES[:2]
    moved = float(np.abs(dec._project(h_ref, centres) - dec._project(aligned, centres)).max())
    if (math.isfinite(rms) and rms > limit) or moved > s.max_moved * major:
        return miss(VerifyOutcome.RESIDUAL)
    reading = dec._read_slots(g, h_ref, ds)
    if reading.code is None or reading.code != code:
        return miss(VerifyOutcome.SLOT_DIFFERS, reading.reason)
    region = dec._Region(
        gray=g,
        holes=[],
        centroids_px=np.zeros((0, 2)),
        cut=dec._LazyFlag(lambda: False),
        rim_contour=None,
        disc_area_px=None,
        disc_centre_px=None,
        allowed=allowed,
        settings=ds,
    )
    accepted, occ, reason = dec._accept_code(region, h_ref, reading, major)
    if accepted != code or occ is None or occ.covered_parts or "x" in occ.pattern:
        return miss(
            VerifyOutcome.REFUSED, reason if accepted is None else dec.DecodeReason.OCCLUDED
        )
    if occ.disturbance > s.max_disturbance:
        return miss(VerifyOutcome.REFUSED, dec.DecodeReason.OCCLUDED)
    ellipse = dec._safe_disc_ellipse(h_ref)
    if ellipse is None:
        return miss(VerifyOutcome.NOT_VERIFIABLE)
    deficit = dec._fill_deficit(aligned, parts, white_area, valid)
    uv = dec._project(h_ref, dec._PART_CENTRES[parts])
    names = [dec._PART_NAMES[p] for p in parts]
    quads = dec._PART_QUADS[parts]
    measured = measure_parts(g, h_ref, names, quads, cents, first.black, first.white)
    result = dec._reading_result(
        code,
        parts,
        uv,
        h_ref,
        ellipse,
        first,
        rms,
        False,
        max(occ.disturbance, deficit),
        (),
        measured,
    )
    return ver.Verification(VerifyOutcome.VERIFIED, result)


def _same(a, b) -> bool:
    """Equal, floats and arrays to 1e-9 (relative above 1), NaN equal to NaN."""
    if isinstance(a, float | np.floating) or isinstance(b, float | np.floating):
        return a == b or (math.isnan(a) and math.isnan(b)) or abs(a - b) <= 1e-9 * max(1, abs(a))
    if isinstance(a, np.ndarray):
        return a.shape == b.shape and np.allclose(a, b, rtol=1e-9, atol=1e-9, equal_nan=True)
    if isinstance(a, tuple | list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if hasattr(a, "__dataclass_fields__"):
        return type(a) is type(b) and all(
            _same(getattr(a, f), getattr(b, f)) for f in a.__dataclass_fields__
        )
    return a == b


def _differences(fast, slow) -> list[str]:
    """Names of the fields where two verifications differ (empty: the same)."""
    out = [] if fast.outcome is slow.outcome else ["outcome"]
    fields = fast.result.__dataclass_fields__
    return out + [f for f in fields if not _same(getattr(fast.result, f), getattr(slow.result, f))]


def _predictions(n: int, seed: int):
    """``n`` (image, image_H_sign, predicted code) of rendered crops: clean and
    occluded signs of 3-6 white parts, predictions off by a few percent of the
    diameter, and every fourth prediction with one bit of the code flipped."""
    rng = np.random.default_rng(seed)
    codes = ("1011", "0110", "0001", "1111", "0101", "1000", "1110")
    options = ({}, {}, {"member": True}, {"power_line": True}, {"dirt": True})
    for i in range(n):
        code = codes[i % len(codes)]
        crop = render_crop(
            code,
            rng,
            sign_px=float(rng.uniform(22, 90)),
            rotation_deg=float(rng.uniform(0, 360)),
            tilt_deg=float(rng.uniform(0, 45)),
            tilt_axis_deg=float(rng.uniform(0, 360)),
            noise_sigma=2.0,
            background=str(rng.choice(["sky", "plain", "lattice"])),
            **options[i % len(options)],
        )
        _, names, src = _CODE_PARTS[code]
        dst = np.array([crop.keypoints_px[nm] for nm in names], np.float32)
        if len(names) >= 4:
            h, _ = cv2.findHomography(src, dst)
        else:
            h = np.vstack([cv2.getAffineTransform(src.astype(np.float32), dst), [0, 0, 1.0]])
        du, dv = rng.normal(0.0, 0.03 * crop.diameter_px, 2)
        h = np.array([[1.0, 0.0, du], [0.0, 1.0, dv], [0.0, 0.0, 1.0]]) @ h
        predicted = code
        if i % 4 == 3:
            k = int(rng.integers(4))
            predicted = code[:k] + ("1" if code[k] == "0" else "0") + code[k + 1 :]
        yield crop.image, h, predicted


def test_the_fast_verification_equals_the_reference_on_60_predictions():
    outcomes = set()
    for image, h, code in _predictions(60, 14):
        if code.count("1") == 0:
            continue
        fast, slow = verify_sign(image, h, code), _reference_verify_sign(image, h, code)
        assert not _differences(fast, slow), (code, _differences(fast, slow))
        outcomes.add(fast.outcome)
    # The comparison covers the verified path and refusals at several stages.
    assert VerifyOutcome.VERIFIED in outcomes and len(outcomes) >= 3, outcomes


def test_the_alignment_equals_the_numpy_reference_exactly():
    s = ver.VerifySettings()
    found = 0
    for image, h, _ in _predictions(30, 15):
        fast, slow = ver._align(image, h, s), _reference_align(image, h, s)
        assert (fast[0] is None) == (slow[0] is None)
        if fast[0] is not None:
            found += 1
            assert np.array_equal(fast[0], slow[0]) and fast[1] == slow[1]
    assert found >= 20


def test_the_part_centroids_equal_the_decoders_subpixel_centroids():
    measured = 0
    for image, h, code in _predictions(30, 16):
        parts = _CODE_PARTS[code][0]
        reading = dec._read_slots(image, h, ver._DECODER_SETTINGS)
        black, white = reading.black, reading.white
        cents, valid, area = dec._subpixel_centroids(image, h, parts, black, white, 1.5)
        fast = ver._part_centroids(image, h, parts, black, white, 1.5)
        assert (fast is None) == (not valid.all())
        if fast is not None:
            measured += 1
            assert np.abs(fast[0] - cents).max() < 1e-9  # [px]
            assert np.allclose(fast[1], area, rtol=1e-12)
    # A window outside the image: not measured, as in the decoder.
    image, h, code = next(_predictions(1, 16))
    far = np.array([[1.0, 0.0, -0.4 * image.shape[1]], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) @ h
    assert ver._part_centroids(image, far, _CODE_PARTS[code][0], 20.0, 200.0, 1.5) is None
    assert measured >= 20
