"""frontend.synth: deterministic crops whose ground truth matches the drawing."""

import numpy as np
import pytest
from signpose.frontend.homography import apply_homography, fit_homography
from signpose.frontend.sign import ALL_CODES, sign_keypoints

from signpose.core.errors import InputError
from signpose.sim.crops import BACKGROUNDS, render_background, render_crop


def test_same_seed_same_crop():
    kw = dict(sign_px=50, rotation_deg=20, tilt_deg=35, background="clutter", noise_sigma=3)
    a = render_crop("0110", np.random.default_rng(7), **kw)
    b = render_crop("0110", np.random.default_rng(7), **kw)
    c = render_crop("0110", np.random.default_rng(8), **kw)
    assert np.array_equal(a.image, b.image)
    assert not np.array_equal(a.image, c.image)
    assert a.keypoints_px == b.keypoints_px


@pytest.mark.parametrize("code", ["0000", "1011", "1111"])
def test_keypoints_are_projections_and_bright(code):
    crop = render_crop(code, np.random.default_rng(1), sign_px=80, rotation_deg=33, tilt_deg=40)
    assert crop.image.dtype == np.uint8 and crop.image.shape == (120, 120)
    kps = sign_keypoints(code, crop.diameter_m)
    assert set(crop.keypoints_px) == set(kps)
    for name, p in kps.items():
        u, v = apply_homography(crop.crop_H_sign, p[None, :2])[0]
        assert crop.keypoints_px[name] == pytest.approx((u, v), abs=1e-9)
        # Every keypoint sits on a white rectangle of the black disc.
        assert crop.image[int(round(v)), int(round(u))] > 180


def test_face_on_sign_fills_sign_px_and_rotation_is_counter_clockwise():
    crop = render_crop("0000", np.random.default_rng(0), sign_px=60, rotation_deg=90)
    (cx, cy), (major, minor), _ = crop.ellipse
    assert major == pytest.approx(60, abs=1e-6) and minor == pytest.approx(60, abs=1e-6)
    du = crop.keypoints_px["direction"][0] - crop.keypoints_px["center"][0]
    dv = crop.keypoints_px["direction"][1] - crop.keypoints_px["center"][1]
    # Turned 90 degrees counter-clockwise on screen, "up" points left.
    assert du < -10 and abs(dv) < 1e-6


def test_tilt_foreshortens_by_cosine():
    crop = render_crop("0000", np.random.default_rng(0), sign_px=60, tilt_deg=60)
    (_, _), (major, minor), _ = crop.ellipse
    assert minor / major == pytest.approx(0.5, abs=0.02)


def test_homography_recovers_synth_geometry():
    crop = render_crop("1111", np.random.default_rng(2), sign_px=90, tilt_deg=50, rotation_deg=10)
    kps = sign_keypoints("1111", crop.diameter_m)
    src = np.array([p[:2] for p in kps.values()])
    dst = np.array([crop.keypoints_px[n] for n in kps])
    h = fit_homography(src, dst)
    assert np.allclose(h, crop.crop_H_sign / crop.crop_H_sign[2, 2], atol=1e-6)


@pytest.mark.parametrize("kind", BACKGROUNDS)
def test_backgrounds(kind):
    img = render_background(np.random.default_rng(3), 40, 56, kind)
    assert img.shape == (40, 56) and img.dtype == np.uint8
    assert img.std() > 0.5 or kind == "plain"


def test_unknown_inputs_raise():
    with pytest.raises(ValueError):
        render_crop("0101", np.random.default_rng(0), sign_px=30, background="moon")
    with pytest.raises(InputError):  # from the sign module
        render_crop("0102", np.random.default_rng(0), sign_px=30)
    assert len(ALL_CODES) == 16
