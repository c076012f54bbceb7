#!/usr/bin/env python
"""A second, small scene renderer for the decoder that shares no drawing code with signpose.sim.

Why: ``signpose.sim`` renders the crops the decoder was tuned on; grading the
decoder only on them is the simulator grading itself. This renderer draws a
crop its own way:

* the face is the PNG that ``signpose sign`` writes (``frontend.sign.render_sign_png``),
  warped with ``cv2.warpPerspective`` at 4x resolution and area-averaged down;
* backgrounds are real photographs (scikit-image's data images, BSD licence),
  random crops at random scale;
* occluders are 3D cylinders (pylon members, conductors) placed between the
  camera and the sign, projected through the same pinhole; bars behind the
  sign cross the background only. Each part's covered fraction is measured on
  the rendered occluder mask, so the truth says which slots are covered;
* photometry: printed black/white levels, faded faces, gain and offset,
  specular glare, optics blur, motion blur bursts, noise, JPEG 70-90.

Geometry. Camera: OpenCV axes (x right, y down, z forward), pinhole ``K``,
principal point near the crop centre. Sign frame as ``frontend.sign`` (x right,
y up, z out of the face); ``cam_R_sign = R_tilt @ diag(1, -1, -1) @ Rz(rot)``,
the sign centre at ``(0, 0, Z)`` with ``Z = f D / sign_px``. Pixel centres at
integers. Everything random comes from the generator passed in.

    .venv/bin/python scripts/independent_scene.py OUT.png [--code 1011] [--seed 1]
"""

from __future__ import annotations

import argparse
import functools
import math
import sys
from dataclasses import dataclass, field

import cv2
import numpy as np
from signpose.frontend.sign import (
    PAPER_CODES,
    render_sign_png,
    sign_keypoints,
    sign_shape,
    slot_angle_rad,
)

DIAMETER_M = 0.8
SUPERSAMPLE = 4
PHOTOS = ("camera", "astronaut", "coffee", "chelsea", "rocket", "grass", "gravel", "brick", "coins")
PART_NAMES = ("center", "direction", "slot1", "slot2", "slot3", "slot4")
# A coded slot counts as covered when an occluder hides this much of it.
COVERED_FRACTION = 0.25


@dataclass(frozen=True)
class SceneSettings:
    """What one crop shows (all lengths in pixels unless named otherwise)."""

    sign_px: float
    rotation_deg: float = 0.0
    tilt_deg: float = 0.0
    tilt_axis_deg: float = 0.0
    focal_px: float = 1000.0
    photo: str = "camera"
    black_level: float = 30.0
    white_level: float = 225.0
    gain: float = 1.0
    offset: float = 0.0
    glare: float = 0.0  # peak added gray level of a specular spot on the face
    psf_sigma_px: float = 0.5
    blur_px: float = 0.0  # motion blur length
    noise_sigma: float = 2.0
    jpeg_quality: int = 85
    members_front: int = 0  # wide bars in front of the sign
    bar_over_slot: int = 0  # 1..4: a member in front laid across that coded slot
    conductors_front: int = 0  # thin bars in front of the sign
    bars_behind: int = 0
    dirt: bool = False


@dataclass(frozen=True)
class SceneCrop:
    """One rendered crop and its truth.

    Attributes:
        image: (S, S) uint8 gray crop.
        code: the sign's code.
        keypoints_px: name -> (u, v) true image of each keypoint (centre,
            direction, white slots) [px].
        covered: part name ("center", "direction", "slot1".."slot4", white or
            black) -> fraction of it hidden by occluders in front.
        settings: what was drawn.
    """

    image: np.ndarray
    code: str
    keypoints_px: dict[str, tuple[float, float]]
    covered: dict[str, float]
    settings: SceneSettings
    bars: list[dict] = field(default_factory=list)

    @property
    def covered_slots(self) -> tuple[int, ...]:
        return tuple(k for k in range(1, 5) if self.covered[f"slot{k}"] >= COVERED_FRACTION)


