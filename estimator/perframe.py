"""Per-frame camera poses: the paper's homography method (§3, Eqs. 7-13) and PnP.

Both work on one frame at a time and never raise for a bad frame: they
return a ``FramePose`` with ``world_T_cam=None`` and a reason instead.

Conventions: ``world_T_cam`` is (4, 4), the camera axes are OpenCV's
(x right, y down, z forward); pixels are undistorted with
``estimator.camera.undistort_px`` before any pose math, and the decoder's
raw-pixel sigmas carried with them through the lens's Jacobian
(``camera.undistort_px_jacobian``): a barrel lens or a fisheye stretches the
image's edges, and a keypoint there is less certain in undistorted pixels
(a full 2 x 2 covariance: the stretch is radial, so it correlates u and v).
"""

from __future__ import annotations

import contextlib
import enum
import pickle
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from signpose.estimator.camera import (
    CameraModel,
    undistort_px_jacobian,
    undistorted_cov,
)
from signpose.estimator.projection import PoseFit, pixels_and_pose_jacobian, pose_fit, weigher
from signpose.frontend.observations import FrameObservations
from signpose.maps.loader import SignMap
from tqdm import tqdm


class PoseFailure(enum.Enum):
    """Why a frame gets no per-frame pose; written to files as its lowercase token."""

    FEW_SIGNS = "few_signs"  # fewer than 4 signs (the paper's method)
    FEW_POINTS = "few_points"  # fewer than 4 keypoints (PnP)
    COLLINEAR = "collinear"  # degenerate geometry: signs collinear
    ONE_SPOT = "one_spot"  # degenerate geometry: signs in one spot
    HOMOGRAPHY = "homography"  # the homography fit failed
    RANSAC = "ransac"  # fewer than 4 RANSAC inliers
    BEHIND = "behind"  # the solution puts signs behind the camera
    SPEED = "speed_gate"  # too far from the previous pose (robustness rule 3)
    PNP = "pnp"  # every PnP candidate failed
    NONFINITE = "nonfinite"  # non-finite solution


_NAN = float("nan")


@dataclass(frozen=True)
class PerFrameSettings:
    """Settings of the per-frame solvers.

    Attributes:
        ransac_px: RANSAC inlier threshold [px] (homography and PnP RANSAC).
        max_speed_mps: speed gate: a pose further than ``max_speed_mps * dt``
            (plus ``gate_slack_m``) from the previous accepted one is rejected.
            0 or less disables the gate.
        gate_slack_m: distance always allowed by the speed gate [m] (noise).
        gate_reset_frames: after this many consecutive gate rejections the
            gate accepts again (otherwise one bad accepted pose would lock the
            gate forever; not in the paper).
        min_spread_m: signs whose centres spread less than this (largest
            singular direction, RMS) are "in one spot" [m].
        min_aspect: second over first principal spread below this => collinear.
        pnp_ransac: run PnP inside RANSAC (solvePnPRansac) before refining.
        planar_tol_m: PnP uses IPPE when all points lie within this of a plane [m].
        warm_start_min_signs: with a prior pose and at least this many signs,
            PnP trusts LM from the prior when every keypoint then fits within
            ``ransac_px`` and skips RANSAC.
        warm_start_max_move_m: ... and only when LM moved the camera less than
            this from the prior [m]. A prior far from the truth (a long gap
            between frames) can lead LM into a wrong minimum that still fits
            within a pixel or two (the lateral-shift/rotation valley of a narrow
            view); the cold RANSAC solve then decides.
    """

    ransac_px: float = 3.0
    max_speed_mps: float = 15.0
    gate_slack_m: float = 0.5
    gate_reset_frames: int = 10
    min_spread_m: float = 0.05
    min_aspect: float = 0.02
    pnp_ransac: bool = True
    planar_tol_m: float = 1e-3
    warm_start_min_signs: int = 4
    warm_start_max_move_m: float = 0.5


@dataclass(frozen=True)
class FramePose:
    """One frame's per-frame pose, or why there is none.

    Attributes:
        frame: frame index.
        stamp_ns: frame time [ns].
        world_T_cam: (4, 4) camera pose in the world, or None.
        reason: None when posed, else why not.
        signs_used: number of distinct map signs that went into the solve.
        inlier_codes: codes of the signs kept (RANSAC inliers).
        rms_px: RMS reprojection error of the inliers [px] (NaN without pose).
        cov6: (6, 6) covariance of the pose from its inlier keypoints alone,
            the pixel noise and the map's survey error propagated through the
            pixel-weighted fit (``projection.pose_fit``; gtsam's order
            [rotation, translation], camera frame), or None.
        keypoints_used: number of inlier keypoints.
        chi2: sum of the inliers' squared residuals whitened by their pixel
            sigmas (NaN without pose).
        cov6_pixel: the pixel noise's share of ``cov6`` (independent from
            frame to frame; the rest, the survey's, is the same error for
            every frame that sees the same signs), or None.
        chi2_map: the residuals' chi-square with the survey noise too
            (``PoseFit.chi2_map``; NaN without pose).
    """

    frame: int
    stamp_ns: int
    world_T_cam: np.ndarray | None
    reason: PoseFailure | None = None
    signs_used: int = 0
    inlier_codes: tuple[str, ...] = field(default_factory=tuple)
    rms_px: float = float("nan")
    cov6: np.ndarray | None = None
    keypoints_used: int = 0
    chi2: float = float("nan")
    cov6_pixel: np.ndarray | None = None
    chi2_map: float = float("nan")


