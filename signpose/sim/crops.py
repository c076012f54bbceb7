"""Synthetic crops of one sign, for decoder evaluation and detector training.

A crop shows one sign (``frontend.sign``) seen through a pinhole camera, on a
procedural background, with the disturbances of the paper's Table 3 (motion
blur, dirt, a power line across the sign, small size, oblique view, complex
surroundings). Everything is drawn from the ``numpy.random.Generator`` passed
in, so a crop is reproducible from its seed.

Geometry. The sign frame is the one of ``frontend.sign`` (x right, y up,
z out of the face). The camera (OpenCV axes: x right, y down, z forward)
looks at the sign centre along its optical axis from a distance chosen so
that the disc, seen face-on, is ``sign_px`` pixels across:

    cam_R_sign = R(tilt axis, tilt) @ diag(1, -1, -1) @ Rz(rotation)
    crop_H_sign = K @ [r1 r2 t],  t = (0, 0, focal_px * diameter / sign_px)

``rotation_deg`` turns the face in its own plane, counter-clockwise as the
viewer sees it; ``tilt_deg`` is the angle between the sign's normal and the
line of sight, about an axis in the image plane at ``tilt_axis_deg`` from the
image u axis (toward +v). The crop's principal point sits near the crop
centre (a random sub-pixel offset, so keypoints do not always fall on pixel
centres). Pixel centres are at integers (OpenCV convention).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from signpose.frontend.homography import Ellipse, apply_homography, disc_ellipse
from signpose.frontend.sign import fill_polygon_aa, sign_keypoints, sign_shape, validate_code
from signpose.sim.crop_occluders import (
    Band,
    CropOccluder,
    bar,
    coverage,
    draw_band,
    line_through,
    part_polygons_px,
    place,
)
from signpose.sim.photos import available_photos, load_photo

BACKGROUNDS: tuple[str, ...] = ("plain", "sky", "lattice", "lines", "ground", "clutter")
# A real photograph (``signpose.sim.photos``); "clutter" when scikit-image is missing.
PHOTO_BACKGROUND = "photo"
PHOTO_FALLBACK = "clutter"

# One name per real-pylon condition, for evaluations that report per condition;
# ``crop_condition`` gives the ``render_crop`` options of each.
CROP_CONDITIONS: tuple[str, ...] = (
    "clean",
    "member",
    "conductor",
    "insulator",
    "photo",
    "jpeg",
    "faded",
    "dirty",
    "glare",
    "vibration",
    "exposure",
)

# Gray levels of the printed face before exposure (contrast/brightness).
BLACK_LEVEL = 28.0
WHITE_LEVEL = 232.0
DEFAULT_FOCAL_PX = 800.0


@dataclass(frozen=True)
class SynthCrop:
    """One rendered crop and its ground truth.

    Attributes:
        image: (H, W) uint8 gray crop.
        code: the sign's code, "0000".."1111".
        keypoints_px: keypoint name -> (u, v) true projection in crop pixels of
            each keypoint ``frontend.sign.sign_keypoints`` defines for this
            code (``center``, ``direction``, white ``slotK``).
        ellipse: the disc's exact image ((cx, cy), (major, minor), angle_deg):
            centre [px], full axis lengths [px], angle of the major axis from
            the u axis toward +v [deg] (cv2.RotatedRect convention).
        diameter_px: the disc diameter seen face-on at the sign's depth [px].
        crop_H_sign: (3, 3) homography from sign-plane metres (x, y, 1) to crop
            pixels (u, v, 1); the sign's diameter is ``diameter_m``.
        diameter_m: disc diameter used for the geometry [m].
        conditions: the rendering parameters (for tables and debugging).
        covered_slots: coded slots (1..4, white or black) whose area the
            occluders cover by >= ``signpose.io.boxes.COVERED_FRACTION``.
        part_cover: part name (``center``, ``direction``, ``slot1``..``slot4``)
            -> covered share of its area (0 for every part without occluders).
        occluders: kinds of the occluders drawn (``crop_occluders.OCCLUDER_KINDS``).
    """

    image: np.ndarray
    code: str
    keypoints_px: dict[str, tuple[float, float]]
    ellipse: Ellipse
    diameter_px: float
    crop_H_sign: np.ndarray
    diameter_m: float = 1.0
    conditions: dict = field(default_factory=dict)
    covered_slots: tuple[int, ...] = ()
    part_cover: dict[str, float] = field(default_factory=dict)
    occluders: tuple[str, ...] = ()


def _rodrigues(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    r, _ = cv2.Rodrigues(np.asarray(axis, float).reshape(3, 1) * angle_rad)
    return r


def crop_homography(
    sign_px: float,
    rotation_deg: float,
    tilt_deg: float,
    tilt_axis_deg: float,
    principal_px: tuple[float, float],
    focal_px: float = DEFAULT_FOCAL_PX,
    diameter_m: float = 1.0,
) -> np.ndarray:
    """(3, 3) homography from sign-plane metres to crop pixels (see module doc)."""
    rot = math.radians(rotation_deg)
    c, s = math.cos(rot), math.sin(rot)
    rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    phi = math.radians(tilt_axis_deg)
    r_tilt = _rodrigues(np.array([math.cos(phi), math.sin(phi), 0.0]), math.radians(tilt_deg))
    cam_R_sign = r_tilt @ np.diag([1.0, -1.0, -1.0]) @ rz
    cam_t_sign = np.array([0.0, 0.0, focal_px * diameter_m / sign_px])
    k = np.array(
        [[focal_px, 0.0, principal_px[0]], [0.0, focal_px, principal_px[1]], [0.0, 0.0, 1.0]]
    )
    h = k @ np.column_stack([cam_R_sign[:, 0], cam_R_sign[:, 1], cam_t_sign])
    return h / h[2, 2]


# ---------------------------------------------------------------------------
# Backgrounds


def _smooth_noise(rng: np.random.Generator, h: int, w: int, cells: int) -> np.ndarray:
    """Zero-mean, unit-ish smooth noise of (h, w), ``cells`` features across."""
    gh, gw = max(2, cells * h // max(h, w) + 2), max(2, cells * w // max(h, w) + 2)
    grid = rng.standard_normal((gh, gw)).astype(np.float32)
    return cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC).astype(np.float64)


def _gradient(rng: np.random.Generator, h: int, w: int, lo: float, hi: float) -> np.ndarray:
    a = rng.uniform(0, 2 * math.pi)
    yy, xx = np.mgrid[0:h, 0:w]
    t = (math.cos(a) * xx + math.sin(a) * yy) / max(h, w)
    t = t - t.min()
    t = t / max(t.max(), 1e-9)
    return lo + (hi - lo) * t


def _background_float(rng: np.random.Generator, h: int, w: int, kind: str) -> np.ndarray:
    if kind == "plain":
        return np.full((h, w), rng.uniform(80, 210)) + _gradient(rng, h, w, -10, 10)
    if kind == "sky":
        img = _gradient(rng, h, w, rng.uniform(150, 200), rng.uniform(200, 245))
        return img + rng.uniform(5, 20) * _smooth_noise(rng, h, w, 3)
    if kind == "lattice":
        img = _background_float(rng, h, w, "sky")
        s = max(h, w)
        steel = rng.uniform(25, 90)
        base = rng.uniform(0, math.pi)
        for family in range(3):
            angle = base + family * rng.uniform(0.5, 1.3)
            width = rng.uniform(0.03, 0.09) * s
            for _ in range(rng.integers(1, 3)):
                bar(img, *line_through(rng, h, w, angle=angle), width, steel)
        return img
    if kind == "lines":
        img = _background_float(rng, h, w, "sky")
        angle = rng.uniform(0, math.pi)
        normal = np.array([-math.sin(angle), math.cos(angle)])
        centre = np.array([w / 2, h / 2])
        for _ in range(rng.integers(2, 6)):
            offset = rng.uniform(-0.6, 0.6) * max(h, w)
            p = centre + offset * normal
            bar(
                img,
                *line_through(rng, h, w, point=p, angle=angle + rng.normal(0, 0.03)),
                rng.uniform(0.8, 3.0),
                rng.uniform(30, 90),
            )
        return img
    if kind == "ground":
        img = np.full((h, w), rng.uniform(60, 140))
        img += rng.uniform(10, 30) * _smooth_noise(rng, h, w, 4)
        img += rng.uniform(5, 20) * _smooth_noise(rng, h, w, 16)
        img += rng.uniform(2, 10) * rng.standard_normal((h, w))
        return img
    if kind == "clutter":
        img = _gradient(rng, h, w, rng.uniform(40, 140), rng.uniform(120, 240))
        s = max(h, w)
        for _ in range(rng.integers(4, 12)):
            value = rng.uniform(0, 255)
            cx, cy = rng.uniform(0, w), rng.uniform(0, h)
            if rng.random() < 0.5:
                a, b = rng.uniform(0.03, 0.3, size=2) * s
                t = rng.uniform(0, math.pi)
                pts = np.array([[-a, -b], [a, -b], [a, b], [-a, b]])
                c, sn = math.cos(t), math.sin(t)
                poly = pts @ np.array([[c, sn], [-sn, c]]) + [cx, cy]
            else:
                a, b = rng.uniform(0.03, 0.2, size=2) * s
                t = np.linspace(0, 2 * math.pi, 48, endpoint=False)
                poly = np.stack([cx + a * np.cos(t), cy + b * np.sin(t)], axis=1)
            fill_polygon_aa(img, poly, value, supersample=2)
        return img
    raise ValueError(f"unknown background {kind!r}: use one of {', '.join(BACKGROUNDS)}")


def render_background(rng: np.random.Generator, h: int, w: int, kind: str) -> np.ndarray:
    """(h, w) uint8 gray procedural background ``kind`` (one of BACKGROUNDS), no sign."""
    img = _background_float(rng, h, w, kind)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


# ---------------------------------------------------------------------------
# Disturbances


def _motion_kernel(length_px: float, angle_rad: float) -> np.ndarray:
    """Normalised linear motion-blur kernel of ``length_px`` along ``angle_rad``."""
    half = int(math.ceil(length_px / 2)) + 1
    size = 2 * half + 1
    k = np.zeros((size, size))
    d = np.array([math.cos(angle_rad), math.sin(angle_rad)]) * length_px / 2
    c = np.array([half, half], float)
    bar(k, c - d, c + d, 1.0, 1.0)
    return k / k.sum()


def _add_dirt(rng: np.random.Generator, img: np.ndarray, centre, radius_px: float) -> None:
    """Semi-transparent smudges and specks over the face (in place on a float canvas)."""
    for _ in range(rng.integers(3, 8)):
        layer = img.copy()
        r = radius_px * math.sqrt(rng.uniform(0, 1))
        a = rng.uniform(0, 2 * math.pi)
        cx, cy = centre[0] + r * math.cos(a), centre[1] + r * math.sin(a)
        ax, ay = rng.uniform(0.04, 0.14, size=2) * radius_px * 2
        t = np.linspace(0, 2 * math.pi, 32, endpoint=False)
        wobble = 1 + 0.25 * np.sin(3 * t + rng.uniform(0, 6))
        rot = rng.uniform(0, math.pi)
        x, y = ax * np.cos(t) * wobble, ay * np.sin(t) * wobble
        poly = np.stack(
            [
                cx + x * math.cos(rot) - y * math.sin(rot),
                cy + x * math.sin(rot) + y * math.cos(rot),
            ],
            axis=1,
        )
        fill_polygon_aa(layer, poly, rng.uniform(70, 160), supersample=2)
        alpha = rng.uniform(0.25, 0.6)
        img *= 1 - alpha
        img += alpha * layer
    h, w = img.shape
    n = int(rng.integers(5, 20))
    us = centre[0] + rng.uniform(-1, 1, n) * radius_px
    vs = centre[1] + rng.uniform(-1, 1, n) * radius_px
    for u, v in zip(us, vs, strict=True):
        iu, iv = int(round(u)), int(round(v))
        if 0 <= iu < w and 0 <= iv < h:
            img[iv, iu] = 0.5 * img[iv, iu] + 0.5 * rng.uniform(60, 180)


# ---------------------------------------------------------------------------
# The crop


def _draw_face(
    img: np.ndarray,
    code: str,
    crop_H_sign: np.ndarray,
    diameter_m: float,
    supersample: int,
    fade: float = 0.0,
) -> None:
    """Paint the black disc and the white parts of ``code`` into float ``img`` (in place).

    ``fade`` > 0 pulls both paints toward their mean grey (weathered paint).
    """
    black, white = BLACK_LEVEL, WHITE_LEVEL
    if fade > 0:
        grey = 0.5 * (black + white)
        black, white = black + fade * (grey - black), white + fade * (grey - white)
    shape = sign_shape(code, diameter_m)
    fill_polygon_aa(img, apply_homography(crop_H_sign, shape.disc), black, supersample)
    for corners in shape.white_parts.values():
        fill_polygon_aa(img, apply_homography(crop_H_sign, corners), white, supersample)


def _add_glare(
    rng: np.random.Generator,
    img: np.ndarray,
    crop_H_sign: np.ndarray,
    diameter_m: float,
    sign_px: float,
    peak_dn: float,
) -> None:
    """Add a Gaussian specular highlight of ``peak_dn`` on the face (in place)."""
    centre = apply_homography(crop_H_sign, np.zeros((1, 2)))[0]
    centre = centre + rng.uniform(-0.3, 0.3, size=2) * sign_px
    sigma = rng.uniform(0.1, 0.25) * sign_px
    disc = np.zeros_like(img)
    fill_polygon_aa(disc, apply_homography(crop_H_sign, sign_shape("0000", diameter_m).disc), 1.0)
    v, u = np.mgrid[0 : img.shape[0], 0 : img.shape[1]]
    r2 = ((u - centre[0]) ** 2 + (v - centre[1]) ** 2) / sigma**2
    img += disc * peak_dn * np.exp(-0.5 * r2)


def _photo_background(rng: np.random.Generator, h: int, w: int) -> tuple[np.ndarray, str] | None:
    """(h, w) float grey cut of a random photograph and ``photo:<name>``, None without any."""
    names = available_photos()
    if not names:
        return None
    name = names[int(rng.integers(len(names)))]
    gray = cv2.cvtColor(load_photo(name), cv2.COLOR_BGR2GRAY)
    side = int(rng.uniform(0.25, 1.0) * min(gray.shape))
    y = int(rng.integers(0, gray.shape[0] - side + 1))
    x = int(rng.integers(0, gray.shape[1] - side + 1))
    cut = cv2.resize(gray[y : y + side, x : x + side], (w, h), interpolation=cv2.INTER_AREA)
    return cut.astype(np.float64), f"photo:{name}"


def _background(rng: np.random.Generator, side: int, kind: str) -> tuple[np.ndarray, str]:
    """The crop's float background and what it shows (``kind`` or ``photo:<name>``)."""
    if kind == PHOTO_BACKGROUND:
        photo = _photo_background(rng, side, side)
        if photo is not None:
            return photo
        kind = PHOTO_FALLBACK
    return _background_float(rng, side, side, kind), kind


