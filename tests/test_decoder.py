"""frontend.decoder on synthetic crops with known answers (frontend.synth)."""

import json
import math

import cv2
import numpy as np
import pytest
from signpose.frontend.decoder import REASONS, DecoderSettings, decode_region, decode_roi
from signpose.frontend.sign import ALL_CODES, PAPER_CODES

from signpose.cli import main as cli_main
from signpose.sim.crops import render_background, render_crop

# (sign_px, rotation_deg, tilt_deg, blur_px, background)
VARIANTS = (
    (24.0, 17.0, 10.0, 0.0, "sky"),
    (48.0, 133.0, 35.0, 2.0, "plain"),
    (90.0, 251.0, 50.0, 0.0, "lattice"),
    (150.0, 305.0, 20.0, 4.0, "sky"),
)


@pytest.mark.parametrize("code", ALL_CODES)
def test_every_code_decodes(code):
    rng = np.random.default_rng(int(code, 2))
    for sign_px, rot, tilt, blur, bg in VARIANTS:
        crop = render_crop(
            code,
            rng,
            sign_px=sign_px,
            rotation_deg=rot,
            tilt_deg=tilt,
            tilt_axis_deg=rot / 2,
            blur_px=blur,
            noise_sigma=2.0,
            background=bg,
        )
        res = decode_roi(crop.image)
        assert res.code == code, (sign_px, rot, tilt, blur, bg, res.reason)
        assert res.reason == "ok"
        # Every visible keypoint, and only those: centre, direction, white slots.
        assert set(res.keypoints_px) == set(crop.keypoints_px)
        for name, uv in crop.keypoints_px.items():
            assert np.hypot(*np.subtract(res.keypoints_px[name], uv)) < 0.5, name
        assert 0.0 < res.sigma_px < 2.0 and 0.0 <= res.quality <= 1.0


@pytest.mark.parametrize("kind", ["lattice", "lines", "sky", "clutter", "ground", "plain"])
def test_background_has_no_code(kind):
    rng = np.random.default_rng(11)
    for size in (30, 64, 120):
        res = decode_roi(render_background(rng, size, size, kind))
        assert res.code is None
        assert res.reason in REASONS and res.reason != "ok"
        assert res.keypoints_px == {}


def test_code_not_in_map_is_dropped():
    crop = render_crop("0111", np.random.default_rng(4), sign_px=60, rotation_deg=40)
    assert decode_roi(crop.image).code == "0111"
    assert "0111" not in PAPER_CODES
    res = decode_roi(crop.image, codes=PAPER_CODES)
    assert res.code is None and res.reason == "code_not_in_map"
    assert decode_roi(crop.image, codes=["0111", "0001"]).code == "0111"


@pytest.mark.parametrize("shift", [0.3, 0.4, 0.5, 0.6])
def test_sign_cut_by_edge_gives_a_reason_not_a_code(shift):
    """Shift the sign so that the crop edge cuts into the disc (and its slots)."""
    rng = np.random.default_rng(5)
    reasons = []
    for k, code in enumerate(("1111", "1010", "0110", "1000")):
        angle = math.radians(90 * k + 20)
        crop = render_crop(
            code,
            rng,
            sign_px=60,
            rotation_deg=60.0 * k,
            offset_px=(shift * 60 * math.cos(angle), shift * 60 * math.sin(angle)),
        )
        res = decode_roi(crop.image)
        assert res.code in (None, code), (code, shift, res.code)  # never a wrong code
        if shift >= 0.4:  # the edge cuts through the slot ring: no code, a reason
            assert res.code is None and res.reason in REASONS and res.reason != "ok"
            reasons.append(res.reason)
    if reasons:
        assert reasons.count("cut_by_edge") >= len(reasons) / 2, reasons


def test_centre_accuracy_on_clean_tilted_crops():
    """Sub-pixel centre: within 0.15 px on clean, tilted, near (strong-perspective) signs."""
    rng = np.random.default_rng(6)
    errors = []
    for k in range(12):
        code = ALL_CODES[(5 * k) % 16]
        crop = render_crop(
            code,
            rng,
            sign_px=float(rng.uniform(60, 160)),
            rotation_deg=float(rng.uniform(0, 360)),
            tilt_deg=float(rng.uniform(30, 55)),
            tilt_axis_deg=float(rng.uniform(0, 180)),
            focal_px=500.0,
            noise_sigma=1.0,
        )
        res = decode_roi(crop.image)
        assert res.code == code
        errors.append(np.subtract(res.keypoints_px["center"], crop.keypoints_px["center"]))
        # The disc of the fitted homography (from the parts, or from the rim
        # for codes with fewer than two white slots) matches the truth.
        assert np.hypot(*np.subtract(res.ellipse[0], crop.ellipse[0])) < 0.5
        assert res.ellipse[1][0] == pytest.approx(crop.ellipse[1][0], rel=0.02)
    errors = np.array(errors)
    assert np.hypot(errors[:, 0], errors[:, 1]).max() < 0.15
    assert math.sqrt((errors**2).sum(axis=1).mean()) < 0.08


