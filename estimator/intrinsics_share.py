"""The camera calibration's share of the position sigmas.

Seen from one pylon face, a focal length and the range to the face are one
parameter: a focal length a fraction ``e`` off scales every camera-to-signs
vector by about ``1 + e`` and the residuals do not change
(scripts/eval_setup_faults.py: a focal length 3 % / 8 % off on 20-27 m
flights gave 0.76-2.3 m errors at a pixel noise scale of 1.0, every ``ok``
pose beyond 3 sigma). Nothing in the video can tell; only the user can say
how well the camera was calibrated. With that relative focal sigma ``e``,
each pose's position covariance grows by ``e**2 d d^T``, with ``d`` the vector
from the centroid of the signs the frame sees to the camera, and its world-axis
sigmas by the diagonal of that. The same error for every frame that sees the
same signs: it does not average out over frames, so the smoother's sigma
gets it whole, as PnP's does.

A principal point off by ``c`` px acts like a camera rotation of ``c / f``
rad and leaves the position nearly as it is: it is not added here.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import TypeVar

import numpy as np
from signpose.estimator.status import PoseStatus
from signpose.frontend.observations import FrameObservations
from signpose.maps.loader import SignMap

# estimate.MethodEstimate (estimate imports this module): sigma_xyz, world_T_cam, status.
Method = TypeVar("Method")


def scene_to_camera_m(
    frames: Sequence[FrameObservations], sign_map: SignMap, world_T_cam: np.ndarray
) -> np.ndarray:
    """(N, 3) vector from the centroid of each frame's map signs to the camera, world [m];
    NaN for a frame without one of the map's signs."""
    out = np.full((len(frames), 3), np.nan)
    for i, f in enumerate(frames):
        centres = [s.center_m for o in f.signs if (s := sign_map.sign(o.code)) is not None]
        if centres:
            out[i] = np.asarray(world_T_cam[i])[:3, 3] - np.mean(centres, axis=0)
    return out


def with_focal_share(
    method: Method,
    frames: Sequence[FrameObservations],
    sign_map: SignMap,
    focal_sigma_rel: float,
    weak_sigma_m: float,
) -> Method:
    """``method`` with the focal length's share added to its position sigmas.

    Args:
        method: one method's trajectory, ``frames`` in its order.
        frames: the flight's observations, one per pose.
        sign_map: the map (the signs' centres).
        focal_sigma_rel: the calibration's focal length sigma, a fraction of it.
        weak_sigma_m: an ``ok`` pose whose worst-axis sigma then exceeds this
            becomes ``weak`` (``StatusSettings.weak_sigma_m``).

    Returns:
        The method unchanged when ``focal_sigma_rel`` is 0 or it has no sigmas
        (the baseline); else with sigmas sqrt(sigma^2 + (e d)^2) per axis; a
        frame that sees no map sign (a bridged pose) takes the nearest seen
        frame's ``d``.
    """
    sigma = np.asarray(method.sigma_xyz, float)
    if focal_sigma_rel <= 0 or not np.any(np.isfinite(sigma)):
        return method
    d = scene_to_camera_m(frames, sign_map, method.world_T_cam)
    seen = np.flatnonzero(np.all(np.isfinite(d), axis=1))
    if len(seen) == 0:
        return method
    missing = np.flatnonzero(~np.all(np.isfinite(d), axis=1))
    if len(missing):
        nearest = seen[np.abs(seen[None, :] - missing[:, None]).argmin(axis=1)]
        d[missing] = d[nearest]
    sigma = np.sqrt(sigma**2 + (focal_sigma_rel * d) ** 2)
    worst = np.max(sigma, axis=1)
    status = tuple(
        PoseStatus.WEAK if st is PoseStatus.OK and not w <= weak_sigma_m else st
        for st, w in zip(method.status, worst, strict=True)
    )
    return replace(method, sigma_xyz=sigma, status=status)