@dataclass(frozen=True)
class _Correspondences:
    codes: list[str]  # one per point
    names: list[str]
    world: np.ndarray  # (N, 3)
    px: np.ndarray  # (N, 2) undistorted pixels (skew-free, see _correspondences)
    sigma_px: np.ndarray  # (N, 2) undistorted-pixel sigma of each point per image axis (u, v)
    sigma_m: np.ndarray  # (N,) survey sigma of each point [m]
    cov_px: np.ndarray | None = None  # (N, 2, 2) their covariance through a lens [px^2]

    @property
    def noise(self) -> np.ndarray:
        """What the fits whiten by: ``cov_px`` through a lens, else ``sigma_px``."""
        return self.sigma_px if self.cov_px is None else self.cov_px

    def fit(
        self,
        camera: CameraModel,
        world_T_cam: np.ndarray,
        inliers: np.ndarray,
        optimal: bool = True,
    ) -> dict:
        """FramePose fields describing how well the inliers fix and fit the pose.

        ``optimal``: the pose is the inliers' pixel-weighted fit (PnP), see
        ``projection.pose_fit``.
        """
        pin = _pinhole(camera)
        uv, _, _ = pixels_and_pose_jacobian(pin, world_T_cam, self.world[inliers])
        sign_id = np.unique(np.asarray(self.codes), return_inverse=True)[1].reshape(-1)
        f: PoseFit = pose_fit(
            pin,
            world_T_cam,
            self.world[inliers],
            self.px[inliers] - uv,
            self.noise[inliers],
            self.sigma_m[inliers],
            sign_id[inliers],
            optimal,
        )
        return {
            "cov6": f.cov6,
            "cov6_pixel": f.cov6_pixel,
            "keypoints_used": int(inliers.sum()),
            "chi2": f.chi2_pixel,
            "chi2_map": f.chi2_map,
        }


def _pinhole(camera: CameraModel) -> CameraModel:
    """The camera without its skew: the model of ``_Correspondences.px``."""
    if camera.K[0, 1] == 0.0:
        return camera
    K = np.array(camera.K, float)
    K[0, 1] = 0.0
    return replace(camera, K=K)


def keypoint_sigmas(obs, name: str) -> tuple[float, float]:
    """(sigma_u, sigma_v) [px] of one keypoint of a sign observation.

    The decoder's per-keypoint, per-axis ``keypoint_sigma_px`` where it gave
    one, but never below the observation's single ``sigma_px`` (which holds
    on both axes where there is none). A keypoint the decoder saw worse than
    its sign (beside an occluder, blurred along one axis) weighs less; one it
    claims better than its sign does not weigh more: on rendered orbits those
    claims were not borne out. Keypoints claimed below 0.8 of their sign's
    sigma erred 0.105 / 0.086 px (u / v) on the hard flights, more than the
    others (0.077-0.10), rms(error / sigma) 1.44 / 1.48 with their own sigma
    against 0.91 / 1.02 with the sign's; the smoother with the exact map
    fixed then had ``ok`` poses beyond 3 sigma 7 -> 24 of ~355 and RMSE z
    7.5 -> 8.8 mm (seeds 5, 6). Above the sign's sigma the keypoint's own is
    the better one (1.33 / 1.37 against 1.61 / 1.68).
    """
    kp = obs.keypoint_sigma_px.get(name)
    if kp is None:
        return (obs.sigma_px, obs.sigma_px)
    return (max(float(kp[0]), obs.sigma_px), max(float(kp[1]), obs.sigma_px))