@functools.cache
def _photo(name: str) -> np.ndarray:
    import skimage.data  # scripts only: the train extra's optional dependency

    img = getattr(skimage.data, name)()
    if img.ndim == 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_RGB2GRAY)
    return img.astype(np.float32)


@functools.cache
def _face(code: str, px: int) -> tuple[np.ndarray, np.ndarray]:
    """The sign PNG (0 black .. 1 white) and its disc's coverage, both (px, px) float32."""
    tex = render_sign_png(code, px).astype(np.float32) / 255.0
    c = (px - 1) / 2.0
    yy, xx = np.mgrid[0:px, 0:px]
    alpha = np.clip(px / 2.0 - np.hypot(xx - c, yy - c) + 0.5, 0.0, 1.0).astype(np.float32)
    return tex, alpha


def _rot(axis: np.ndarray, angle: float) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(axis, float) * angle)[0]


def _camera(s: SceneSettings, side: int, rng: np.random.Generator):
    """K, cam_R_sign and cam_t_sign for the crop."""
    pp = (side - 1) / 2.0 + rng.uniform(-0.5, 0.5, 2) + rng.uniform(-0.04, 0.04, 2) * s.sign_px
    k = np.array([[s.focal_px, 0, pp[0]], [0, s.focal_px, pp[1]], [0, 0, 1.0]])
    a = math.radians(s.tilt_axis_deg)
    r_tilt = _rot([math.cos(a), math.sin(a), 0.0], math.radians(s.tilt_deg))
    r = r_tilt @ np.diag([1.0, -1.0, -1.0]) @ _rot([0, 0, 1], math.radians(s.rotation_deg))
    t = np.array([0.0, 0.0, s.focal_px * DIAMETER_M / s.sign_px])
    return k, r, t


def _project(k, r, t, sign_xyz: np.ndarray) -> np.ndarray:
    cam = sign_xyz @ r.T + t
    uvw = cam @ k.T
    return uvw[:, :2] / uvw[:, 2:]


def _hires(side: int) -> np.ndarray:
    """Low-res pixel -> 4x pixel (pixel centres at integers in both)."""
    s = SUPERSAMPLE
    return np.array([[s, 0, (s - 1) / 2], [0, s, (s - 1) / 2], [0, 0, 1.0]])


def _background(s: SceneSettings, side: int, rng: np.random.Generator) -> np.ndarray:
    photo = _photo(s.photo)
    h, w = photo.shape
    crop = int(min(h, w) * rng.uniform(0.1, 0.6))
    y0, x0 = rng.integers(0, h - crop), rng.integers(0, w - crop)
    patch = photo[y0 : y0 + crop, x0 : x0 + crop]
    n = side * SUPERSAMPLE
    return cv2.resize(patch, (n, n), interpolation=cv2.INTER_LINEAR)


def _bar_polygon(k, p0: np.ndarray, p1: np.ndarray, radius_m: float) -> np.ndarray:
    """(4, 2) image outline [px] of a cylinder from camera points p0 to p1."""
    ends = np.stack([p0, p1])
    uv = (ends @ k.T)[:, :2] / ends[:, 2:]
    d = uv[1] - uv[0]
    n = np.array([-d[1], d[0]]) / max(np.hypot(*d), 1e-9)
    half = k[0, 0] * radius_m / ends[:, 2]
    return np.array(
        [uv[0] + half[0] * n, uv[1] + half[1] * n, uv[1] - half[1] * n, uv[0] - half[0] * n]
    )


