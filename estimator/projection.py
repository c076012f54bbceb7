"""Pinhole projection of world points and its Jacobian with respect to the camera pose.

Pixels are undistorted (``estimator.camera.undistort_px``), so the model is
``uv = K pi(cam_R_world (world_p - world_t_cam))`` with the full K (skew
K[0, 1] included, as ``undistort_px`` keeps it). Pose perturbations follow
gtsam's ``Pose3`` convention: ``world_T_cam * Exp(xi)`` with
``xi = [omega, v]`` (rotation first, both in the camera frame), so a 6x6
covariance from gtsam and the Jacobians here share one order.

Also the chi-square quantile for even degrees of freedom (residuals come in
pixel pairs), written out to avoid a scipy dependency.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from signpose.estimator.camera import CameraModel

MIN_DEPTH_M = 1e-9  # depths are clamped to this to keep points at the camera finite
# Fisher information with a larger condition number leaves a direction unfixed
# (three points on a line, or two points): no covariance then.
MAX_CONDITION = 1e12


def cam_points(world_T_cam: np.ndarray, world_p: np.ndarray) -> np.ndarray:
    """(K, 3) points in the camera frame [m] from (K, 3) world points and one (4, 4) pose."""
    return (world_p - world_T_cam[:3, 3]) @ world_T_cam[:3, :3]


def pixel_from_normalised(camera: CameraModel, xy: np.ndarray) -> np.ndarray:
    """(N, 2) undistorted pixels of (N, 2) normalised coordinates (x/z, y/z): the full K.

    The skew K[0, 1] is part of K, as in ``estimator.camera.undistort_px``:
    u = fx * x + s * y + cx, v = fy * y + cy.
    """
    K = camera.K
    x, y = xy[:, 0], xy[:, 1]
    return np.stack([K[0, 0] * x + K[0, 1] * y + K[0, 2], K[1, 1] * y + K[1, 2]], axis=1)


def pixels_and_jacobians(
    camera: CameraModel, world_T_cam: np.ndarray, world_p: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projected pixels and their Jacobians, one pose per point.

    Args:
        camera: the camera (only K is used, its skew K[0, 1] included).
        world_T_cam: (K, 4, 4) the pose each point is seen from.
        world_p: (K, 3) world points [m].

    Returns:
        ((K, 2) undistorted pixels, (K, 2, 6) d(pixel)/d(xi) for the pose
        perturbation xi = [omega, v], (K, 2, 3) d(pixel)/d(world point)).
    """
    R, t = world_T_cam[:, :3, :3], world_T_cam[:, :3, 3]
    pc = np.einsum("kji,kj->ki", R, np.asarray(world_p, float).reshape(-1, 3) - t)
    x, y = pc[:, 0], pc[:, 1]
    z = np.maximum(pc[:, 2], MIN_DEPTH_M)
    uv = pixel_from_normalised(camera, np.stack([x / z, y / z], axis=1))
    # uv = K[:2] (x/z, y/z, 1): the skew K[0, 1] couples u to y.
    K = camera.K
    d_pi = np.zeros((len(pc), 2, 3))
    d_pi[:, 0, 0] = K[0, 0] / z
    d_pi[:, 0, 1] = K[0, 1] / z
    d_pi[:, 0, 2] = -(K[0, 0] * x + K[0, 1] * y) / z**2
    d_pi[:, 1, 1] = K[1, 1] / z
    d_pi[:, 1, 2] = -K[1, 1] * y / z**2
    # p_cam(xi) = Exp(-omega) (p_cam - v): d/d omega = [p_cam]x, d/dv = -I.
    skew = np.zeros((len(pc), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2] = -pc[:, 2], pc[:, 1]
    skew[:, 1, 0], skew[:, 1, 2] = pc[:, 2], -pc[:, 0]
    skew[:, 2, 0], skew[:, 2, 1] = -pc[:, 1], pc[:, 0]
    d_pose = np.concatenate([d_pi @ skew, -d_pi], axis=2)
    d_point = np.einsum("kab,kcb->kac", d_pi, R)  # d_pi R^T
    return uv, d_pose, d_point


def pixels_and_pose_jacobian(
    camera: CameraModel, world_T_cam: np.ndarray, world_p: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``pixels_and_jacobians`` with one (4, 4) pose for all (K, 3) points."""
    world_p = np.asarray(world_p, float).reshape(-1, 3)
    poses = np.broadcast_to(world_T_cam, (len(world_p), 4, 4))
    return pixels_and_jacobians(camera, poses, world_p)


def pose_information(
    camera: CameraModel, world_T_cam: np.ndarray, world_p: np.ndarray, sigma_px: np.ndarray
) -> np.ndarray:
    """(6, 6) Fisher information of one pose from keypoints with known world positions.

    Args:
        world_p: (K, 3) world points [m]; sigma_px: (K,) pixel sigma of each, or
            (K, 2) per image axis (u, v).
    """
    _, J, _ = pixels_and_pose_jacobian(camera, world_T_cam, world_p)
    if is_covariance(sigma_px):
        return np.einsum("kai,kab,kbj->ij", J, information_blocks(sigma_px), J)
    w = 1.0 / axis_sigmas(sigma_px, len(J)) ** 2
    return np.einsum("ka,kai,kaj->ij", w, J, J)


def axis_sigmas(sigma_px: np.ndarray, k: int) -> np.ndarray:
    """(K, 2) per-axis pixel sigmas from (K,) isotropic or (K, 2) per-axis ones,
    or the marginal sigmas of (K, 2, 2) covariances."""
    sp = np.asarray(sigma_px, float)
    if sp.ndim == 3:
        return np.sqrt(np.stack([sp[:, 0, 0], sp[:, 1, 1]], axis=1))
    return np.repeat(sp.reshape(-1, 1), 2, axis=1) if sp.size == k else sp.reshape(k, 2)


# Pixel noise comes as (K,) isotropic sigmas, (K, 2) per-axis sigmas or, through
# a lens (its Jacobian correlates the axes: ``camera.undistorted_cov``), as
# (K, 2, 2) covariances [px^2]; the functions here take any of the three.


def is_covariance(sigma_px: np.ndarray) -> bool:
    """True for (K, 2, 2) pixel covariances (else per-axis or isotropic sigmas)."""
    return np.ndim(sigma_px) == 3


def information_blocks(cov: np.ndarray) -> np.ndarray:
    """(K, 2, 2) inverses of (K, 2, 2) pixel covariances (closed form)."""
    c = np.asarray(cov, float)
    det = c[:, 0, 0] * c[:, 1, 1] - c[:, 0, 1] * c[:, 1, 0]
    out = np.empty_like(c)
    out[:, 0, 0], out[:, 1, 1] = c[:, 1, 1] / det, c[:, 0, 0] / det
    out[:, 0, 1], out[:, 1, 0] = -c[:, 0, 1] / det, -c[:, 1, 0] / det
    return out


def whitened(residual_px: np.ndarray, sigma_px: np.ndarray) -> np.ndarray:
    """(K, 2) residuals whitened by their pixel noise: ``r / sigma`` per axis, or
    ``L^-1 r`` with ``L L^T`` a (K, 2, 2) covariance (its Cholesky factor, closed
    form), so that the squares sum to ``r^T Sigma^-1 r``."""
    r = np.asarray(residual_px, float).reshape(-1, 2)
    if not is_covariance(sigma_px):
        return r / axis_sigmas(sigma_px, len(r))
    c = np.asarray(sigma_px, float)
    l11 = np.sqrt(c[:, 0, 0])
    l21 = c[:, 1, 0] / l11
    l22 = np.sqrt(c[:, 1, 1] - l21**2)
    w0 = r[:, 0] / l11
    return np.stack([w0, (r[:, 1] - l21 * w0) / l22], axis=1)


def weigher(sigma_px: np.ndarray, k: int):
    """``y -> W y`` for (2K,) or (2K, m) y, W the pixels' (2K, 2K) inverse covariance."""
    if is_covariance(sigma_px):
        blocks = information_blocks(sigma_px)

        def weigh_blocks(y: np.ndarray) -> np.ndarray:
            return (blocks @ y.reshape(k, 2, -1)).reshape(y.shape)

        return weigh_blocks
    w = 1.0 / axis_sigmas(sigma_px, k).reshape(-1) ** 2

    def weigh(y: np.ndarray) -> np.ndarray:
        return w[:, None] * y if y.ndim == 2 else w * y

    return weigh


def position_cov_world(cov6: np.ndarray, world_R_cam: np.ndarray) -> np.ndarray:
    """(3, 3) world-frame position covariance from a (6, 6) [rot, trans] camera-frame one."""
    return world_R_cam @ cov6[3:, 3:] @ world_R_cam.T


def chi2_survival_even(x: float, dof: int) -> float:
    """P(chi2 > x) for an even number of degrees of freedom (closed form)."""
    half = 0.5 * x
    term, total = 1.0, 1.0
    for i in range(1, dof // 2):
        term *= half / i
        total += term
    return math.exp(-half) * total


@functools.lru_cache(maxsize=1024)
def chi2_quantile_even(p: float, dof: int) -> float:
    """x with P(chi2 <= x) = p, for even ``dof`` (bisection on the closed form; cached)."""
    if dof % 2 or dof <= 0:
        raise ValueError(f"dof must be even and positive, got {dof}")
    tail = 1.0 - p
    lo, hi = 0.0, float(dof)
    while chi2_survival_even(hi, dof) > tail:
        hi *= 2.0
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if chi2_survival_even(mid, dof) > tail:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def pose_covariance(
    camera: CameraModel,
    world_T_cam: np.ndarray,
    world_p: np.ndarray,
    sigma_px: np.ndarray,
    sigma_m: np.ndarray,
    sign_id: np.ndarray | None = None,
) -> np.ndarray | None:
    """(6, 6) covariance of a pose fixed by its keypoints alone (inverse Fisher information).

    The pixels' covariance is the pixel noise plus the survey noise seen
    through the projection. With ``sign_id`` the survey error is a rigid
    shift of each sign (shared by its keypoints, as a survey of the sign's
    centre gives it); without, every keypoint's is independent.

    Args:
        world_p: (K, 3) world points [m]; sigma_px: (K,) pixel sigmas, or (K, 2)
        per image axis; sigma_m: (K,) survey sigmas [m]; sign_id: (K,) sign of
        each point, or None.

    Returns:
        The covariance ([rotation, translation], camera frame), or None when
        the keypoints do not fix all six degrees of freedom.
    """
    k = len(world_p)
    if k < 3:
        return None
    _, J, J_point = pixels_and_pose_jacobian(camera, world_T_cam, world_p)
    sm = np.asarray(sigma_m, float).reshape(-1)
    same = np.eye(k, dtype=bool) if sign_id is None else sign_id[:, None] == sign_id[None, :]
    # (2K, 2K): blocks J_a sigma^2 J_b^T between keypoints a, b of one sign.
    survey = (
        np.einsum("aij,bkj->aibk", J_point, J_point)
        * (same * sm[:, None] * sm[None, :])[:, None, :, None]
    )
    C = survey.reshape(2 * k, 2 * k)
    if is_covariance(sigma_px):
        idx = np.arange(k)
        C4 = C.reshape(k, 2, k, 2)
        C4[idx, :, idx, :] += np.asarray(sigma_px, float)
    else:
        C = C + np.diag(axis_sigmas(sigma_px, k).reshape(-1) ** 2)
    Jf = J.reshape(2 * k, 6)
    info = Jf.T @ np.linalg.solve(C, Jf)
    if np.linalg.cond(info) > MAX_CONDITION:
        return None
    return np.linalg.inv(info)


@dataclass(frozen=True)
class PoseFit:
    """How a frame's keypoints fix and fit a pose estimated with pixel weights.

    The pose is the weighted least-squares one (each residual axis weighted
    by its pixel sigma, the map taken as given). Its error has two parts:
    the pixel noise, independent from frame to frame, and the survey error
    of the signs it sees, the same for every frame that sees those signs
    (correlated over the flight). Both are propagated through the same
    estimator (a sandwich, not the inverse information of a weighting the
    estimate did not use).

    Attributes:
        cov6_pixel: (6, 6) covariance from the pixel noise alone ([rotation,
            translation], camera frame), or None when the keypoints do not
            fix all six degrees of freedom.
        cov6_survey: (6, 6) the survey error's share (zero for an exact map), or None.
        chi2_pixel: the residuals whitened by the pixel sigmas, squared and
            summed (chi-square with 2K - 6 dof when the map is exact).
        chi2_map: the residuals' chi-square with the survey noise too: for the
            pixel-weighted pose, the generalised least-squares refit of its
            residuals with the pixel plus survey covariance (chi-square with
            2K - 6 dof when both the pixel sigmas and the survey sigmas are
            right); for another pose (``optimal=False``) the residuals at it,
            unrefitted, so that a wrong pose fails the test.
    """

    cov6_pixel: np.ndarray | None
    cov6_survey: np.ndarray | None
    chi2_pixel: float
    chi2_map: float

    @property
    def cov6(self) -> np.ndarray | None:
        """(6, 6) total covariance: pixel noise and the survey error, or None."""
        if self.cov6_pixel is None or self.cov6_survey is None:
            return None
        return self.cov6_pixel + self.cov6_survey


def survey_columns(
    J_point: np.ndarray, sigma_m: np.ndarray, sign_id: np.ndarray | None
) -> np.ndarray:
    """(2K, 3S) how the survey errors move the pixels, in units of their sigma.

    Column block s is the pixels' Jacobian with respect to a shift of sign s
    (rigid: shared by its keypoints) times its survey sigma; without
    ``sign_id`` every keypoint is its own sign.

    Args:
        J_point: (K, 2, 3) d(pixel)/d(world point); sigma_m: (K,) survey sigma [m];
        sign_id: (K,) sign index of each keypoint (0..S-1), or None.
    """
    k = len(J_point)
    sid = np.arange(k) if sign_id is None else np.asarray(sign_id, np.int64).reshape(-1)
    n_signs = int(sid.max()) + 1 if k else 0
    G = np.zeros((k, 2, n_signs, 3))
    sm = np.asarray(sigma_m, float).reshape(-1)
    G[np.arange(k), :, sid, :] = J_point * sm[:, None, None]
    return G.reshape(2 * k, 3 * n_signs)


def pose_fit(
    camera: CameraModel,
    world_T_cam: np.ndarray,
    world_p: np.ndarray,
    residual_px: np.ndarray,
    sigma_px: np.ndarray,
    sigma_m: np.ndarray,
    sign_id: np.ndarray | None = None,
    optimal: bool = True,
) -> PoseFit:
    """Covariances and chi-squares of a pose fitted to its keypoints with pixel weights.

    Args:
        camera: the camera the pixels are of (its K, skew included).
        world_T_cam: (4, 4) the pose.
        world_p: (K, 3) world points [m].
        residual_px: (K, 2) observed minus projected pixels at the pose.
        sigma_px: (K,) or (K, 2) pixel sigmas (per image axis), or (K, 2, 2)
            pixel covariances [px^2].
        sigma_m: (K,) survey sigmas [m] (zeros: an exact map).
        sign_id: (K,) sign of each point (its survey error a rigid shift), or None.
        optimal: the pose minimises the pixel-weighted residuals (PnP); False
            for a pose from elsewhere (the baseline): its chi-squares are then
            of the residuals at it, and its covariances those of the
            pixel-weighted fit it is not.
    """
    k = len(world_p)
    weigh = weigher(sigma_px, k)
    r = np.asarray(residual_px, float).reshape(-1)
    chi2_pixel = float(r @ weigh(r))
    if k < 3:
        return PoseFit(None, None, chi2_pixel, chi2_pixel)
    _, J, J_point = pixels_and_pose_jacobian(camera, world_T_cam, world_p)
    Jf = J.reshape(2 * k, 6)
    info = Jf.T @ weigh(Jf)
    G = survey_columns(J_point, sigma_m, sign_id)
    chi2_map = _chi2_map(Jf if optimal else None, r, weigh, G, chi2_pixel)
    if np.linalg.cond(info) > MAX_CONDITION:
        return PoseFit(None, None, chi2_pixel, chi2_map)
    cov_px = np.linalg.inv(info)
    AG = cov_px @ (Jf.T @ weigh(G))  # (6, 3S): pose error per unit survey error
    cov_sv = AG @ AG.T
    return PoseFit(cov_px, 0.5 * (cov_sv + cov_sv.T), chi2_pixel, chi2_map)


def _chi2_map(Jf: np.ndarray | None, r: np.ndarray, weigh, G: np.ndarray, chi2: float) -> float:
    """min over xi of (r - J xi)^T C^-1 (r - J xi), C = W^-1 + G G^T (Woodbury).

    ``weigh``: y -> W y, W the pixels' inverse covariance (``weigher``).

    The residuals of a pixel-weighted fit refitted by generalised least
    squares: the same as the generalised least-squares residuals of the
    data, whatever weights the first fit used (both remove J's column space).
    ``Jf`` None: no refit, r^T C^-1 r.
    """
    if G.size == 0 or not np.any(G):
        return chi2
    wG = weigh(G)
    M = np.eye(G.shape[1]) + G.T @ wG

    def c_inv(y: np.ndarray) -> np.ndarray:  # C^-1 y by Woodbury
        wy = weigh(y)
        return wy - wG @ np.linalg.solve(M, G.T @ wy)

    try:
        ci_r = c_inv(r)
        if Jf is None:
            return float(r @ ci_r)
        g = Jf.T @ ci_r
        return float(r @ ci_r - g @ np.linalg.solve(Jf.T @ c_inv(Jf), g))
    except np.linalg.LinAlgError:
        return float("nan")