def _correspondences(
    frame: FrameObservations, sign_map: SignMap, camera: CameraModel, all_keypoints: bool
) -> _Correspondences:
    """Undistorted image points matched to map points; codes absent from the map dropped,
    and keypoints where the lens model holds no inverse (``undistort_px_jacobian``)."""
    codes, names, world, raw, sig_px, sig_m = [], [], [], [], [], []
    for obs in frame.signs:
        sign = sign_map.sign(obs.code)
        if sign is None:  # robustness rule 1: decoded codes absent from the map
            continue
        kw = sign.keypoints_world()
        wanted = kw if all_keypoints else {"center": kw["center"]}
        for name, X in wanted.items():
            if name in obs.keypoints_px:
                codes.append(obs.code)
                names.append(name)
                world.append(X)
                raw.append(obs.keypoints_px[name])
                sig_px.append(keypoint_sigmas(obs, name))
                sig_m.append(sign.sigma_m)
    world_a = np.asarray(world, dtype=float).reshape(-1, 3)
    # The decoder's sigmas are in raw pixels: carried through the lens's
    # Jacobian into the undistorted image the pose math works in.
    px, jac, valid = undistort_px_jacobian(camera, np.asarray(raw, dtype=float).reshape(-1, 2))
    sigma_px = np.asarray(sig_px, float).reshape(-1, 2)
    sigma_m = np.asarray(sig_m, float)
    cov = None
    if jac is not None:  # the lens correlates the axes: the full 2 x 2 covariance
        cov = undistorted_cov(jac, sigma_px)
        sigma_px = np.sqrt(np.stack([cov[:, 0, 0], cov[:, 1, 1]], axis=1))
    if valid is not None and not np.all(valid):  # where the lens model holds no inverse
        keep = np.nonzero(valid)[0].tolist()
        codes, names = [codes[k] for k in keep], [names[k] for k in keep]
        world_a, px, sigma_px, sigma_m, cov = (
            a[valid] for a in (world_a, px, sigma_px, sigma_m, cov)
        )
    # The solvers here read only fx, fy, cx, cy (as cv2.solvePnP does): take the
    # skew term K[0, 1] * y off, so that px is the skew-free pinhole image.
    if camera.K[0, 1] != 0.0:
        px[:, 0] -= camera.K[0, 1] * (px[:, 1] - camera.cy) / camera.fy
    return _Correspondences(codes, names, world_a, px, sigma_px, sigma_m, cov)


def _spread(points: np.ndarray) -> np.ndarray:
    """(3,) RMS spread of the points along their principal directions [m], largest first."""
    centred = points - points.mean(axis=0)
    return np.linalg.svd(centred, compute_uv=False) / np.sqrt(max(len(points), 1))


def _degenerate(sv: np.ndarray, s: PerFrameSettings) -> PoseFailure | None:
    """Why points of spread ``sv`` (see _spread) cannot fix a pose, or None."""
    if sv[0] < s.min_spread_m:
        return PoseFailure.ONE_SPOT
    if sv[1] < s.min_aspect * sv[0] or sv[1] < s.min_spread_m:
        return PoseFailure.COLLINEAR
    return None


