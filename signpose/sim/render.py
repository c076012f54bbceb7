"""Synthetic camera frames of signs on a pylon (the image side of the flight simulator).

This module only draws. The caller (``signpose.sim.frame``) owns the camera
model and projects every 3D element -- the sign faces, dirt and occluders on
them, lattice members, conductors -- into raw (distorted) pixels; this module
receives those 2D polygons and polylines and turns them into a BGR frame:

    sky and ground (once-per-flight textures, re-projected per frame) or a
       photograph (``PhotoBackdrop``)
    -> lattice members and far conductors -> motion blur of that layer
    -> each sign, rendered in its own bounding box (anti-aliased, supersampled,
       faded paint, specular glare, blurred with its own motion)
    -> conductors in front of the signs -> lattice members in front of signs
    -> lighting gain/offset -> sensor noise -> JPEG round trip.

Pixels: u right, v down, pixel centres at integer coordinates (as in
``frontend.sign``). Intensities are on a 0..255 scale before quantisation.

The sky and ground are drawn through an ideal pinhole with the camera's K
(lens distortion is ignored there: they carry no measured geometry); all
projected geometry passed in by the caller includes the distortion.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from signpose.frontend.sign import fill_polygon_aa

# Paint reflectances on the 0..255 scale: matt black and white sign faces.
SIGN_BLACK = 28.0
SIGN_WHITE = 226.0


@dataclass(frozen=True)
class RenderOptions:
    """How a frame is rendered (defaults: the realistic flight).

    Attributes:
        supersample: sub-samples per pixel side for sign polygons.
        blur: apply motion blur from the per-sign / background image motion.
        noise_sigma: standard deviation of the additive sensor noise [DN]; 0 = off.
        jpeg_quality: JPEG encode/decode round trip quality (1..100), None = off.
        background: draw sky, ground, lattice and conductors; False gives a flat
            mid-grey background (clean frames for geometry tests).
        lighting: apply the global gain/offset passed to ``compose_frame``.
    """

    supersample: int = 4
    blur: bool = True
    noise_sigma: float = 2.5
    jpeg_quality: int | None = 90
    background: bool = True
    lighting: bool = True


@dataclass(frozen=True)
class ProjectedLine:
    """A thin structure (lattice member, conductor) projected into the image.

    Attributes:
        points_px: (N, 2) polyline in raw pixels, N >= 2.
        widths_px: (N - 1,) drawn width of each segment [px].
        bgr: colour on the 0..255 scale.
    """

    points_px: np.ndarray
    widths_px: np.ndarray
    bgr: tuple[float, float, float]


@dataclass(frozen=True)
class Glare:
    """A specular highlight on a face as projected this frame.

    Attributes:
        center_px: (2,) centre of the highlight in raw pixels.
        radius_px: its 1-sigma radius [px].
        peak_dn: intensity added at its centre [DN] (the face's sum saturates at 255).
    """

    center_px: np.ndarray
    radius_px: float
    peak_dn: float


@dataclass(frozen=True)
class ProjectedSign:
    """One sign face as the caller projected it for this frame.

    Attributes:
        code: the sign's code (for bookkeeping only).
        disc_px: (N, 2) black disc outline in raw pixels (densely sampled so
            that lens distortion is respected).
        white_px: (M_k, 2) outlines of the white rectangles in raw pixels.
        dirt_px: (polygon (P, 2) px, intensity 0..255, opacity 0..1) stains
            on the face, clipped to the disc when drawn.
        occluders_px: (polygon (P, 2) px, intensity 0..255) opaque objects in
            front of the face.
        motion_px: (2,) image motion of the sign centre during the exposure
            [px]; the blur kernel is this segment, centred on the sign.
        shade: reflectance/illumination factor of this face (weathering, sun angle).
        fade: paint fading: black and white are pulled toward their mean by ``fade``.
        glare: a specular highlight on the face, None = none.
    """

    code: str
    disc_px: np.ndarray
    white_px: tuple[np.ndarray, ...]
    dirt_px: tuple[tuple[np.ndarray, float, float], ...] = ()
    occluders_px: tuple[tuple[np.ndarray, float], ...] = ()
    motion_px: np.ndarray = field(default_factory=lambda: np.zeros(2))
    shade: float = 1.0
    fade: float = 0.0
    glare: Glare | None = None


def _value_noise(rng: np.random.Generator, shape: tuple[int, int], cells: list[int]) -> np.ndarray:
    """Smooth multi-octave noise in about [-1, 1], float32 of ``shape``, seamless when tiled.

    Each octave is a random grid of ``c`` cells across the height (and as many
    square cells across the width), wrapped by two cells on every side before
    the bicubic resize so the result tiles without a seam. ``shape`` must be
    divisible by every cell count.
    """
    h, w = shape
    out = np.zeros(shape, np.float32)
    amp, total = 1.0, 0.0
    for c in cells:
        cw = max(1, c * w // h)
        step_y, step_x = h // c, w // cw
        small = rng.standard_normal((c, cw)).astype(np.float32)
        padded = np.pad(small, 2, mode="wrap")
        big = cv2.resize(
            padded, ((cw + 4) * step_x, (c + 4) * step_y), interpolation=cv2.INTER_CUBIC
        )
        out += amp * big[2 * step_y : 2 * step_y + h, 2 * step_x : 2 * step_x + w]
        total += amp
        amp *= 0.55
    return out / total


def _ray_grid(
    K: np.ndarray, world_R_cam: np.ndarray, gu: np.ndarray, gv: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World directions (x, y, z), each (len(gv), len(gu)), of the pinhole rays through
    the pixel grid ``gu`` x ``gv`` (not normalised: camera z component 1)."""
    Ki = np.linalg.inv(K)
    xc = (Ki[0, 0] * gu + Ki[0, 2])[None, :]
    yc = (Ki[1, 1] * gv + Ki[1, 2])[:, None]
    R = world_R_cam
    dx = R[0, 0] * xc + R[0, 1] * yc + R[0, 2]
    dy = R[1, 0] * xc + R[1, 1] * yc + R[1, 2]
    dz = R[2, 0] * xc + R[2, 1] * yc + R[2, 2]
    return dx, dy, dz


class Backdrop:
    """Once-per-flight background layers: sky panorama, ground texture, noise bank.

    Built from a seed; per frame ``sky_and_ground`` re-projects them for a pose.
    The textures depend only on the seed and are shared between backdrops
    (cached per process), the noise bank is built on first use.

    Args:
        width, height: frame size [px].
        seed: seeds every texture.
        ground_m_per_px: ground texture resolution [m/px].
    """

    SKY_W, SKY_H = 2048, 512  # azimuth 0..360 deg x elevation 90..0 deg
    GROUND_PX = 2048
    NOISE_PAD = 64
    BG_SCALE = 4
    MAP_SCALE = 16

    def __init__(self, width: int, height: int, seed: int = 0, ground_m_per_px: float = 0.25):
        self.width, self.height = int(width), int(height)
        self.ground_m_per_px = float(ground_m_per_px)
        self.seed = int(seed)
        self.haze_bgr = np.array([222.0, 214.0, 205.0], np.float32)
        self._noise: np.ndarray | None = None

    @property
    def sky_u8(self) -> np.ndarray:
        """(SKY_H, SKY_W, 3) uint8 BGR panorama: azimuth across, elevation 90..0 down."""
        return _sky_texture(self.seed)

    @property
    def ground_u8(self) -> np.ndarray:
        """(GROUND_PX, GROUND_PX, 3) uint8 BGR ground texture, ``ground_m_per_px`` per texel."""
        return _ground_texture(self.seed)

    @property
    def noise_u8(self) -> np.ndarray:
        """(H + pad, W + pad, 3) uint8 noise bank: 128 + 16 N(0, 1), cropped per frame."""
        if self._noise is None:
            z = np.random.default_rng([self.seed, 3]).standard_normal(
                (self.height + self.NOISE_PAD, self.width + self.NOISE_PAD, 3), dtype=np.float32
            )
            self._noise = np.clip(128.0 + 16.0 * z, 0, 255).astype(np.uint8)
        return self._noise

    def sky_and_ground(self, K: np.ndarray, world_T_cam: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 BGR sky and ground as seen from ``world_T_cam`` (world z up).

        The ray geometry is evaluated on a 1/``MAP_SCALE`` grid and interpolated,
        the textures are sampled at 1/``BG_SCALE`` resolution and upscaled (the
        background is soft anyway; lattice and conductors are drawn at full
        resolution by ``compose_frame``).
        """
        sc, ms = self.BG_SCALE, self.MAP_SCALE
        bw, bh = -(-self.width // sc), -(-self.height // sc)
        mw, mh = -(-self.width // ms) + 1, -(-self.height // ms) + 1
        # Grid node k of the coarse grid sits at full-resolution pixel k * ms - 0.5 + ...;
        # nodes are placed so that resizing (mw, mh) -> (bw, bh) keeps them aligned.
        gu = (np.arange(mw, dtype=np.float64) + 0.5) * (bw / mw) * sc - 0.5
        gv = (np.arange(mh, dtype=np.float64) + 0.5) * (bh / mh) * sc - 0.5
        R = np.asarray(world_T_cam, dtype=np.float64)[:3, :3]
        dx, dy, dz = _ray_grid(K, R, gu, gv)
        horiz = np.sqrt(dx * dx + dy * dy) + 1e-12
        el = np.arctan2(dz, horiz)
        # Azimuth relative to the optical axis, so it is continuous across the image.
        az0 = math.atan2(R[1, 2], R[0, 2])
        c0, s0 = math.cos(az0), math.sin(az0)
        az = az0 + np.arctan2(-s0 * dx + c0 * dy, c0 * dx + s0 * dy)
        sky_x = az / (2 * np.pi) * self.SKY_W
        sky_y = (1.0 - np.clip(el, 0.0, np.pi / 2) / (np.pi / 2)) * self.SKY_H - 0.5
        # Ground: intersect rays with z = 0 (clamped far away; hazed out there anyway).
        cam = world_T_cam[:3, 3]
        height = max(float(cam[2]), 0.5)
        s = np.minimum(height / np.maximum(-dz, 1e-6), 4000.0 / horiz)
        lim = 30000.0  # remap's fixed-point coordinates
        gx = np.clip((cam[0] + s * dx) / self.ground_m_per_px, -lim, lim)
        gy = np.clip((cam[1] + s * dy) / self.ground_m_per_px, -lim, lim)
        haze = 1.0 - np.exp(-(s * horiz) / 900.0)
        # Poor man's mipmap: far ground is sampled from a blurred copy (no aliasing).
        far = np.clip((s * horiz - 60.0) / 200.0, 0.0, 1.0)
        w_sky = np.clip(0.5 + el / math.radians(0.5), 0.0, 1.0)
        coarse = np.stack([sky_x, sky_y, gx, gy, w_sky, haze, far], axis=-1).astype(np.float32)
        fine = cv2.resize(coarse[..., :4], (bw, bh), interpolation=cv2.INTER_LINEAR)
        weights = cv2.resize(coarse[..., 4:], (bw, bh), interpolation=cv2.INTER_LINEAR)
        # Wrap into the textures here: remap's border handling is a slow per-pixel path.
        sky_x = np.mod(fine[..., 0], np.float32(self.SKY_W))
        gx = np.mod(fine[..., 2], np.float32(self.GROUND_PX))
        gy = np.mod(fine[..., 3], np.float32(self.GROUND_PX))
        sky = cv2.remap(
            self.sky_u8, sky_x, fine[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP
        )
        ground = cv2.remap(self.ground_u8, gx, gy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        ground_far = cv2.remap(
            _ground_texture_far(self.seed), gx, gy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP
        )
        w_sky, haze, far = weights[..., 0], weights[..., 1], weights[..., 2]
        ground = cv2.blendLinear(ground, ground_far, 1.0 - far, far)
        hazy = np.empty_like(ground)
        hazy[:] = np.rint(self.haze_bgr).astype(np.uint8)
        ground = cv2.blendLinear(ground, hazy, 1.0 - haze, haze)
        small = cv2.blendLinear(sky, ground, w_sky, 1.0 - w_sky)
        big = cv2.resize(small, (bw * sc, bh * sc), interpolation=cv2.INTER_LINEAR)
        return np.ascontiguousarray(big[: self.height, : self.width])


class PhotoBackdrop(Backdrop):
    """A photograph behind the pylon instead of the procedural sky and ground.

    The photograph is wrapped around the viewer at infinity: a ray's azimuth
    (about world z, from ``look_dir``) and elevation map linearly to photo
    pixels, the photo's height spanning the frame's vertical field of view at
    the photo's centre, mirror-tiled beyond its edges. Rotating the camera
    pans the photo; the lens distortion is ignored (as for the sky).

    Args:
        width, height: frame size [px].
        photo_bgr: (h, w, 3) uint8 BGR photograph.
        look_dir: (3,) world direction the flight mostly looks along.
        seed: seeds the noise bank.
    """

    def __init__(
        self, width: int, height: int, photo_bgr: np.ndarray, look_dir: np.ndarray, seed: int = 0
    ):
        super().__init__(width, height, seed=seed)
        self.photo = np.ascontiguousarray(photo_bgr, dtype=np.uint8)
        self.az0 = math.atan2(float(look_dir[1]), float(look_dir[0]))

    def sky_and_ground(self, K: np.ndarray, world_T_cam: np.ndarray) -> np.ndarray:
        ms = self.MAP_SCALE
        mw, mh = -(-self.width // ms) + 1, -(-self.height // ms) + 1
        gu = np.linspace(-0.5, self.width - 0.5, mw)
        gv = np.linspace(-0.5, self.height - 0.5, mh)
        R = np.asarray(world_T_cam, dtype=np.float64)[:3, :3]
        d = _ray_grid(K, R, gu, gv)
        el = np.arctan2(d[2], np.hypot(d[0], d[1]))
        c0, s0 = math.cos(self.az0), math.sin(self.az0)
        az = np.arctan2(-s0 * d[0] + c0 * d[1], c0 * d[0] + s0 * d[1])
        ph, pw = self.photo.shape[:2]
        scale = ph * K[1, 1] / self.height  # photo px per radian
        coarse = np.stack([(pw - 1) / 2 - az * scale, (ph - 1) / 2 - el * scale], -1)
        fine = cv2.resize(
            coarse.astype(np.float32), (self.width, self.height), interpolation=cv2.INTER_LINEAR
        )
        mx = _mirror(fine[..., 0], pw)
        my = _mirror(fine[..., 1], ph)
        return cv2.remap(self.photo, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _mirror(x: np.ndarray, n: int) -> np.ndarray:
    """Coordinates folded into [0, n - 1] by mirror tiling (float32)."""
    period = 2.0 * (n - 1)
    y = np.mod(x, period)
    return np.where(y > n - 1, period - y, y).astype(np.float32)


@functools.lru_cache(maxsize=4)
def _sky_texture(seed: int) -> np.ndarray:
    """(SKY_H, SKY_W, 3) uint8 BGR panorama: azimuth across, elevation 90..0 down (read-only)."""
    rng = np.random.default_rng([seed, 1])
    h, w = Backdrop.SKY_H, Backdrop.SKY_W
    el = (1.0 - (np.arange(h, dtype=np.float32) + 0.5) / h)[:, None]  # 1 at zenith, 0 horizon
    zenith = np.array([190.0, 140.0, 95.0], np.float32)
    horizon = np.array([225.0, 215.0, 205.0], np.float32)
    t = np.sqrt(el)[..., None]
    sky = horizon * (1 - t) + zenith * t
    sky = np.broadcast_to(sky, (h, w, 3)).copy()
    clouds = _value_noise(rng, (h, w), [4, 8, 16, 32, 64])
    cover = np.clip((clouds - 0.05) * 2.5, 0.0, 1.0)[..., None] * 0.85
    cloud_bgr = np.array([235.0, 235.0, 235.0], np.float32) - 25.0 * np.clip(
        clouds[..., None], 0, 1
    )
    out = np.clip(np.rint(sky * (1 - cover) + cloud_bgr * cover), 0, 255).astype(np.uint8)
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=4)
def _ground_texture(seed: int) -> np.ndarray:
    """(GROUND_PX, GROUND_PX, 3) uint8 BGR seamless ground texture (read-only)."""
    rng = np.random.default_rng([seed, 2])
    n = Backdrop.GROUND_PX
    base = _value_noise(rng, (n, n), [8, 16, 32, 64, 128, 256])
    fields = _value_noise(rng, (n, n), [6, 12])
    grass = np.array([60.0, 120.0, 95.0], np.float32)
    soil = np.array([75.0, 105.0, 135.0], np.float32)
    mix = np.clip(0.5 + 1.5 * fields, 0, 1)[..., None]
    tex = grass * (1 - mix) + soil * mix
    tex *= (1.0 + 0.35 * base)[..., None]
    # A few tracks across the fields, drawn with their wrapped copies (seamless tile).
    for _ in range(6):
        p = rng.uniform(0, n, 2)
        a = rng.uniform(0, np.pi)
        d = np.array([np.cos(a), np.sin(a)]) * n * 2
        width = int(rng.integers(3, 9))
        for ox in (-n, 0, n):
            for oy in (-n, 0, n):
                q = p + [ox, oy]
                cv2.line(
                    tex,
                    tuple(int(v) for v in q - d),
                    tuple(int(v) for v in q + d),
                    (150.0, 165.0, 175.0),
                    width,
                    cv2.LINE_AA,
                )
    tex = cv2.GaussianBlur(tex, (0, 0), 0.8)
    out = np.clip(np.rint(tex), 0, 255).astype(np.uint8)
    out.flags.writeable = False
    return out


@functools.lru_cache(maxsize=4)
def _ground_texture_far(seed: int) -> np.ndarray:
    """The ground texture blurred for distant, grazing views (read-only)."""
    out = cv2.GaussianBlur(_ground_texture(seed), (0, 0), 6.0, borderType=cv2.BORDER_WRAP)
    out.flags.writeable = False
    return out


def line_kernel(motion_px: np.ndarray) -> np.ndarray | None:
    """Normalised float32 motion-blur kernel: the segment ``motion_px`` centred on the origin.

    Symmetric about its centre pixel, so blurring moves no centroid. Returns
    None when the motion is under half a pixel.
    """
    m = np.asarray(motion_px, dtype=float).reshape(2)
    length = float(np.hypot(*m))
    if not np.isfinite(length) or length < 0.5:
        return None
    half = int(math.ceil(max(abs(m[0]), abs(m[1])) / 2.0)) + 1
    k = 2 * half + 1
    ker = np.zeros((k, k), np.float32)
    n = max(int(math.ceil(length * 4)), 2) + 1
    for t in np.linspace(-0.5, 0.5, n):
        x, y = half + t * m[0], half + t * m[1]
        x0, y0 = int(math.floor(x)), int(math.floor(y))
        fx, fy = x - x0, y - y0
        ker[y0, x0] += (1 - fx) * (1 - fy)
        ker[y0, x0 + 1] += fx * (1 - fy)
        ker[y0 + 1, x0] += (1 - fx) * fy
        ker[y0 + 1, x0 + 1] += fx * fy
    # Bilinear splats of symmetric samples are symmetric up to rounding; force it.
    ker = 0.5 * (ker + ker[::-1, ::-1])
    return ker / ker.sum()


def _draw_lines(image: np.ndarray, lines: list[ProjectedLine], mask_mode: bool = False) -> None:
    """Draw anti-aliased polylines into uint8 ``image`` in place.

    With ``mask_mode`` the image is a single-channel coverage mask and each
    segment paints 255 (scaled down for sub-pixel widths); otherwise it paints
    the line's colour, faded toward the sky's haze for sub-pixel widths.
    Consecutive segments of equal drawn width go to one ``cv2.polylines`` call.
    """
    if not lines:
        return
    h, w = image.shape[:2]
    shift = 4
    scale = 1 << shift
    lim = 8 * max(h, w)
    haze = np.array([215.0, 210.0, 205.0])
    # All segments of all lines at once; a segment's key changes between lines.
    n_pts = np.array([len(ln.points_px) for ln in lines])
    pts = np.concatenate([np.asarray(ln.points_px, dtype=float).reshape(-1, 2) for ln in lines])
    widths = np.concatenate(
        [np.append(np.asarray(ln.widths_px, dtype=float), 0.0) for ln in lines]
    )  # one dummy segment from each line's last point to the next line's first
    line_id = np.repeat(np.arange(len(lines)), n_pts)
    a, b = pts[:-1], pts[1:]
    same_line = line_id[:-1] == line_id[1:]
    inside = same_line & ~(
        (np.maximum(a[:, 0], b[:, 0]) < -20)
        | (np.minimum(a[:, 0], b[:, 0]) > w + 20)
        | (np.maximum(a[:, 1], b[:, 1]) < -20)
        | (np.minimum(a[:, 1], b[:, 1]) > h + 20)
    )
    widths = widths[:-1]
    thick = np.maximum(1, np.rint(widths)).astype(np.int64)
    fade = np.round(np.minimum(widths, 1.0), 1)
    ip = np.round(np.clip(pts, -lim, lim) * scale).astype(np.int32)
    # Runs of consecutive visible segments of one line with the same drawn width and fade.
    key = np.where(
        inside, (line_id[:-1] * 1000 + thick) * 100 + np.rint(fade * 10).astype(np.int64), -1
    )
    starts = np.flatnonzero(np.diff(key, prepend=-2) != 0)
    ends = np.append(starts[1:], len(key))
    for i, j in zip(starts.tolist(), ends.tolist(), strict=True):
        if key[i] < 0:
            continue
        f = float(fade[i])
        if mask_mode:
            color: tuple[float, ...] = (255.0 * f,)
        else:
            color = tuple((haze + f * (np.asarray(lines[line_id[i]].bgr) - haze)).tolist())
        cv2.polylines(image, [ip[i : j + 1]], False, color, int(thick[i]), cv2.LINE_AA, shift)


def line_coverage(
    lines: Sequence[ProjectedLine], origin_px: np.ndarray, shape: tuple[int, int]
) -> np.ndarray:
    """(h, w) float32 share of each pixel the ``lines`` cover (0..1), as they are drawn.

    The box's pixel (0, 0) is the frame's pixel ``origin_px`` (2,); no blur.
    """
    mask = np.zeros(shape, np.uint8)
    off = np.asarray(origin_px, float)
    shifted = [ProjectedLine(ln.points_px - off, ln.widths_px, ln.bgr) for ln in lines]
    _draw_lines(mask, shifted, mask_mode=True)
    return mask.astype(np.float32) / 255.0


def _bbox(polygons: list[np.ndarray], margin: int, w: int, h: int) -> tuple[int, int, int, int]:
    """Integer (x0, y0, x1, y1) around ``polygons`` plus ``margin``, clipped to the frame."""
    allp = np.concatenate([np.asarray(p, dtype=float).reshape(-1, 2) for p in polygons])
    x0 = max(int(math.floor(allp[:, 0].min())) - margin, 0)
    y0 = max(int(math.floor(allp[:, 1].min())) - margin, 0)
    x1 = min(int(math.ceil(allp[:, 0].max())) + margin + 1, w)
    y1 = min(int(math.ceil(allp[:, 1].max())) + margin + 1, h)
    return x0, y0, x1, y1


def _glare_spot(glare: Glare, off: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(h, w) float32 Gaussian highlight [DN] on a box whose pixel (0, 0) is ``off``."""
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float32)
    du = u + off[0] - glare.center_px[0]
    dv = v + off[1] - glare.center_px[1]
    r2 = (du * du + dv * dv) / max(glare.radius_px, 0.5) ** 2
    return (glare.peak_dn * np.exp(-0.5 * r2)).astype(np.float32)


def _render_sign(frame: np.ndarray, sign: ProjectedSign, options: RenderOptions) -> None:
    """Composite one sign (and its occluders) over ``frame`` inside its bounding box.

    The face is rendered as premultiplied (alpha, alpha * intensity) so that
    blurring it with its own motion kernel and compositing over the already
    rendered background is exact at the disc's edge.
    """
    h, w = frame.shape[:2]
    kernel = line_kernel(sign.motion_px) if options.blur else None
    margin = 2 + (kernel.shape[0] // 2 if kernel is not None else 0)
    polys = [sign.disc_px] + [p for p, _ in sign.occluders_px]
    x0, y0, x1, y1 = _bbox(polys, margin, w, h)
    if x1 <= x0 or y1 <= y0:
        return
    off = np.array([x0, y0], float)
    ss = options.supersample
    alpha = np.zeros((y1 - y0, x1 - x0), np.float32)
    disc = sign.disc_px - off
    fill_polygon_aa(alpha, disc, 1.0, ss)
    black, white = SIGN_BLACK * sign.shade, SIGN_WHITE * sign.shade
    if sign.fade > 0:
        grey = 0.5 * (black + white)
        black, white = black + sign.fade * (grey - black), white + sign.fade * (grey - white)
    premult = alpha * black  # the black disc, premultiplied
    for part in sign.white_px:
        fill_polygon_aa(premult, part - off, white, ss)
    for poly, value, opacity in sign.dirt_px:
        stain = np.zeros_like(alpha)
        fill_polygon_aa(stain, poly - off, 1.0, ss)
        a = stain * alpha * float(opacity)
        premult += a * (float(value) - premult)
    if sign.glare is not None and sign.glare.peak_dn > 0:
        premult += alpha * _glare_spot(sign.glare, off, alpha.shape)
    for poly, value in sign.occluders_px:
        fill_polygon_aa(alpha, poly - off, 1.0, ss)
        fill_polygon_aa(premult, poly - off, float(value), ss)
    if kernel is not None:
        alpha = cv2.filter2D(alpha, -1, kernel, borderType=cv2.BORDER_CONSTANT)
        premult = cv2.filter2D(premult, -1, kernel, borderType=cv2.BORDER_CONSTANT)
    roi = frame[y0:y1, x0:x1].astype(np.float32)
    out = roi * (1.0 - alpha)[..., None] + premult[..., None]
    frame[y0:y1, x0:x1] = np.clip(np.rint(out), 0, 255).astype(np.uint8)


def compose_frame(
    backdrop: Backdrop | None,
    K: np.ndarray,
    world_T_cam: np.ndarray,
    signs: Sequence[ProjectedSign],
    rng: np.random.Generator,
    *,
    lines_behind: Sequence[ProjectedLine] = (),
    lines_front: Sequence[ProjectedLine] = (),
    members_front: Sequence[ProjectedLine] = (),
    background_motion_px: np.ndarray | None = None,
    gain: float = 1.0,
    offset: float = 0.0,
    options: RenderOptions = RenderOptions(),
    size: tuple[int, int] | None = None,
) -> np.ndarray:
    """Render one frame.

    Args:
        backdrop: the flight's static layers (required when ``options.background``).
        K: (3, 3) camera intrinsics [px], used for the sky and ground only.
        world_T_cam: (4, 4) camera pose, world z up, camera axes x right, y down, z forward.
        signs: the visible signs, projected by the caller (drawn in list order).
        rng: source of the per-frame randomness (noise crop).
        lines_behind: lattice members and conductors behind the signs.
        lines_front: conductors in front of the signs (drawn with the background).
        members_front: lattice members in front of signs (drawn even without
            background: they are an occlusion condition, not scenery).
        background_motion_px: (2,) image motion during the exposure used to blur
            the background and the front lines [px].
        gain, offset: global lighting, ``out = gain * in + offset`` [DN].
        options: rendering switches.
        size: (width, height) [px]; defaults to the backdrop's.

    Returns:
        (H, W, 3) uint8 BGR image.
    """
    if size is None:
        if backdrop is None:
            raise ValueError("compose_frame needs a backdrop or a size")
        size = (backdrop.width, backdrop.height)
    w, h = size
    bg_kernel = (
        line_kernel(background_motion_px)
        if options.blur and background_motion_px is not None
        else None
    )
    if options.background and backdrop is not None:
        frame = backdrop.sky_and_ground(K, world_T_cam)
        _draw_lines(frame, list(lines_behind))
        if bg_kernel is not None:
            frame = cv2.filter2D(frame, -1, bg_kernel, borderType=cv2.BORDER_REFLECT)
    else:
        frame = np.full((h, w, 3), 128, np.uint8)
    for sign in signs:
        _render_sign(frame, sign, options)
    if options.background and lines_front:
        _composite_front_lines(frame, lines_front, bg_kernel)
    if members_front:
        _composite_front_lines(frame, members_front, bg_kernel)
    if not options.lighting:
        gain, offset = 1.0, 0.0
    return _sensor(frame, backdrop, rng, gain, offset, options)


def _composite_front_lines(
    frame: np.ndarray, lines: Sequence[ProjectedLine], kernel: np.ndarray | None
) -> None:
    """Blend ``lines`` (blurred by ``kernel``) into ``frame``, one pass per colour."""
    for bgr in dict.fromkeys(ln.bgr for ln in lines):
        _composite_lines_of_one_colour(frame, [ln for ln in lines if ln.bgr == bgr], kernel)


def _composite_lines_of_one_colour(
    frame: np.ndarray, lines: list[ProjectedLine], kernel: np.ndarray | None
) -> None:
    h, w = frame.shape[:2]
    mask = np.zeros((h, w), np.uint8)
    _draw_lines(mask, lines, mask_mode=True)
    if kernel is not None:
        mask = cv2.filter2D(mask, -1, kernel, borderType=cv2.BORDER_CONSTANT)
    # Thin lines cover few pixels: composite only those.
    nz = cv2.findNonZero(mask)
    if nz is not None:
        xs, ys = nz[:, 0, 0], nz[:, 0, 1]
        a = mask[ys, xs].astype(np.float32)[:, None] * (1.0 / 255.0)
        px = frame[ys, xs].astype(np.float32)
        color = np.asarray(lines[0].bgr, np.float32)
        frame[ys, xs] = np.clip(np.rint(px + a * (color - px)), 0, 255).astype(np.uint8)


def _sensor(
    frame: np.ndarray,
    backdrop: Backdrop | None,
    rng: np.random.Generator,
    gain: float,
    offset: float,
    options: RenderOptions,
) -> np.ndarray:
    """Lighting gain/offset, sensor noise and the JPEG round trip of a rendered frame."""
    h, w = frame.shape[:2]
    sigma = float(options.noise_sigma)
    if sigma > 0 and backdrop is not None:
        pad = Backdrop.NOISE_PAD
        dy, dx = (int(v) for v in rng.integers(0, pad, 2))
        noise = backdrop.noise_u8[dy : dy + h, dx : dx + w]
        beta = sigma / 16.0
        frame = cv2.addWeighted(frame, gain, noise, beta, offset - 128.0 * beta)
    elif gain != 1.0 or offset != 0.0:
        frame = cv2.convertScaleAbs(frame, alpha=gain, beta=offset)
    if options.jpeg_quality is not None:
        ok, buf = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, int(options.jpeg_quality)])
        if ok:
            frame = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    return frame
