"""Real photographs for backgrounds: scikit-image's bundled data images, when installed.

scikit-image is optional (the ``train`` extra); without it ``load_photo``
returns None and callers fall back to procedural backgrounds. Nothing is
downloaded: only images that ship inside the installed package are used
(``skimage.data`` fetches some others on demand; those are skipped).

Images are returned as (H, W, 3) uint8 BGR (OpenCV's channel order),
read-only and cached per process.
"""

from __future__ import annotations

import functools
import importlib
import logging

import numpy as np

log = logging.getLogger(__name__)

# Outdoor scenes, textures, a dark sky and indoor clutter: the range of what
# lies behind a pylon (sky, fields, buildings, dark regions, busy texture).
PHOTO_NAMES: tuple[str, ...] = (
    "rocket",
    "camera",
    "astronaut",
    "coffee",
    "chelsea",
    "grass",
    "gravel",
    "brick",
    "hubble_deep_field",
    "moon",
)


@functools.lru_cache(maxsize=1)
def _skimage_data():
    """``skimage.data``, or None when scikit-image is not installed.

    Imported on first use, not at module level: scikit-image is an optional
    extra and the simulator must import without it.
    """
    try:
        return importlib.import_module("skimage.data")
    except ImportError:
        log.info("scikit-image is not installed: no photographs, procedural backgrounds only")
        return None


@functools.lru_cache(maxsize=32)
def load_photo(name: str) -> np.ndarray | None:
    """(H, W, 3) uint8 BGR image ``name`` of ``skimage.data``, None if unavailable."""
    data = _skimage_data()
    if data is None or not hasattr(data, name):
        return None
    try:
        im = np.asarray(getattr(data, name)())
    except Exception:  # noqa: BLE001 - some images need optional data files or a download
        return None
    if im.ndim == 2:
        im = np.repeat(im[..., None], 3, axis=2)
    out = np.ascontiguousarray(im[..., :3][..., ::-1]).astype(np.uint8)  # RGB -> BGR
    out.flags.writeable = False
    return out


def available_photos(names: tuple[str, ...] = PHOTO_NAMES) -> tuple[str, ...]:
    """The names among ``names`` that load here (empty without scikit-image)."""
    return tuple(n for n in names if load_photo(n) is not None)