def _reproject_errors(
    camera: CameraModel, world_T_cam: np.ndarray, X: np.ndarray, px: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(N,) reprojection error [px] and (N,) depth [m] of world points X."""
    R = world_T_cam[:3, :3]
    Xc = (X - world_T_cam[:3, 3]) @ R
    z = np.where(np.abs(Xc[:, 2]) < 1e-12, 1e-12, Xc[:, 2])
    uv = Xc[:, :2] / z[:, None] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
    return np.linalg.norm(uv - px, axis=1), Xc[:, 2]


def _reproject_rms(
    camera: CameraModel, world_T_cam: np.ndarray, X: np.ndarray, px: np.ndarray
) -> tuple[float, np.ndarray]:
    """RMS reprojection error [px] and (N,) depth [m] of world points X."""
    err, depth = _reproject_errors(camera, world_T_cam, X, px)
    return float(np.sqrt(np.mean(err**2))), depth


def _warm_start(X, x, K, dist, prior_world_T_cam: np.ndarray):
    """(rvec, tvec) from Levenberg-Marquardt started at the prior pose, or None."""
    R0 = prior_world_T_cam[:3, :3].T
    rvec0, _ = cv2.Rodrigues(R0)
    tvec0 = (-R0 @ prior_world_T_cam[:3, 3]).reshape(3, 1)
    try:
        rvec, tvec = cv2.solvePnPRefineLM(X, x, K, dist, rvec0.copy(), tvec0.copy())
    except cv2.error:
        return None
    if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return None
    return np.asarray(rvec, float).reshape(3, 1), np.asarray(tvec, float).reshape(3, 1)


def _orthonormal(R: np.ndarray) -> np.ndarray:
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def _pose_from_rt(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """world_T_cam from x_cam = R X + t; Eq. (13): C = -R^T t."""
    T = np.eye(4)
    T[:3, :3] = R.T
    T[:3, 3] = -R.T @ t
    return T


def pose_from_homography(
    world_points: np.ndarray, normalised_px: np.ndarray, ransac_thresh: float
) -> tuple[np.ndarray | None, np.ndarray, PoseFailure | None]:
    """The paper's Eqs. (7)-(13) on matched map and image points.

    Args:
        world_points: (N, 3) map points [m], N >= 4, roughly coplanar.
        normalised_px: (N, 2) undistorted image points with K^-1 applied.
        ransac_thresh: RANSAC reprojection threshold in normalised units.

    Returns:
        (world_T_cam or None, (N,) inlier mask, why not or None).
    """
    M = np.asarray(world_points, dtype=float)
    m_c = M.mean(axis=0)  # step (1)
    M_t = (M - m_c).T @ (M - m_c)  # Eq. (7)
    _, _, V = np.linalg.svd(M_t)  # Eq. (8): M_t = U W V (numpy's vh is the paper's V)
    R_t = V
    if np.linalg.det(R_t) < 0:  # fix-up: make R_t a rotation so that R below is one
        R_t = R_t * np.array([1.0, 1.0, -1.0])[:, None]
    # Eq. (9) fix-up: with column vectors T_t = -R_t m_c (the paper writes -m_c R_t
    # for row vectors), so M_xy = R_t X + T_t has its third coordinate ~ 0.
    T_t = -R_t @ m_c
    M_xy = M @ R_t.T + T_t
    H, mask = cv2.findHomography(
        M_xy[:, :2].reshape(-1, 1, 2),
        np.asarray(normalised_px, dtype=float).reshape(-1, 1, 2),
        cv2.RANSAC,
        ransac_thresh,
        maxIters=2000,
        confidence=0.999,
    )  # step (4), Eq. (10): H = [h1 h2 t']
    if H is None or not np.all(np.isfinite(H)):
        return None, np.zeros(len(M), bool), PoseFailure.HOMOGRAPHY
    inliers = mask.reshape(-1).astype(bool)
    if inliers.sum() < 4:
        return None, inliers, PoseFailure.RANSAC
    # Sign ambiguity: H is defined up to scale, including -1. The plane origin
    # (the centroid, at t') must be in front of the camera: t'_z > 0.
    if H[2, 2] < 0:
        H = -H
    h1, h2, tp = H[:, 0], H[:, 1], H[:, 2]
    n1, n2 = np.linalg.norm(h1), np.linalg.norm(h2)
    # Eq. (11). Fix-up: the scale of t' is the mean column norm, (|h1| + |h2|) / 2;
    # the paper's divisor |h1| + |h2| would halve the distance.
    h1, h2 = h1 / n1, h2 / n2
    tp = tp / ((n1 + n2) / 2.0)
    h3 = np.cross(h1, h2)
    # Fix-up: with noise h1 and h2 are not orthogonal; take the nearest rotation.
    R_plane = _orthonormal(np.stack([h1, h2, h3], axis=1))
    R = R_plane @ R_t  # Eq. (12)
    t = R_plane @ T_t + tp
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return None, inliers, PoseFailure.NONFINITE
    return _pose_from_rt(R, t), inliers, None


class BaselineTracker:
    """The paper's per-frame positioning with its three robustness rules.

    Holds the previous accepted position for the speed gate (rule 3); feed
    frames in time order with ``solve``.
    """

    def __init__(self, sign_map: SignMap, camera: CameraModel, settings: PerFrameSettings):
        self.sign_map = sign_map
        self.camera = camera
        self.settings = settings
        self._prev_pos: np.ndarray | None = None
        self._prev_stamp_ns = 0
        self._rejections = 0

    def solve(self, frame: FrameObservations) -> FramePose:
        pose = solve_frame_baseline(frame, self.sign_map, self.camera, self.settings)
        if pose.world_T_cam is None:
            return pose
        s = self.settings
        if s.max_speed_mps > 0 and self._prev_pos is not None:
            dt = abs(frame.stamp_ns - self._prev_stamp_ns) * 1e-9
            jump = float(np.linalg.norm(pose.world_T_cam[:3, 3] - self._prev_pos))
            if (
                jump > s.max_speed_mps * dt + s.gate_slack_m
                and self._rejections < s.gate_reset_frames
            ):
                self._rejections += 1
                return replace(pose, world_T_cam=None, reason=PoseFailure.SPEED, rms_px=_NAN)
        self._rejections = 0
        self._prev_pos = pose.world_T_cam[:3, 3].copy()
        self._prev_stamp_ns = frame.stamp_ns
        return pose


def solve_frame_baseline(
    frame: FrameObservations,
    sign_map: SignMap,
    camera: CameraModel,
    settings: PerFrameSettings | None = None,
) -> FramePose:
    """The paper's method on one frame (sign centres only; no speed gate, see BaselineTracker)."""
    s = settings or PerFrameSettings()
    c = _correspondences(frame, sign_map, camera, all_keypoints=False)
    distinct = sorted(set(c.codes))

    def failed(reason: PoseFailure, used: tuple[str, ...] = ()) -> FramePose:
        n_used = len(used) if used else len(distinct)
        return FramePose(
            frame=frame.frame,
            stamp_ns=frame.stamp_ns,
            world_T_cam=None,
            reason=reason,
            signs_used=n_used,
            inlier_codes=used,
        )

    if len(distinct) < 4:
        return failed(PoseFailure.FEW_SIGNS)
    reason = _degenerate(_spread(c.world), s)
    if reason is not None:
        return failed(reason)
    normalised = (c.px - [camera.cx, camera.cy]) / [camera.fx, camera.fy]  # K^-1 applied
    T, inliers, reason = pose_from_homography(c.world, normalised, s.ransac_px / camera.fx)
    if T is None:
        return failed(reason or PoseFailure.HOMOGRAPHY)
    used = tuple(sorted({code for code, ok in zip(c.codes, inliers, strict=True) if ok}))
    rms, depth = _reproject_rms(camera, T, c.world[inliers], c.px[inliers])
    if np.any(depth <= 0):
        return failed(PoseFailure.BEHIND, used)
    return FramePose(
        frame=frame.frame,
        stamp_ns=frame.stamp_ns,
        world_T_cam=T,
        signs_used=len(used),
        inlier_codes=used,
        rms_px=rms,
        **c.fit(camera, T, inliers, optimal=False),
    )


@dataclass(frozen=True)
class _PnPProblem:
    """One frame's PnP inputs in OpenCV's layout."""

    c: _Correspondences
    spread: np.ndarray  # (3,) see _spread
    K: np.ndarray  # (3, 3)
    X: np.ndarray  # (N, 1, 3) world points [m]
    x: np.ndarray  # (N, 1, 2) undistorted pixels

    @property
    def dist(self) -> np.ndarray:
        return np.zeros(5)  # pixels are undistorted already


def _warm_candidate(
    p: _PnPProblem, camera: CameraModel, prior_world_T_cam: np.ndarray, s: PerFrameSettings
) -> tuple[tuple[np.ndarray, np.ndarray] | None, bool]:
    """LM from the prior on all points: (rvec, tvec) or None, and whether it is the answer.

    When every point then reprojects within the RANSAC threshold, RANSAC would
    keep them all and end in the same LM refinement, so it is skipped (~10x
    cheaper). Only with several signs: one or two nearly coplanar signs have a
    second, mirrored minimum that LM from a distant prior can fall into.
    """
    warm = _warm_start(p.X, p.x, p.K, p.dist, prior_world_T_cam)
    if warm is None:
        return None, False
    rvec, tvec = warm
    T = _pose_from_rt(cv2.Rodrigues(rvec)[0], tvec.reshape(3))
    err, depth = _reproject_errors(camera, T, p.c.world, p.c.px)
    accept = (
        len(set(p.c.codes)) >= s.warm_start_min_signs
        and np.linalg.norm(T[:3, 3] - prior_world_T_cam[:3, 3]) < s.warm_start_max_move_m
        and np.all(depth > 0)
        and np.all(np.isfinite(err))
        and err.max() < s.ransac_px
    )
    return warm, bool(accept)


def _cold_candidates(
    p: _PnPProblem, s: PerFrameSettings
) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray]:
    """RANSAC SQPnP (six points or more), else IPPE (planar) or SQPnP: candidates and inliers."""
    n = len(p.c.world)
    inliers = np.ones(n, bool)
    candidates: list[tuple[np.ndarray, np.ndarray]] = []
    try:
        if s.pnp_ransac and n >= 6:
            ok, rvec, tvec, idx = cv2.solvePnPRansac(
                p.X, p.x, p.K, p.dist, reprojectionError=s.ransac_px, flags=cv2.SOLVEPNP_SQPNP
            )
            if ok and idx is not None and len(idx) >= 4:
                inliers = np.zeros(n, bool)
                inliers[idx.reshape(-1)] = True
                return [(rvec, tvec)], inliers
        if p.spread[2] < s.planar_tol_m:  # planar
            k, rvecs, tvecs, _ = cv2.solvePnPGeneric(p.X, p.x, p.K, p.dist, flags=cv2.SOLVEPNP_IPPE)
            candidates += list(zip(rvecs, tvecs, strict=False))[:k]
        else:
            ok, rvec, tvec = cv2.solvePnP(p.X, p.x, p.K, p.dist, flags=cv2.SOLVEPNP_SQPNP)
            if ok:
                candidates.append((rvec, tvec))
    except cv2.error:
        pass
    return candidates, inliers


