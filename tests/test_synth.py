"""frontend.synth: deterministic crops whose ground truth matches the drawing."""

import numpy as np
import pytest
from signpose.frontend.homography import apply_homography, fit_homography
from signpose.frontend.sign import ALL_CODES, fill_polygon_aa, sign_keypoints

from signpose.core.errors import InputError
from signpose.sim import crops, photos
from signpose.sim.crop_occluders import CropOccluder, part_polygons_px
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


def _mean_in(image: np.ndarray, polygon_px: np.ndarray) -> float:
    mask = np.zeros(image.shape, float)
    fill_polygon_aa(mask, polygon_px, 1.0, 4)
    return float((mask * image).sum() / mask.sum())


@pytest.mark.parametrize("slot", [1, 2, 3, 4])
def test_a_member_over_slot_k_marks_it_covered_and_darkens_it(slot):
    kw = dict(sign_px=80, rotation_deg=17, tilt_deg=25, psf_sigma_px=0.0)
    member = CropOccluder("member", through=f"slot{slot}", width_px=14.0, value=60.0)
    clean = render_crop("1111", np.random.default_rng(3), **kw)
    crossed = render_crop("1111", np.random.default_rng(3), occluders=(member,), **kw)
    assert clean.covered_slots == () and clean.occluders == ()
    assert slot in crossed.covered_slots
    assert crossed.occluders == ("member",)
    assert crossed.part_cover[f"slot{slot}"] > 0.5
    for k in range(1, 5):
        assert (k in crossed.covered_slots) == (crossed.part_cover[f"slot{k}"] >= 0.2)
    parts = part_polygons_px(crossed.crop_H_sign, crossed.diameter_m)
    for name, poly in parts.items():
        before = _mean_in(clean.image.astype(float), poly)
        after = _mean_in(crossed.image.astype(float), poly)
        # The grey level drops by the covered share of (white - member grey).
        expected = crossed.part_cover[name] * (before - 60.0)
        assert before - after == pytest.approx(expected, abs=12.0), name
    assert crossed.conditions["occluders"][0]["kind"] == "member"


def test_a_black_slot_counts_as_covered_too():
    member = CropOccluder("member", through="slot3", width_px=12.0)
    crop = render_crop("0000", np.random.default_rng(0), sign_px=60, occluders=(member,))
    assert 3 in crop.covered_slots


def test_random_occluders_and_conditions_are_recorded():
    crop = render_crop(
        "1010",
        np.random.default_rng(4),
        sign_px=60,
        power_line=True,
        member=True,
        insulator=True,
        fade=0.4,
        glare_dn=100.0,
        jpeg_quality=75,
    )
    assert crop.occluders == ("conductor", "member", "insulator")
    assert [o["kind"] for o in crop.conditions["occluders"]] == list(crop.occluders)
    assert crop.conditions["power_line"]["width_px"] == crop.conditions["occluders"][0]["width_px"]
    assert crop.conditions["fade"] == 0.4 and crop.conditions["jpeg_quality"] == 75
    assert set(crop.part_cover) == {"center", "direction", "slot1", "slot2", "slot3", "slot4"}
    with pytest.raises(ValueError, match="occluder"):
        render_crop("1010", np.random.default_rng(0), occluders=(CropOccluder("bird"),))


def test_fading_lowers_and_glare_raises_the_face():
    kw = dict(sign_px=70, psf_sigma_px=0.0)
    fresh = render_crop("1111", np.random.default_rng(5), **kw)
    faded = render_crop("1111", np.random.default_rng(5), fade=0.5, **kw)
    glared = render_crop("1111", np.random.default_rng(5), glare_dn=150.0, **kw)
    parts = part_polygons_px(fresh.crop_H_sign, fresh.diameter_m)
    white = _mean_in(fresh.image.astype(float), parts["slot1"])
    assert _mean_in(faded.image.astype(float), parts["slot1"]) < white - 30
    disc = np.zeros(fresh.image.shape, bool)
    (cx, cy), (a, _), _ = fresh.ellipse
    yy, xx = np.mgrid[: disc.shape[0], : disc.shape[1]]
    disc = np.hypot(xx - cx, yy - cy) < 0.45 * a
    assert glared.image[disc].astype(float).sum() > fresh.image[disc].astype(float).sum()


def test_photo_background_falls_back_without_photographs(monkeypatch):
    crop = render_crop("0101", np.random.default_rng(0), sign_px=40, background="photo")
    if photos.available_photos():
        assert crop.conditions["background"].startswith("photo:")
    monkeypatch.setattr(crops, "available_photos", lambda: ())
    crop = render_crop("0101", np.random.default_rng(0), sign_px=40, background="photo")
    assert crop.conditions["background"] == "clutter"


@pytest.mark.parametrize("condition", crops.CROP_CONDITIONS)
def test_every_crop_condition_renders_and_occluders_are_reported(condition):
    rng = np.random.default_rng(11)
    crop = render_crop("1101", rng, sign_px=50, **crops.crop_condition(condition, rng))
    assert crop.image.shape == (75, 75)  # 50 px and a quarter of it on each side
    kinds = {"member": ("member",), "conductor": ("conductor",), "insulator": ("insulator",)}
    assert crop.occluders == kinds.get(condition, ())
    with pytest.raises(ValueError, match="condition"):
        crops.crop_condition("fog", rng)