def test_perspective_correction_removes_centroid_bias():
    """Near and oblique: treating centroids as centres is measurably worse."""
    rng = np.random.default_rng(9)
    plain, corrected = [], []
    for k in range(6):
        crop = render_crop(
            "1111", rng, sign_px=180, rotation_deg=30.0 * k, tilt_deg=55, focal_px=400.0
        )
        truth = np.asarray(crop.keypoints_px["center"])
        a = decode_roi(crop.image, settings=DecoderSettings(perspective_correction=False))
        b = decode_roi(crop.image)
        plain.append(np.hypot(*(np.asarray(a.keypoints_px["center"]) - truth)))
        corrected.append(np.hypot(*(np.asarray(b.keypoints_px["center"]) - truth)))
    assert np.mean(corrected) < 0.1
    assert np.mean(plain) > 2 * np.mean(corrected)


def test_decode_region_returns_full_image_pixels():
    rng = np.random.default_rng(8)
    crop = render_crop("1001", rng, sign_px=50, rotation_deg=70, tilt_deg=20, margin=0.1)
    image = render_background(rng, 240, 320, "sky")
    x0, y0 = 131, 77
    h, w = crop.image.shape
    image[y0 : y0 + h, x0 : x0 + w] = crop.image
    res = decode_region(image, (x0 + 3, y0 - 2, w - 4, h + 1), codes=PAPER_CODES)
    assert res.code == "1001"
    for name, (u, v) in crop.keypoints_px.items():
        assert (
            np.hypot(res.keypoints_px[name][0] - (u + x0), res.keypoints_px[name][1] - (v + y0))
            < 0.3
        )


def test_cli_decode_prints_json_lines(tmp_path, capsys):
    good = tmp_path / "sign.png"
    crop = render_crop("0101", np.random.default_rng(3), sign_px=60, rotation_deg=40, tilt_deg=30)
    cv2.imwrite(str(good), crop.image)
    bad = tmp_path / "broken.png"
    bad.write_text("not an image")
    code = cli_main(["decode", str(good), str(bad), "--codes", "0101,0010"])
    lines = [json.loads(s) for s in capsys.readouterr().out.splitlines()]
    assert code == 0 and len(lines) == 2
    assert lines[0]["image"] == str(good) and lines[0]["code"] == "0101"
    assert lines[0]["reason"] == "ok" and lines[0]["sigma_px"] > 0
    u, v = lines[0]["keypoints_px"]["center"]
    assert np.hypot(u - crop.keypoints_px["center"][0], v - crop.keypoints_px["center"][1]) < 0.3
    assert lines[1] == {
        "image": str(bad),
        "code": None,
        "reason": "unreadable",
        "keypoints_px": {},
        "sigma_px": None,
    }
    assert cli_main(["decode", str(bad), str(tmp_path / "missing.png")]) == 2
    assert cli_main(["decode", str(good), "--codes", "0001"]) == 0
    last = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert last["code"] is None and last["reason"] == "code_not_in_map"


def test_prepared_fits_match_plain_fits():
    """The decoder's cached fits (prepared source, affine design) equal the plain ones."""
    from signpose.frontend.homography import (
        affine_design,
        disc_ellipse,
        ellipse_from_conic,
        fit_affine,
        fit_homography,
        prepare_source,
    )

    rng = np.random.default_rng(11)
    src = rng.uniform(-0.4, 0.4, (6, 2))
    h_true = np.array([[80.0, 12.0, 50.0], [-9.0, -75.0, 40.0], [0.3, -0.2, 1.0]])
    dst = cv2.perspectiveTransform(src.reshape(-1, 1, 2), h_true).reshape(-1, 2)
    dst += rng.normal(0, 0.05, dst.shape)
    for n in (4, 5, 6):
        plain = fit_homography(src[:n], dst[:n])
        fast = fit_homography(src[:n], dst[:n], prepare_source(src[:n]))
        np.testing.assert_allclose(fast, plain, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(
        fit_affine(src[:3], dst[:3], affine_design(src[:3])), fit_affine(src[:3], dst[:3])
    )
    # The disc ellipse in plain floats equals the matrix form of its conic.
    _, hinv = cv2.invert(h_true)
    conic = hinv.T @ np.diag([1.0, 1.0, -0.25]) @ hinv
    np.testing.assert_allclose(
        np.concatenate([np.ravel(v) for v in disc_ellipse(h_true, 1.0)]),
        np.concatenate([np.ravel(v) for v in ellipse_from_conic(conic)]),
        rtol=1e-9,
    )