def _best_refined(
    p: _PnPProblem,
    camera: CameraModel,
    candidates: list[tuple[np.ndarray, np.ndarray]],
    inliers: np.ndarray,
) -> tuple[np.ndarray, float] | None:
    """The candidate with the lowest inlier RMS after LM refinement: (world_T_cam, rms_px)."""
    best = None
    for rvec0, tvec0 in candidates:
        rvec = np.asarray(rvec0, dtype=float).reshape(3, 1).copy()
        tvec = np.asarray(tvec0, dtype=float).reshape(3, 1).copy()
        with contextlib.suppress(cv2.error):
            rvec, tvec = cv2.solvePnPRefineLM(p.X[inliers], p.x[inliers], p.K, p.dist, rvec, tvec)
        if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
            continue
        T = _pose_from_rt(cv2.Rodrigues(rvec)[0], tvec.reshape(3))
        rms, depth = _reproject_rms(camera, T, p.c.world[inliers], p.c.px[inliers])
        if np.any(depth <= 0) or not np.isfinite(rms):
            continue
        if best is None or rms < best[1]:
            best = (T, rms)
    return best


def solve_frame_pnp(
    frame_obs: FrameObservations,
    sign_map: SignMap,
    camera: CameraModel,
    prior_world_T_cam: np.ndarray | None = None,
    settings: PerFrameSettings | None = None,
) -> FramePose:
    """PnP on one frame with every keypoint the map orients (causal; for tracking too).

    SQPnP for general point sets, IPPE when the points are planar, then
    Levenberg-Marquardt refinement (``cv2.solvePnPRefineLM``). With
    ``prior_world_T_cam`` (e.g. the previous frame's pose) Levenberg-Marquardt
    from the prior comes first: when every keypoint then reprojects within
    ``ransac_px`` that pose is the answer (RANSAC could only keep them all);
    otherwise it is one more candidate beside RANSAC's and the lower
    reprojection error over the inliers wins.

    Args:
        frame_obs: the frame's observations (raw pixels).
        sign_map: the map.
        camera: the camera.
        prior_world_T_cam: (4, 4) optional initial guess.
        settings: solver settings.

    Returns:
        The FramePose (``world_T_cam`` None with a reason on failure).
    """
    s = settings or PerFrameSettings()
    f = frame_obs
    c = _correspondences(f, sign_map, camera, all_keypoints=True)
    distinct = tuple(sorted(set(c.codes)))

    def posed(T: np.ndarray | None, used: tuple[str, ...], **kw) -> FramePose:
        return FramePose(
            frame=f.frame,
            stamp_ns=f.stamp_ns,
            world_T_cam=T,
            signs_used=len(used),
            inlier_codes=used if T is not None else (),
            **kw,
        )

    if len(c.world) < 4:
        return posed(None, distinct, reason=PoseFailure.FEW_POINTS)
    spread = _spread(c.world)
    reason = _degenerate(spread, s)
    if reason is not None:
        return posed(None, distinct, reason=reason)
    p = _PnPProblem(
        c, spread, camera.K.astype(float), c.world.reshape(-1, 1, 3), c.px.reshape(-1, 1, 2)
    )
    candidates: list[tuple[np.ndarray, np.ndarray]] = []
    if prior_world_T_cam is not None:
        warm, accept = _warm_candidate(p, camera, prior_world_T_cam, s)
        if accept:
            T = _pose_from_rt(cv2.Rodrigues(warm[0])[0], warm[1].reshape(3))
            every = np.ones(len(c.world), bool)
            T = _weighted_refine(camera, T, c, every)
            rms, _ = _reproject_rms(camera, T, c.world, c.px)
            return posed(T, distinct, rms_px=rms, **c.fit(camera, T, every))
        if warm is not None:
            candidates.append(warm)
    cold, inliers = _cold_candidates(p, s)
    best = _best_refined(p, camera, candidates + cold, inliers)
    if best is None:
        return posed(None, distinct, reason=PoseFailure.PNP)
    used = tuple(sorted({code for code, ok in zip(c.codes, inliers, strict=True) if ok}))
    T = _weighted_refine(camera, best[0], c, inliers)
    rms = best[1] if T is best[0] else _reproject_rms(camera, T, c.world[inliers], c.px[inliers])[0]
    return posed(T, used, rms_px=rms, **c.fit(camera, T, inliers))


