"""Per-frame sign observations and their JSON Lines file (the frontend/estimator boundary).

One line per frame, in frame order; a frame with no signs is still a line::

    {"frame": 0, "stamp_ns": 0, "image_size": [1920, 1080],
     "signs": [{"code": "0101", "keypoints_px": {"center": [u, v], "direction": [u, v]},
                "bbox_px": [x, y, w, h], "sigma_px": 0.4, "score": 1.0,
                "erased_slots": [2], "keypoint_sigma_px": {"center": [su, sv]}}]}

Pixels are raw image pixels (distorted, centres at integers). Only ``code``
and ``keypoints_px.center`` are required for a sign; ``erased_slots`` and
``keypoint_sigma_px`` are written only when not empty. The file is read and
written by ``signpose.io.observations``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

DEFAULT_SIGMA_PX = 0.5


@dataclass(frozen=True)
class SignObservation:
    """One decoded sign in one image.

    Attributes:
        code: the decoded code, "0000".."1111".
        keypoints_px: keypoint name -> (u, v) raw pixel position; always has
            ``center``; other names as in ``frontend.sign.KEYPOINT_NAMES``.
        bbox_px: (x, y, w, h) region in pixels, or None.
        sigma_px: standard deviation of each keypoint coordinate [px] (one
            value for all; ``keypoint_sigma_px`` refines it per keypoint).
        score: detector/decoder confidence in [0, 1].
        erased_slots: coded slots (1..4) the image did not show (an
            occluder); ``code`` is the one code of the map that fits the
            others. Empty for a sign read whole.
        keypoint_sigma_px: keypoint name -> (sigma_u, sigma_v) [px], the
            decoder's calibrated noise per keypoint and axis; empty when
            unknown (then ``sigma_px`` holds for every keypoint).
    """

    code: str
    keypoints_px: dict[str, tuple[float, float]]
    bbox_px: tuple[float, float, float, float] | None = None
    sigma_px: float = DEFAULT_SIGMA_PX
    score: float = 1.0
    erased_slots: tuple[int, ...] = ()
    keypoint_sigma_px: dict[str, tuple[float, float]] = field(default_factory=dict)

    @property
    def center_px(self) -> tuple[float, float]:
        return self.keypoints_px["center"]


@dataclass(frozen=True)
class FrameObservations:
    """All sign observations of one frame.

    Attributes:
        frame: frame index, from 0.
        stamp_ns: frame time [ns] (from the container/log, or frame / fps).
        image_size: (width, height) [px].
        signs: the decoded signs, any order.
    """

    frame: int
    stamp_ns: int
    image_size: tuple[int, int]
    signs: tuple[SignObservation, ...] = field(default_factory=tuple)