def _occluders(settings: CropSettings) -> tuple[CropOccluder, ...]:
    """Every occluder the settings ask for, in drawing order (power line first)."""
    out = [CropOccluder("conductor")] if settings.power_line else []
    out += list(settings.occluders)
    if settings.member:
        out.append(CropOccluder("member"))
    if settings.insulator:
        out.append(CropOccluder("insulator"))
    return tuple(out)


def _jpeg(image: np.ndarray, quality: int | None) -> np.ndarray:
    if quality is None:
        return image
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE) if ok else image


@dataclass(frozen=True)
class _Exposure:
    """How the drawn crop becomes an image: blur, optics, exposure, noise (``render_crop``)."""

    blur_px: float
    blur_angle: float
    psf_sigma_px: float
    contrast: float
    brightness: float
    noise_sigma: float


def _expose(rng: np.random.Generator, img: np.ndarray, e: _Exposure) -> np.ndarray:
    """Motion blur, optics blur, contrast/brightness and noise; (H, W) uint8."""
    if e.blur_px > 0:
        kernel = _motion_kernel(e.blur_px, e.blur_angle)
        img = cv2.filter2D(img, -1, kernel, borderType=cv2.BORDER_REFLECT)
    if e.psf_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), e.psf_sigma_px, borderType=cv2.BORDER_REFLECT)
    img = (img - 128.0) * e.contrast + 128.0 + e.brightness
    if e.noise_sigma > 0:
        img = img + rng.normal(0.0, e.noise_sigma, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class CropSettings:
    """How ``render_crop`` draws a sign (every field is also a keyword of ``render_crop``).

    Attributes:
        sign_px: disc diameter seen face-on [px].
        out_px: crop side [px]; default ``ceil(sign_px * (1 + 2 * margin))``.
        rotation_deg: in-plane turn of the face, counter-clockwise as seen [deg].
        tilt_deg: angle between the sign's normal and the line of sight [deg].
        tilt_axis_deg: image direction of the tilt axis, from u toward +v [deg].
        blur_px: length of a linear motion blur at a random direction [px].
        noise_sigma: standard deviation of additive Gaussian noise [gray levels].
        dirt: draw smudges and specks on the face.
        power_line: draw a dark conductor across the sign.
        background: one of BACKGROUNDS.
        contrast, brightness: exposure, ``(I - 128) * contrast + 128 + brightness``.
        margin: space around the disc on each side, as a fraction of sign_px.
        focal_px: focal length of the pinhole camera [px] (sets the perspective).
        psf_sigma_px: Gaussian optics blur always applied [px].
        offset_px: shift of the sign centre from the crop centre [px].
        supersample: sub-samples per pixel side for the polygon fill.
        occluders: bands in front of the sign (``crop_occluders.CropOccluder``),
            drawn after the power line.
        member: add one lattice member at a random place and angle.
        insulator: add one insulator string at a random place and angle.
        fade: pull the black and white paint toward their mean grey by this share.
        glare_dn: peak of a specular highlight on the face [grey levels], 0 = none.
        jpeg_quality: JPEG round trip of the crop (1..100), None = none.

    ``background`` may also be ``PHOTO_BACKGROUND`` ("photo"): a cut of a real
    photograph, or ``PHOTO_FALLBACK`` when scikit-image is not installed
    (``conditions["background"]`` says which).
    """

    sign_px: float = 48.0
    out_px: int | None = None
    rotation_deg: float = 0.0
    tilt_deg: float = 0.0
    tilt_axis_deg: float = 0.0
    blur_px: float = 0.0
    noise_sigma: float = 0.0
    dirt: bool = False
    power_line: bool = False
    background: str = "plain"
    contrast: float = 1.0
    brightness: float = 0.0
    margin: float = 0.25
    focal_px: float = DEFAULT_FOCAL_PX
    psf_sigma_px: float = 0.4
    offset_px: tuple[float, float] = (0.0, 0.0)
    supersample: int = 8
    occluders: tuple[CropOccluder, ...] = ()
    member: bool = False
    insulator: bool = False
    fade: float = 0.0
    glare_dn: float = 0.0
    jpeg_quality: int | None = None

    def side_px(self) -> int:
        if self.out_px is not None:
            return int(self.out_px)
        return int(math.ceil(self.sign_px * (1 + 2 * self.margin)))

    def conditions(self, blur_angle: float, bands: tuple[Band, ...], background: str) -> dict:
        """The rendering parameters as ``SynthCrop.conditions`` reports them.

        ``power_line`` keeps its old form ({angle_deg, width_px} or None);
        ``occluders`` lists every band drawn (kind, angle_deg, width_px, value).
        """
        line = None
        if self.power_line:
            line = {"angle_deg": math.degrees(bands[0].angle_rad), "width_px": bands[0].width_px}
        return {
            "sign_px": float(self.sign_px),
            "out_px": self.side_px(),
            "rotation_deg": float(self.rotation_deg),
            "tilt_deg": float(self.tilt_deg),
            "tilt_axis_deg": float(self.tilt_axis_deg),
            "blur_px": float(self.blur_px),
            "blur_angle_deg": math.degrees(blur_angle) if self.blur_px > 0 else None,
            "noise_sigma": float(self.noise_sigma),
            "dirt": bool(self.dirt),
            "power_line": line,
            "occluders": [b.to_json() for b in bands],
            "background": background,
            "fade": float(self.fade),
            "glare_dn": float(self.glare_dn),
            "jpeg_quality": self.jpeg_quality,
            "contrast": float(self.contrast),
            "brightness": float(self.brightness),
            "focal_px": float(self.focal_px),
            "psf_sigma_px": float(self.psf_sigma_px),
        }


def render_crop(
    code: str, rng: np.random.Generator, settings: CropSettings | None = None, **options
) -> SynthCrop:
    """Render sign ``code`` in a square gray crop (a detector's region of interest).

    Args:
        code: sign code, "0000".."1111".
        rng: the only source of randomness (background, jitter, disturbances).
        settings: how to draw it (default ``CropSettings()``).
        **options: fields of ``CropSettings`` that override ``settings``, e.g.
            ``render_crop("0101", rng, sign_px=40, tilt_deg=30)``.

    Returns:
        The crop with its exact keypoints and disc ellipse.
    """
    validate_code(code)
    s = replace(settings or CropSettings(), **options)
    if s.background not in (*BACKGROUNDS, PHOTO_BACKGROUND):
        raise ValueError(
            f"unknown background {s.background!r}: use one of "
            f"{', '.join((*BACKGROUNDS, PHOTO_BACKGROUND))}"
        )
    side = s.side_px()
    diameter_m = 1.0
    jitter = rng.uniform(-0.5, 0.5, size=2)
    principal = (
        (side - 1) / 2.0 + s.offset_px[0] + jitter[0],
        (side - 1) / 2.0 + s.offset_px[1] + jitter[1],
    )
    crop_H_sign = crop_homography(
        s.sign_px, s.rotation_deg, s.tilt_deg, s.tilt_axis_deg, principal, s.focal_px, diameter_m
    )
    img, background = _background(rng, side, s.background)
    _draw_face(img, code, crop_H_sign, diameter_m, s.supersample, s.fade)
    if s.glare_dn > 0:
        _add_glare(rng, img, crop_H_sign, diameter_m, s.sign_px, s.glare_dn)
    ellipse = disc_ellipse(crop_H_sign, diameter_m)
    if s.dirt:
        _add_dirt(rng, img, ellipse[0], ellipse[1][0] / 2)
    parts_px = part_polygons_px(crop_H_sign, diameter_m)
    bands = tuple(place(o, rng, side, ellipse[0], parts_px, s.sign_px) for o in _occluders(s))
    for band in bands:
        draw_band(img, band)
    part_cover, covered_slots = coverage(bands, parts_px, img.shape)
    blur_angle = rng.uniform(0, math.pi)
    exposure = _Exposure(
        s.blur_px, blur_angle, s.psf_sigma_px, s.contrast, s.brightness, s.noise_sigma
    )
    image = _jpeg(_expose(rng, img, exposure), s.jpeg_quality)
    kps = sign_keypoints(code, diameter_m)
    names = list(kps)
    uv = apply_homography(crop_H_sign, np.array([kps[n][:2] for n in names]))
    return SynthCrop(
        image=image,
        code=code,
        keypoints_px={n: (float(p[0]), float(p[1])) for n, p in zip(names, uv, strict=True)},
        ellipse=ellipse,
        diameter_px=float(s.sign_px),
        crop_H_sign=crop_H_sign,
        diameter_m=diameter_m,
        conditions=s.conditions(blur_angle, bands, background),
        covered_slots=covered_slots,
        part_cover=part_cover,
        occluders=tuple(b.kind for b in bands),
    )


def crop_condition(name: str, rng: np.random.Generator) -> dict:
    """``render_crop`` options for condition ``name`` of ``CROP_CONDITIONS``, drawn from ``rng``.

    ``member``, ``conductor`` and ``insulator`` put one occluder of that kind in
    front of the sign (see ``SynthCrop.covered_slots`` for what it covers);
    ``photo`` a photograph behind it; ``jpeg`` a round trip at quality 70-90;
    ``faded`` paint faded by 0.15-0.5; ``dirty`` stains; ``glare`` a highlight
    of 40-120 grey levels; ``vibration`` a 3-12 px motion blur; ``exposure``
    contrast 0.5-0.8 and brightness -60..60.
    """
    if name not in CROP_CONDITIONS:
        raise ValueError(f"unknown condition {name!r}: use one of {', '.join(CROP_CONDITIONS)}")
    draws = {
        "clean": lambda: {},
        "member": lambda: {"member": True},
        "conductor": lambda: {"power_line": True},
        "insulator": lambda: {"insulator": True},
        "photo": lambda: {"background": PHOTO_BACKGROUND},
        "jpeg": lambda: {"jpeg_quality": int(rng.integers(70, 91))},
        "faded": lambda: {"fade": float(rng.uniform(0.15, 0.5))},
        "dirty": lambda: {"dirt": True},
        "glare": lambda: {"glare_dn": float(rng.uniform(40.0, 120.0))},
        "vibration": lambda: {"blur_px": float(rng.uniform(3.0, 12.0))},
        "exposure": lambda: {
            "contrast": float(rng.uniform(0.5, 0.8)),
            "brightness": float(rng.uniform(-60.0, 60.0)),
        },
    }
    return draws[name]()