# Gauss-Newton steps of the weighted refinement, and the step [rad or m] below which it stops.
_WEIGHTED_STEPS = 5
_WEIGHTED_TOL = 1e-10


def _weighted_refine(
    camera: CameraModel, world_T_cam: np.ndarray, c: _Correspondences, inliers: np.ndarray
) -> np.ndarray:
    """The pose minimising the inliers' residuals whitened per keypoint and axis.

    OpenCV's Levenberg-Marquardt weighs every pixel alike; where the
    keypoints' sigmas differ (a keypoint beside an occluder, a blurred axis)
    a few Gauss-Newton steps from its solution weigh each residual by its
    sigma, so that the pose is the one ``_Correspondences.fit``'s covariance
    describes. Equal sigmas: the same pose, returned as is. A step that does
    not lower the weighted error, or leaves a point behind the camera, ends it.
    """
    sig = c.sigma_px[inliers]
    if sig.size == 0 or (c.cov_px is None and np.all(sig == sig.flat[0])):
        return world_T_cam
    pin = _pinhole(camera)
    X, px = c.world[inliers], c.px[inliers]
    weigh = weigher(c.noise[inliers], len(X))  # y -> W y, W the pixels' inverse covariance
    T = world_T_cam
    uv, J, _ = pixels_and_pose_jacobian(pin, T, X)
    r = (px - uv).reshape(-1)
    err = float(r @ weigh(r))
    for _ in range(_WEIGHTED_STEPS):
        Jf = J.reshape(-1, 6)
        try:
            xi = np.linalg.solve(Jf.T @ weigh(Jf), Jf.T @ weigh(r))
        except np.linalg.LinAlgError:
            break
        new = T.copy()  # world_T_cam * Exp(xi), xi = [omega, v] in the camera frame
        new[:3, :3] = _orthonormal(T[:3, :3] @ cv2.Rodrigues(xi[:3].reshape(3, 1))[0])
        new[:3, 3] = T[:3, 3] + T[:3, :3] @ xi[3:]
        uv, J_new, _ = pixels_and_pose_jacobian(pin, new, X)
        r_new = (px - uv).reshape(-1)
        err_new = float(r_new @ weigh(r_new))
        depth_ok = np.all(((X - new[:3, 3]) @ new[:3, :3])[:, 2] > 0)
        if not (np.isfinite(err_new) and err_new <= err and depth_ok):
            break
        T, J, r, err = new, J_new, r_new, err_new
        if np.max(np.abs(xi)) < _WEIGHTED_TOL:
            break
    return T