def _random_bar(
    rng, k, r, t, width_frac: float, depth_m: float, over_slot: int = 0
) -> tuple[np.ndarray, float]:
    """A long cylinder passing ``depth_m`` in front of (negative: behind) a point of the face.

    ``over_slot`` (1..4): through that coded slot's centre, about along the slot's
    tangential direction (+-10 deg), so that it hides the slot; else anywhere.
    """
    if over_slot:
        theta = slot_angle_rad(over_slot)
        q_sign = 0.3 * DIAMETER_M * np.array([math.cos(theta), math.sin(theta), 0.0])
        a = theta - math.pi / 2 + math.radians(rng.uniform(-10, 10))
        d = r @ np.array([math.cos(a), math.sin(a), 0.0])
    else:
        q_sign = np.array([*rng.uniform(-0.45, 0.45, 2) * DIAMETER_M, 0.0])
        d = rng.normal(size=3)
        d[2] *= 0.3  # mostly across the view
        d /= np.linalg.norm(d)
    q = r @ q_sign + t
    q = q - depth_m * q / np.linalg.norm(q)  # toward the camera along the ray
    z_min = 0.3 * q[2]
    p0, p1 = q - 20 * d, q + 20 * d
    # Keep the segment in front of the camera.
    for i, (a, b) in enumerate(((p0, p1), (p1, p0))):
        if a[2] < z_min:
            f = (z_min - a[2]) / (b[2] - a[2])
            a = a + f * (b - a)
            if i == 0:
                p0 = a
            else:
                p1 = a
    radius = width_frac * DIAMETER_M / 2 * q[2] / t[2]
    return _bar_polygon(k, p0, p1, radius), float(radius)


def _draw_bar(canvas, mask, poly_px, value_lo, value_hi, side):
    """Fill a shaded bar into the 4x canvas (and its coverage into ``mask``)."""
    h = _hires(side)
    pts = (np.c_[poly_px, np.ones(4)] @ h.T)[:, :2]
    m = np.zeros(canvas.shape, np.uint8)
    cv2.fillConvexPoly(m, np.round(pts * 16).astype(np.int32), 255, cv2.LINE_AA, 4)
    cover = m.astype(np.float32) / 255.0
    # Shading across the bar: a linear ramp from one edge to the other.
    e = pts[3] - pts[0]
    yy, xx = np.mgrid[0 : canvas.shape[0], 0 : canvas.shape[1]]
    f = ((xx - pts[0, 0]) * e[0] + (yy - pts[0, 1]) * e[1]) / max(float(e @ e), 1e-9)
    shade = value_lo + (value_hi - value_lo) * np.clip(f, 0, 1)
    canvas *= 1 - cover
    canvas += cover * shade.astype(np.float32)
    if mask is not None:
        np.maximum(mask, cover, out=mask)


def _motion_kernel(length: float, angle: float) -> np.ndarray:
    n = int(math.ceil(length)) | 1
    kern = np.zeros((n * 4, n * 4), np.float32)
    c = (n * 4 - 1) / 2
    dx, dy = math.cos(angle) * length * 2, math.sin(angle) * length * 2
    cv2.line(
        kern,
        (int(round((c - dx) * 16)), int(round((c - dy) * 16))),
        (int(round((c + dx) * 16)), int(round((c + dy) * 16))),
        1.0,
        2,
        cv2.LINE_AA,
        4,
    )
    kern = cv2.resize(kern, (n, n), interpolation=cv2.INTER_AREA)
    return kern / kern.sum()


def _part_coverage(k, r, t, occluder: np.ndarray, side: int) -> dict[str, float]:
    parts = sign_shape("1111", DIAMETER_M).white_parts
    h = _hires(side)
    out = {}
    for name in PART_NAMES:
        xy = parts[name]
        uv = _project(k, r, t, np.c_[xy, np.zeros(4)])
        pts = (np.c_[uv, np.ones(4)] @ h.T)[:, :2]
        m = np.zeros(occluder.shape, np.uint8)
        cv2.fillConvexPoly(m, np.round(pts * 16).astype(np.int32), 1, cv2.LINE_8, 4)
        area = float(m.sum())
        out[name] = float((occluder * m).sum() / area) if area > 0 else 0.0
    return out


