"""Camera model: intrinsics, lens distortion, projection and undistortion.

The undistortion's Jacobian (``undistort_px_jacobian``) carries a raw-pixel
keypoint sigma into the undistorted image (``undistorted_cov``: the lens
stretches and correlates the axes; ``undistorted_sigmas``: the marginals).

Camera frame: OpenCV's and gtsam's, x right, y down, z forward (optical axis).
Pixels: u right, v down, pixel centres at integer coordinates.

Calibration files are read and written by ``signpose.io.camera_file``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from signpose.core.errors import InputError

PLUMB_BOB = "plumb_bob"
EQUIDISTANT = "equidistant"


@dataclass(frozen=True)
class CameraModel:
    """A calibrated pinhole camera with lens distortion.

    Attributes:
        width: image width [px].
        height: image height [px].
        K: (3, 3) intrinsic matrix [px].
        dist: distortion coefficients; plumb_bob: (k1, k2, p1, p2[, k3, ...]),
            equidistant: (k1, k2, k3, k4).
        model: ``"plumb_bob"`` or ``"equidistant"``.
        name: camera name (free text).
    """

    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    model: str = PLUMB_BOB
    name: str = "camera"

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(np.abs(self.dist) > 0))

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) [px]."""
        return (self.width, self.height)


def pinhole_camera(
    width: int = 1920, height: int = 1080, hfov_deg: float = 60.0, name: str = "camera"
) -> CameraModel:
    """An ideal pinhole camera with square pixels and the principal point centred."""
    f = (width / 2.0) / np.tan(np.radians(hfov_deg) / 2.0)
    K = np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])
    return CameraModel(width, height, K, np.zeros(5), PLUMB_BOB, name)


def pixel_from_cam_point(camera: CameraModel, cam_points: np.ndarray) -> np.ndarray:
    """Project points given in the camera frame to raw (distorted) pixels.

    Args:
        camera: the camera.
        cam_points: (N, 3) points in the camera frame [m], z > 0.

    Returns:
        (N, 2) raw pixel coordinates.
    """
    pts = np.asarray(cam_points, dtype=np.float64).reshape(-1, 1, 3)
    if len(pts) == 0:
        return np.zeros((0, 2))
    rvec = np.zeros(3)
    tvec = np.zeros(3)
    skew = float(camera.K[0, 1])
    if camera.model == EQUIDISTANT:
        out, _ = cv2.fisheye.projectPoints(
            pts, rvec, tvec, _without_skew(camera.K), camera.dist[:4], alpha=skew / camera.fx
        )
        return out.reshape(-1, 2)
    # cv2.projectPoints reads only fx, fy, cx, cy: add the skew term s * y_d.
    out, _ = cv2.projectPoints(pts, rvec, tvec, _without_skew(camera.K), camera.dist)
    px = out.reshape(-1, 2)
    if skew != 0.0:
        px[:, 0] += skew * (px[:, 1] - camera.cy) / camera.fy
    return px


def _without_skew(K: np.ndarray) -> np.ndarray:
    """K with K[0, 1] = 0 (the part of K that OpenCV's distortion functions read)."""
    K0 = np.array(K, dtype=np.float64)
    K0[0, 1] = 0.0
    return K0