@dataclass(frozen=True)
class SolvedPnP:
    """One frame's ``solve_frame_pnp`` call made elsewhere (the tracker's), to be reused.

    Attributes:
        observations: the frame it was solved on (the very object).
        prior_world_T_cam: the prior it was given, or None.
        settings: the settings it was given (None: the defaults).
        pose: what it returned.
        sign_map: the map it was given.
        camera: the camera it was given.
    """

    observations: FrameObservations
    prior_world_T_cam: np.ndarray | None
    settings: PerFrameSettings | None
    pose: FramePose
    sign_map: SignMap
    camera: CameraModel

    def answers(
        self, frame: FrameObservations, prior: np.ndarray | None, s: PerFrameSettings
    ) -> bool:
        """True when this call had exactly this frame, prior and settings."""
        if frame is not self.observations or (self.settings or PerFrameSettings()) != s:
            return False
        if prior is None or self.prior_world_T_cam is None:
            return prior is None and self.prior_world_T_cam is None
        a, b = np.asarray(prior), np.asarray(self.prior_world_T_cam)
        return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _same_object(a, b) -> bool:
    """The same object, or one with the same pickled bytes (a copy from another process)."""
    if a is b:
        return True
    try:
        return pickle.dumps(a) == pickle.dumps(b)
    except (pickle.PicklingError, TypeError, AttributeError):
        return False


class PnPChain:
    """Per-frame PnP fed frames in time order, each solved with the last pose as prior.

    ``solve(frame, solved)`` takes ``solved``'s pose instead of solving again
    when that call had exactly the inputs the chain gives the frame
    (``SolvedPnP.answers``); the caller vouches that it had this map and camera.
    """

    def __init__(self, sign_map: SignMap, camera: CameraModel, settings: PerFrameSettings):
        self.sign_map = sign_map
        self.camera = camera
        self.settings = settings
        self._prior: np.ndarray | None = None
        self.solves = 0  # solve_frame_pnp calls made (the others were reused)

    def solve(self, frame: FrameObservations, solved: SolvedPnP | None = None) -> FramePose:
        if solved is not None and solved.answers(frame, self._prior, self.settings):
            pose = solved.pose
        else:
            pose = solve_frame_pnp(frame, self.sign_map, self.camera, self._prior, self.settings)
            self.solves += 1
        if pose.world_T_cam is not None:
            self._prior = pose.world_T_cam
        return pose