def render_scene_crop(code: str, s: SceneSettings, rng: np.random.Generator) -> SceneCrop:
    """Render sign ``code`` as ``s`` says, in a square crop with 25 % margin per side."""
    side = int(math.ceil(s.sign_px * 1.5))
    k, r, t = _camera(s, side, rng)
    n = side * SUPERSAMPLE
    canvas = _background(s, side, rng)
    for _ in range(s.bars_behind):
        poly, _ = _random_bar(rng, k, r, t, rng.uniform(0.05, 0.3), -rng.uniform(0.1, 1.0))
        lo = rng.uniform(20, 160)
        _draw_bar(canvas, None, poly, lo, lo + rng.uniform(0, 60), side)
    # The face: texture px -> sign metres -> image px -> 4x px.
    tex_px = int(min(512, max(64, 4 * SUPERSAMPLE * s.sign_px)))
    tex, alpha = _face(code, tex_px)
    scale = tex_px / DIAMETER_M
    rad = DIAMETER_M / 2
    sign_from_tex = np.array(
        [[1 / scale, 0, 0.5 / scale - rad], [0, -1 / scale, rad - 0.5 / scale], [0, 0, 1]]
    )
    img_from_sign = k @ np.c_[r[:, :2], t]
    hi_from_tex = _hires(side) @ img_from_sign @ sign_from_tex
    face = cv2.warpPerspective(tex, hi_from_tex, (n, n), flags=cv2.INTER_LINEAR)
    cover = cv2.warpPerspective(alpha, hi_from_tex, (n, n), flags=cv2.INTER_LINEAR)
    face = s.black_level + (s.white_level - s.black_level) * face
    if s.dirt:
        for _ in range(rng.integers(2, 6)):
            c = _project(k, r, t, np.array([[*rng.uniform(-0.35, 0.35, 2) * DIAMETER_M, 0]]))[0]
            c = (_hires(side) @ np.r_[c, 1])[:2]
            rr = rng.uniform(0.03, 0.1) * s.sign_px * SUPERSAMPLE
            spot = np.zeros((n, n), np.float32)
            cv2.circle(spot, (int(c[0]), int(c[1])), int(rr), 1.0, -1, cv2.LINE_AA)
            face = face * (1 - 0.5 * spot) + 0.5 * spot * rng.uniform(60, 140)
    if s.glare > 0:
        c = _project(k, r, t, np.array([[*rng.uniform(-0.3, 0.3, 2) * DIAMETER_M, 0]]))[0]
        c = (_hires(side) @ np.r_[c, 1])[:2]
        sg = rng.uniform(0.08, 0.25) * s.sign_px * SUPERSAMPLE
        yy, xx = np.mgrid[0:n, 0:n]
        face = face + s.glare * np.exp(-((xx - c[0]) ** 2 + (yy - c[1]) ** 2) / (2 * sg * sg))
    canvas = canvas * (1 - cover) + face * cover
    occluder = np.zeros((n, n), np.float32)
    bars = []
    front = [("member", 0)] * s.members_front + [("conductor", 0)] * s.conductors_front
    if s.bar_over_slot:
        front.append(("member", s.bar_over_slot))
    for kind, slot in front:
        if kind == "member" and slot:
            width = rng.uniform(0.16, 0.2)
            lo = rng.uniform(25, 120)
            hi = lo + rng.uniform(0, 40)
        elif kind == "member":
            width = rng.uniform(0.08, 0.35)
            lo = rng.uniform(25, 120) if rng.random() > 0.15 else rng.uniform(130, 190)
            hi = lo + rng.uniform(0, 50)
        else:
            width = rng.uniform(0.015, 0.06)
            lo = rng.uniform(10, 70)
            hi = lo + rng.uniform(0, 20)
        poly, radius = _random_bar(rng, k, r, t, width, rng.uniform(0.05, 1.5), slot)
        _draw_bar(canvas, occluder, poly, lo, hi, side)
        bars.append({"kind": kind, "width_frac": float(width)})
    img = cv2.resize(canvas, (side, side), interpolation=cv2.INTER_AREA)
    if s.blur_px > 0:
        img = cv2.filter2D(img, -1, _motion_kernel(s.blur_px, rng.uniform(0, math.pi)))
    if s.psf_sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), s.psf_sigma_px)
    img = img * s.gain + s.offset + rng.normal(0, s.noise_sigma, img.shape)
    img = np.clip(np.round(img), 0, 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(s.jpeg_quality)])
    img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    kps = sign_keypoints(code, DIAMETER_M)
    names = list(kps)
    uv = _project(k, r, t, np.array([kps[m] for m in names]))
    covered = _part_coverage(k, r, t, occluder, side)
    return SceneCrop(
        image=img,
        code=code,
        keypoints_px={m: (float(p[0]), float(p[1])) for m, p in zip(names, uv, strict=True)},
        covered=covered,
        settings=s,
        bars=bars,
    )


