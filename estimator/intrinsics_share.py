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

A principal point off by ``c`` px shifts every keypoint by ``c`` px, which a
camera rotation of ``c / f`` rad does too, and so does a shift of the camera
by ``c / f`` times the signs' depth across the optical axis: from one pylon
face the two are nearly one direction, and where the fit settles between
them depends on the face's tilt and spread. The share here is the fit's own
first-order answer (``principal_point_response``): the pose change of the
frame's pixel-weighted least squares when every keypoint moves by one pixel
in u (and in v), ``(J^T W J)^-1 J^T W 1``, of which the position part in
world axes, times the stated sigma, adds in quadrature
(scripts/eval_principal_share.py compares it, and ``c / f`` times the depth,
with the poses a shifted principal point gives). It too is the same error
for every frame that sees the same signs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace
from typing import TypeVar

import numpy as np
from signpose.estimator.camera import CameraModel
from signpose.estimator.perframe import keypoint_sigmas
from signpose.estimator.projection import MAX_CONDITION, pixels_and_pose_jacobian
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
    d = _nearest_filled(scene_to_camera_m(frames, sign_map, method.world_T_cam))
    if d is None:
        return method
    return _with_share(method, (focal_sigma_rel * d) ** 2, weak_sigma_m)


def principal_point_response(
    frame: FrameObservations, sign_map: SignMap, camera: CameraModel, world_T_cam: np.ndarray
) -> np.ndarray | None:
    """(2, 3) first-order camera position change, world [m], per pixel of principal
    point error in u (row 0) and v (row 1); None without enough map keypoints.

    The pose fit minimises the keypoints' pixel residuals weighted by their
    sigmas (``perframe.keypoint_sigmas``); a principal point ``c`` px off moves
    every predicted keypoint by ``c``, so the fit moves by ``-(J^T W J)^-1 J^T W b``
    with ``J`` the (2K, 6) pixel Jacobian of the pose perturbation
    (``projection``: ``xi = [omega, v]`` in the camera frame) and ``b`` ones on
    that pixel axis. The sign does not matter to a sigma; the position part
    is ``world_R_cam @ v``.
    """
    points, weights = [], []
    for obs in frame.signs:
        sign = sign_map.sign(obs.code)
        if sign is None:
            continue
        for name, world_p in sign.keypoints_world().items():
            if name in obs.keypoints_px:
                points.append(world_p)
                weights.extend(1.0 / np.square(keypoint_sigmas(obs, name)))
    if len(points) < 3:
        return None
    _, J, _ = pixels_and_pose_jacobian(camera, world_T_cam, np.asarray(points))
    J = J.reshape(-1, 6)
    w = np.asarray(weights)
    info = J.T @ (w[:, None] * J)
    if not np.linalg.cond(info) < MAX_CONDITION:
        return None
    b = np.zeros((len(w), 2))
    b[0::2, 0], b[1::2, 1] = 1.0, 1.0  # residuals alternate u, v
    xi = np.linalg.solve(info, J.T @ (w[:, None] * b))  # (6, 2)
    return (np.asarray(world_T_cam)[:3, :3] @ xi[3:]).T


def with_principal_share(
    method: Method,
    frames: Sequence[FrameObservations],
    sign_map: SignMap,
    camera: CameraModel,
    principal_sigma_px: float,
    weak_sigma_m: float,
) -> Method:
    """``method`` with the principal point's share added to its position sigmas.

    Args:
        method: one method's trajectory, ``frames`` in its order.
        frames: the flight's observations, one per pose.
        sign_map: the map (the signs' keypoints).
        camera: the camera file's model (its K: the Jacobians).
        principal_sigma_px: the calibration's principal point sigma on each
            image axis [px].
        weak_sigma_m: as for ``with_focal_share``.

    Returns:
        The method unchanged when ``principal_sigma_px`` is 0 or it has no
        sigmas; else with sigma^2 + principal_sigma_px^2 (a_u^2 + a_v^2) per
        world axis, ``a_u``, ``a_v`` the rows of ``principal_point_response``
        at the method's pose; a frame without one (no map sign, too few
        keypoints) takes the nearest such frame's.
    """
    sigma = np.asarray(method.sigma_xyz, float)
    if principal_sigma_px <= 0 or not np.any(np.isfinite(sigma)):
        return method
    share = np.full(sigma.shape, np.nan)
    for i in np.flatnonzero(np.all(np.isfinite(sigma), axis=1)):
        a = principal_point_response(frames[i], sign_map, camera, method.world_T_cam[i])
        if a is not None:
            share[i] = principal_sigma_px**2 * np.sum(a**2, axis=0)
    share = _nearest_filled(share)
    if share is None:
        return method
    return _with_share(method, share, weak_sigma_m)


def with_intrinsics_shares(
    method: Method,
    frames: Sequence[FrameObservations],
    sign_map: SignMap,
    camera: CameraModel,
    focal_sigma_rel: float,
    principal_sigma_px: float,
    weak_sigma_m: float,
) -> Method:
    """``method`` with the focal length's share, then the principal point's, added to its
    position sigmas (independent errors: in quadrature); unchanged when both are 0."""
    method = with_focal_share(method, frames, sign_map, focal_sigma_rel, weak_sigma_m)
    return with_principal_share(method, frames, sign_map, camera, principal_sigma_px, weak_sigma_m)


def _nearest_filled(rows: np.ndarray) -> np.ndarray | None:
    """(N, 3) ``rows`` with each row holding a NaN replaced by the nearest finite row
    (by index); None when no row is finite."""
    seen = np.flatnonzero(np.all(np.isfinite(rows), axis=1))
    if len(seen) == 0:
        return None
    missing = np.flatnonzero(~np.all(np.isfinite(rows), axis=1))
    if len(missing):
        rows = rows.copy()
        nearest = seen[np.abs(seen[None, :] - missing[:, None]).argmin(axis=1)]
        rows[missing] = rows[nearest]
    return rows


def _with_share(method: Method, share_var: np.ndarray, weak_sigma_m: float) -> Method:
    """``method`` with (N, 3) variances [m^2] added to its position sigmas; an ``ok``
    pose whose worst axis then exceeds ``weak_sigma_m`` becomes ``weak``."""
    sigma = np.sqrt(np.asarray(method.sigma_xyz, float) ** 2 + share_var)
    worst = np.max(sigma, axis=1)
    status = tuple(
        PoseStatus.WEAK if st is PoseStatus.OK and not w <= weak_sigma_m else st
        for st, w in zip(method.status, worst, strict=True)
    )
    return replace(method, sigma_xyz=sigma, status=status)