class _SameContext:
    """Whether a SolvedPnP call had this map and camera (copies from another process count)."""

    def __init__(self, sign_map: SignMap, camera: CameraModel) -> None:
        self.sign_map = sign_map
        self.camera = camera
        self._known: dict[tuple[int, int], bool] = {}  # (id(map), id(camera)) of the calls

    def __call__(self, k: SolvedPnP) -> bool:
        pair = (id(k.sign_map), id(k.camera))
        if pair not in self._known:
            self._known[pair] = _same_object(k.sign_map, self.sign_map) and _same_object(
                k.camera, self.camera
            )
        return self._known[pair]


def _chained_pnp(
    frames, sign_map: SignMap, camera: CameraModel, s: PerFrameSettings, solved
) -> list[FramePose]:
    """PnP frame by frame, each with the last pose as prior; a ``solved`` call with
    the same inputs is taken instead of solving again."""
    known = {id(k.observations): k for k in solved}
    same = _SameContext(sign_map, camera)
    chain = PnPChain(sign_map, camera, s)
    out: list[FramePose] = []
    for f in frames:
        k = known.get(id(f))
        out.append(chain.solve(f, k if k is not None and same(k) else None))
    return out


PER_FRAME_METHODS = ("baseline", "pnp")


class PerFrameRun:
    """The per-frame methods fed one frame at a time, in flight order (while observing).

    The same poses as ``run_per_frame`` on the frames fed (with the same
    ``solved`` calls), kept per method; ``seconds`` is each method's time.
    """

    def __init__(
        self,
        sign_map: SignMap,
        camera: CameraModel,
        methods: Sequence[str],
        settings: PerFrameSettings | None = None,
    ) -> None:
        unknown = set(methods) - set(PER_FRAME_METHODS)
        if unknown:
            raise ValueError(f"unknown per-frame method {sorted(unknown)[0]!r}")
        self.sign_map = sign_map
        self.camera = camera
        self.settings = settings or PerFrameSettings()
        self.methods = tuple(m for m in PER_FRAME_METHODS if m in methods)
        self.frames: list[FrameObservations] = []
        self.poses: dict[str, list[FramePose]] = {m: [] for m in self.methods}
        self.seconds: dict[str, float] = dict.fromkeys(self.methods, 0.0)
        self._baseline = BaselineTracker(sign_map, camera, self.settings)
        self._pnp = PnPChain(sign_map, camera, self.settings)
        self._same = _SameContext(sign_map, camera)

    @property
    def pnp_solves(self) -> int:
        """solve_frame_pnp calls the PnP method made (frames not taken from ``solved``)."""
        return self._pnp.solves

    def add(self, frame: FrameObservations, solved: SolvedPnP | None = None) -> None:
        """The next frame of the flight; ``solved``: the tracker's PnP call on it, if any."""
        self.frames.append(frame)
        if "baseline" in self.methods:
            t0 = time.perf_counter()
            self.poses["baseline"].append(self._baseline.solve(frame))
            self.seconds["baseline"] += time.perf_counter() - t0
        if "pnp" in self.methods:
            t0 = time.perf_counter()
            reuse = solved if solved is not None and self._same(solved) else None
            self.poses["pnp"].append(self._pnp.solve(frame, reuse))
            self.seconds["pnp"] += time.perf_counter() - t0

    def fed(
        self,
        frames: Sequence[FrameObservations],
        sign_map: SignMap,
        camera: CameraModel,
        settings: PerFrameSettings,
    ) -> bool:
        """True when this run was fed exactly ``frames`` (the very objects) with these inputs."""
        return (
            sign_map is self.sign_map
            and camera is self.camera
            and settings == self.settings
            and len(frames) == len(self.frames)
            and all(a is b for a, b in zip(frames, self.frames, strict=True))
        )


def run_per_frame(
    frames: Sequence[FrameObservations],
    sign_map: SignMap,
    camera: CameraModel,
    method: str,
    settings: PerFrameSettings | None = None,
    progress: bool = False,
    solved: Sequence[SolvedPnP] = (),
) -> list[FramePose]:
    """Run ``"baseline"`` (with the speed gate) or ``"pnp"`` (chained priors) over a flight.

    ``solved``: PnP calls already made on these frames (the pipeline's tracker
    poses every frame with the previous frame's pose as prior); where one had
    exactly the inputs the chain gives a frame (the same observations object,
    equal settings, an equal map and camera, a bit-identical prior) its result
    is used, not solved again: the output is the same bytes either way.
    """
    s = settings or PerFrameSettings()
    out: list[FramePose] = []
    it = tqdm(frames, desc=method, unit="frame", disable=not progress, leave=False)
    if method == "baseline":
        tracker = BaselineTracker(sign_map, camera, s)
        out = [tracker.solve(f) for f in it]
    elif method == "pnp":
        out = _chained_pnp(it, sign_map, camera, s, solved)
    else:
        raise ValueError(f"unknown per-frame method {method!r}")
    return out