CONDITIONS = (
    "photo background",
    "jpeg 70",
    "blur burst",
    "gain and exposure",
    "specular glare",
    "faded or dirty face",
    "member in front",
    "conductor in front",
    "one slot covered",
    "mixed",
)


def scene_settings(rng: np.random.Generator, condition: str) -> SceneSettings:
    """Random settings of one crop of ``condition`` (nominal except for it; "mixed": all)."""
    mixed = condition == "mixed"
    sign_px = float(math.exp(rng.uniform(math.log(18), math.log(120))))
    kw = {
        "sign_px": sign_px,
        "rotation_deg": float(rng.uniform(0, 360)),
        "tilt_deg": float(rng.uniform(0, 45)),
        "tilt_axis_deg": float(rng.uniform(0, 180)),
        "focal_px": float(rng.choice([600.0, 1000.0, 1600.0])),
        "photo": str(rng.choice(PHOTOS)),
        "black_level": float(rng.uniform(15, 50)),
        "white_level": float(rng.uniform(195, 240)),
        "noise_sigma": float(rng.uniform(1, 3)),
        "psf_sigma_px": float(rng.uniform(0.3, 0.7)),
        "jpeg_quality": int(rng.integers(80, 91)),
        "bars_behind": int(rng.random() < 0.3),
    }
    if condition == "jpeg 70" or (mixed and rng.random() < 0.3):
        kw["jpeg_quality"] = int(rng.integers(70, 76))
    if condition == "blur burst" or (mixed and rng.random() < 0.15):
        kw["blur_px"] = float(rng.uniform(2, max(3, min(10, 0.12 * sign_px))))
    if condition == "gain and exposure" or (mixed and rng.random() < 0.3):
        kw["gain"] = float(rng.uniform(0.45, 1.5))
        kw["offset"] = float(rng.uniform(-30, 30))
    if condition == "specular glare" or (mixed and rng.random() < 0.1):
        kw["glare"] = float(rng.uniform(40, 140))
    if condition == "faded or dirty face" or (mixed and rng.random() < 0.1):
        kw["white_level"] = float(rng.uniform(140, 190))
        kw["black_level"] = float(rng.uniform(40, 80))
        kw["dirt"] = bool(rng.random() < 0.6)
    if condition == "member in front" or (mixed and rng.random() < 0.15):
        kw["members_front"] = 1
    if condition == "one slot covered":
        kw["bar_over_slot"] = int(rng.integers(1, 5))
    if condition == "conductor in front" or (mixed and rng.random() < 0.15):
        kw["conductors_front"] = int(rng.integers(1, 3))
    return SceneSettings(**kw)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", help="PNG to write (a sheet of crops)")
    ap.add_argument("--condition", default="mixed", choices=CONDITIONS)
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    tiles = []
    for i in range(16):
        s = scene_settings(rng, args.condition)
        crop = render_scene_crop(PAPER_CODES[i % len(PAPER_CODES)], s, rng)
        tiles.append(cv2.resize(crop.image, (128, 128), interpolation=cv2.INTER_NEAREST))
    sheet = np.vstack([np.hstack(tiles[r * 4 : r * 4 + 4]) for r in range(4)])
    cv2.imwrite(args.out, sheet)
    return 0


if __name__ == "__main__":
    sys.exit(main())
