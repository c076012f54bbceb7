"""Training data for the sign cascade: rendered positive windows and sign-free images.

Positives are synthetic crops (``signpose.sim.crops``) of every code under
random disturbances, cut to the disc's bounding square and resampled to the
detector's window (``features.WINDOW_PX``). Negatives come from procedural
backgrounds of every kind and photographs shipped by installed packages,
mirrored too; ``signpose.training.mining`` cuts hard negatives out of them.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence

import cv2
import matplotlib
import numpy as np

from signpose.frontend.sign import ALL_CODES
from signpose.sim.crops import BACKGROUNDS, render_background, render_crop
from signpose.sim.photos import load_photo
from signpose.training.features import WINDOW_PX

MATPLOTLIB_PHOTOS = ("grace_hopper.jpg", "Minduka_Present_Blue_Pack.png", "logo2.png")
SKIMAGE_PHOTOS = (
    "astronaut",
    "camera",
    "coffee",
    "chelsea",
    "rocket",
    "brick",
    "grass",
    "gravel",
    "moon",
    "page",
    "text",
    "coins",
    "clock",
    "hubble_deep_field",
)


def square_from_ellipse(
    ellipse: tuple[tuple[float, float], tuple[float, float], float],
) -> tuple[float, float, float]:
    """(cx, cy, side) of the square bounding a ``cv2.RotatedRect``-style ellipse [px]."""
    (cx, cy), (a, b), ang = ellipse
    t = math.radians(ang)
    hx = math.sqrt((a / 2 * math.cos(t)) ** 2 + (b / 2 * math.sin(t)) ** 2)
    hy = math.sqrt((a / 2 * math.sin(t)) ** 2 + (b / 2 * math.cos(t)) ** 2)
    return cx, cy, 2 * max(hx, hy)


def crop_square(image: np.ndarray, cx: float, cy: float, side: float, out_px: int) -> np.ndarray:
    """Resample the square of ``side`` px centred at (cx, cy) to ``out_px`` (bilinear).

    Downscaling goes through ``cv2.INTER_AREA`` first when strong, then
    ``INTER_LINEAR`` like the detector's pyramid.
    """
    s = out_px / side
    m = np.array([[s, 0, out_px / 2 - 0.5 - s * cx], [0, s, out_px / 2 - 0.5 - s * cy]])
    return cv2.warpAffine(
        image, m, (out_px, out_px), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )


def render_positives(
    n: int,
    rng: np.random.Generator,
    codes: Sequence[str] | None = None,
    window_px: int = WINDOW_PX,
    progress: Callable[[int], None] | None = None,
) -> np.ndarray:
    """``n`` positive windows: signs of all codes from ``signpose.sim.crops``, randomly disturbed.

    Each sign is rendered at 22-90 px with random in-plane rotation, view angle
    up to 65 degrees, motion blur, noise, exposure, dirt and power lines on
    every background kind, then cut to the disc's bounding square (with a
    little position/size jitter, as a detector window sees it) and resampled
    to ``window_px``.

    Returns:
        (n, window_px, window_px) uint8.
    """
    codes = tuple(codes or ALL_CODES)
    out = np.empty((n, window_px, window_px), np.uint8)
    for i in range(n):
        sign_px = float(math.exp(rng.uniform(math.log(22), math.log(90))))
        crop = render_crop(
            codes[i % len(codes)],
            rng,
            sign_px=sign_px,
            rotation_deg=rng.uniform(0, 360),
            tilt_deg=rng.uniform(0, 65) if rng.random() < 0.8 else 0.0,
            tilt_axis_deg=rng.uniform(0, 180),
            blur_px=rng.uniform(0, 0.08 * sign_px) if rng.random() < 0.4 else 0.0,
            noise_sigma=rng.uniform(0, 10),
            dirt=bool(rng.random() < 0.15),
            power_line=bool(rng.random() < 0.3),
            background=BACKGROUNDS[int(rng.integers(len(BACKGROUNDS)))],
            contrast=rng.uniform(0.45, 1.15),
            brightness=rng.uniform(-50, 50),
            margin=0.4,
            psf_sigma_px=rng.uniform(0.3, 0.9),
            supersample=4,
        )
        cx, cy, side = square_from_ellipse(crop.ellipse)
        side *= math.exp(rng.uniform(-0.07, 0.07))
        cx += rng.uniform(-0.05, 0.05) * side
        cy += rng.uniform(-0.05, 0.05) * side
        out[i] = crop_square(crop.image, cx, cy, side, window_px)
        if progress is not None:
            progress(1)
    return out


def photo_images() -> list[np.ndarray]:
    """Grey photographs shipped by installed packages (no downloads).

    matplotlib's sample_data always; scikit-image's ``skimage.data`` images
    when the optional ``train`` extra is installed (``signpose.sim.photos``).
    """
    out: list[np.ndarray] = []
    folder = os.path.join(matplotlib.get_data_path(), "sample_data")
    for name in MATPLOTLIB_PHOTOS:
        im = cv2.imread(os.path.join(folder, name), cv2.IMREAD_GRAYSCALE)
        if im is not None:
            out.append(im)
    for name in SKIMAGE_PHOTOS:
        bgr = load_photo(name)
        if bgr is not None:
            out.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    return out


def background_images(rng: np.random.Generator, per_kind: int = 6) -> list[np.ndarray]:
    """Sign-free negative images: procedural backgrounds of every kind plus photographs."""
    out = []
    for kind in BACKGROUNDS:
        for _ in range(per_kind):
            h, w = int(rng.integers(240, 720)), int(rng.integers(240, 960))
            out.append(render_background(rng, h, w, kind))
    photos = photo_images()
    out += photos
    out += [np.ascontiguousarray(p[:, ::-1]) for p in photos]  # mirrored copies
    return out