def pixel_from_world_point(
    camera: CameraModel, world_T_cam: np.ndarray, world_points: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Project world points into the image.

    Args:
        camera: the camera.
        world_T_cam: (4, 4) camera pose in the world frame.
        world_points: (N, 3) points in the world frame [m].

    Returns:
        ((N, 2) raw pixels, (N,) depth along the optical axis [m]). Pixels of
        points behind the camera (depth <= 0) are NaN.
    """
    P = np.asarray(world_points, dtype=float).reshape(-1, 3)
    cam_T_world = np.linalg.inv(world_T_cam)
    cam_pts = P @ cam_T_world[:3, :3].T + cam_T_world[:3, 3]
    depth = cam_pts[:, 2].copy()
    px = np.full((len(P), 2), np.nan)
    front = depth > 1e-6
    if np.any(front):
        px[front] = pixel_from_cam_point(camera, cam_pts[front])
    return px, depth


def undistort_px(camera: CameraModel, pixels: np.ndarray) -> np.ndarray:
    """Raw pixels to the ideal pinhole image with the same K (``cv2.undistortPoints``).

    The skew K[0, 1] is part of the lens model on both sides, as in
    ``pixel_from_cam_point``: raw u = fx * x_d + s * y_d + cx. OpenCV's
    undistortion reads only fx, fy, cx, cy of its input matrix, so the skew term
    is taken off the raw pixels first; the output uses the full K.

    Args:
        pixels: (N, 2) raw pixel coordinates.

    Returns:
        (N, 2) pixel coordinates as an undistorted pinhole camera with
        intrinsics ``camera.K`` (skew included) would see them.
    """
    pts = np.asarray(pixels, dtype=np.float64).reshape(-1, 1, 2)
    if len(pts) == 0 or not camera.has_distortion:
        return pts.reshape(-1, 2).copy()
    skew = float(camera.K[0, 1])
    if skew != 0.0:
        pts = pts.copy()
        pts[:, 0, 0] -= skew * (pts[:, 0, 1] - camera.cy) / camera.fy
    K0 = _without_skew(camera.K)
    if camera.model == EQUIDISTANT:
        out = cv2.fisheye.undistortPoints(pts, K0, camera.dist[:4], P=camera.K)
    else:
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-9)
        out = cv2.undistortPointsIter(pts, K0, camera.dist, None, camera.K, crit)
    return out.reshape(-1, 2)


# A raw pixel whose undistorted point projects back further than this is one
# the lens model does not describe (a fisheye's ray at 90 deg or more, which no
# pinhole image holds; a polynomial that folds beyond its calibrated radius, where
# the iteration finds no inverse): the converged points miss by < 1e-9 px.
MAX_ROUND_TRIP_PX = 0.01


def undistort_px_jacobian(
    camera: CameraModel, pixels: np.ndarray
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Raw pixels undistorted (``undistort_px``), the lens's Jacobian there, and where valid.

    ``J = d(undistorted pixel) / d(raw pixel)`` per point: a keypoint's
    covariance in the undistorted image is ``J Sigma_raw J^T``. It is the
    inverse of the projection's Jacobian at the undistorted point, which is
    closed-form for both lens models (no iteration): ``d raw / d x_n`` by
    central differences of ``pixel_from_cam_point`` at ``x_n = K^-1 q``, and
    ``J = K_2 (d raw / d x_n)^-1`` with ``K_2`` the upper 2 x 2 of K (skew
    included, as ``undistort_px`` keeps it).

    A point is valid when its undistorted point projects back onto it (within
    ``MAX_ROUND_TRIP_PX``) and the projection does not fold there (its
    Jacobian's determinant > 0); elsewhere the undistorted pixel is not the
    keypoint's and must not be used (its J is the identity, a placeholder).

    Args:
        pixels: (N, 2) raw pixel coordinates.

    Returns:
        ((N, 2) undistorted pixels, (N, 2, 2) Jacobians, (N,) valid); the
        Jacobians and validity None for a camera without distortion (the
        identity, every point valid: nothing to carry).
    """
    und = undistort_px(camera, pixels)
    if not camera.has_distortion or len(und) == 0:
        return und, None, None
    K2 = np.asarray(camera.K, float)[:2, :2]
    xy = np.linalg.solve(K2, (und - camera.K[:2, 2]).T).T  # normalised, z = 1
    n = len(xy)
    h = 1e-6 * np.maximum(1.0, np.abs(xy))  # (N, 2); ~1e-3 px at f = 1000 px
    pts = np.ones((5, n, 3))
    pts[:, :, :2] = xy
    pts[1, :, 0] += h[:, 0]
    pts[2, :, 0] -= h[:, 0]
    pts[3, :, 1] += h[:, 1]
    pts[4, :, 1] -= h[:, 1]
    with np.errstate(invalid="ignore", over="ignore"):
        raw = pixel_from_cam_point(camera, pts.reshape(-1, 3)).reshape(5, n, 2)
        D = np.empty((n, 2, 2))  # d raw / d (x_n, y_n)
        D[:, :, 0] = (raw[1] - raw[2]) / (2 * h[:, :1])
        D[:, :, 1] = (raw[3] - raw[4]) / (2 * h[:, 1:])
        det = D[:, 0, 0] * D[:, 1, 1] - D[:, 0, 1] * D[:, 1, 0]
        miss = np.linalg.norm(raw[0] - np.asarray(pixels, float).reshape(-1, 2), axis=1)
    valid = np.isfinite(det) & (det > 0) & (miss <= MAX_ROUND_TRIP_PX)
    valid &= np.all(np.isfinite(D.reshape(n, 4)), axis=1)
    D[~valid] = np.eye(2)
    det = np.where(valid, det, 1.0)
    inv = np.empty_like(D)
    inv[:, 0, 0], inv[:, 1, 1] = D[:, 1, 1] / det, D[:, 0, 0] / det
    inv[:, 0, 1], inv[:, 1, 0] = -D[:, 0, 1] / det, -D[:, 1, 0] / det
    J = K2 @ inv
    J[~valid] = np.eye(2)
    return und, J, valid


def undistorted_cov(jac: np.ndarray, sigma_uv: np.ndarray) -> np.ndarray:
    """(N, 2, 2) covariances [px^2] in the undistorted image: ``J diag(su^2, sv^2) J^T``."""
    s = np.asarray(sigma_uv, dtype=float).reshape(-1, 2)
    return np.einsum("nia,na,nja->nij", jac, s**2, jac)


def undistorted_sigmas(jac: np.ndarray | None, sigma_uv: np.ndarray) -> np.ndarray:
    """(N, 2) per-axis sigmas [px] of raw-pixel sigmas carried into the undistorted image.

    ``sqrt(diag(J diag(sigma_u^2, sigma_v^2) J^T))``: each axis's marginal
    sigma (``undistorted_cov`` keeps the correlation too). ``jac`` None (no
    distortion): ``sigma_uv`` itself.
    """
    s = np.asarray(sigma_uv, dtype=float).reshape(-1, 2)
    if jac is None:
        return s
    return np.sqrt(np.einsum("nij,nj->ni", jac**2, s**2))


# --------------------------------------------------------------------------- files


def check_image_size(camera: CameraModel, width: int, height: int, source: str) -> None:
    """Raise InputError when the images are not the size the camera was calibrated for."""
    if (int(width), int(height)) != (camera.width, camera.height):
        raise InputError(
            f"{source}: images are {width}x{height} but the camera file says "
            f"{camera.width}x{camera.height}; pass the calibration of this camera"
        )
