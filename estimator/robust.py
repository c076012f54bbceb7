"""No silent jumps: observations tested against the pose their neighbours predict.

A sign observation (all keypoints of one decoded sign in one frame) is
tested against the pose interpolated from the smoothed poses of the frames
before and after it, with the predicted covariance (the neighbours' marginal
covariances plus the motion prior's noise over the gap, the pixel noise and
the survey noise): the chi-square statistic of its innovation. This works with
any number of signs in the frame (RANSAC needs four), including centre-only
maps. The worst failing observation of each frame is dropped and the flight
solved again, for a few rounds; then the final solve's kernel (``gnc`` or
``tukey``) removes what is left. Every rejection is a ``Rejection`` value
naming its test.

Poses are ``world_T_cam`` (4, 4); covariances are gtsam's Pose3 order
([rotation, translation], camera frame).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import cv2
import numpy as np
from signpose.estimator.camera import CameraModel
from signpose.estimator.projection import (
    chi2_quantile_even,
    pixels_and_jacobians,
    pixels_and_pose_jacobian,
)
from signpose.estimator.smoother import CONSTANT_VELOCITY, Measurements, SmootherSettings

# Without marginals (very long flights) the neighbours' pose uncertainty is
# taken as this: 0.01 rad and 0.1 m per axis, loose enough to keep good data.
FALLBACK_ROT_SIGMA_RAD = 0.01
FALLBACK_POS_SIGMA_M = 0.1


class RejectionTest(enum.Enum):
    """Which test removed an observation from the solve; files carry the token."""

    PNP_GATE = "pnp_gate"  # far from where the frame's RANSAC PnP pose projects it
    INNOVATION = "innovation"  # chi-square against the pose the neighbours predict
    GNC = "gnc"  # truncated by graduated non-convexity in the final solve
    TUKEY = "tukey"  # beyond the redescending kernel's threshold in the final solve


@dataclass(frozen=True)
class Rejection:
    """One sign observation (or some of its keypoints) left out of the trajectory.

    Attributes:
        frame: frame index; code: the decoded code.
        keypoints: how many of its keypoints were rejected.
        test: the test that rejected them.
        statistic: the test's value (chi-square of the innovation, or the
            largest whitened squared residual for the final kernels).
        threshold: the value it exceeded.
    """

    frame: int
    code: str
    keypoints: int
    test: RejectionTest
    statistic: float
    threshold: float

    def to_dict(self) -> dict:
        return {
            "frame": self.frame,
            "code": self.code,
            "keypoints": self.keypoints,
            "test": self.test.value,
            "statistic": self.statistic,
            "threshold": self.threshold,
        }


@dataclass(frozen=True)
class OutlierSettings:
    """Settings of the outlier tests.

    Attributes:
        alpha: false rejection rate of each chi-square test (per observation).
        rounds: at most this many rounds of innovation test and re-solve.
    """

    alpha: float = 1e-3
    rounds: int = 4


def _exp_so3(w: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(w, float).reshape(3, 1))[0]


def _log_so3(R: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(R, float))[0].reshape(3)


def _blend(Ta: np.ndarray, Tb: np.ndarray, w: float) -> np.ndarray:
    """The pose a fraction ``w`` of the way from Ta to Tb (w outside [0, 1] extrapolates)."""
    T = np.eye(4)
    T[:3, :3] = Ta[:3, :3] @ _exp_so3(w * _log_so3(Ta[:3, :3].T @ Tb[:3, :3]))
    T[:3, 3] = (1 - w) * Ta[:3, 3] + w * Tb[:3, 3]
    return T


def _gap_noise(dt_a: float, dt_b: float, s: SmootherSettings) -> np.ndarray:
    """(6, 6) motion-prior noise of a pose bridged between neighbours dt_a and dt_b away [s].

    dt_b = inf for extrapolation from one side. Constant velocity: position of
    integrated white-noise acceleration pinned at both ends (Brownian-bridge
    form of the cubic spline's variance), rotation a pinned random walk.
    """
    if s.motion == CONSTANT_VELOCITY:
        q_pos, q_rot = s.cv_sigma_acc**2, s.cv_sigma_rot**2
        if np.isinf(dt_b):
            var_pos = q_pos * dt_a**3 / 3.0
        else:
            var_pos = q_pos * dt_a**3 * dt_b**3 / (3.0 * (dt_a + dt_b) ** 3)
    else:
        q_pos, q_rot = s.rw_sigma_pos**2, s.rw_sigma_rot**2
        var_pos = q_pos * (dt_a if np.isinf(dt_b) else dt_a * dt_b / (dt_a + dt_b))
    var_rot = q_rot * (dt_a if np.isinf(dt_b) else dt_a * dt_b / (dt_a + dt_b))
    return np.diag([var_rot] * 3 + [var_pos] * 3)


def predict_from_neighbours(
    world_T_cam: np.ndarray,
    cov6: np.ndarray | None,
    stamps_s: np.ndarray,
    s: SmootherSettings,
) -> tuple[np.ndarray, np.ndarray]:
    """Each pose predicted from the frames before and after it, without its own data.

    Args:
        world_T_cam: (N, 4, 4) smoothed poses.
        cov6: (N, 6, 6) their marginal covariances, or None (fallback sigmas).
        stamps_s: (N,) frame times [s].
        s: the smoother settings (the motion prior's noise).

    Returns:
        ((N, 4, 4) predicted poses, (N, 6, 6) predicted covariances). The
        first and last frames are extrapolated from their two neighbours.
    """
    n = len(world_T_cam)
    fallback = np.diag([FALLBACK_ROT_SIGMA_RAD**2] * 3 + [FALLBACK_POS_SIGMA_M**2] * 3)
    cov = np.repeat(fallback[None], n, axis=0) if cov6 is None else np.nan_to_num(cov6, nan=1.0)
    pred = np.array(world_T_cam, float, copy=True)
    pred_cov = np.repeat(fallback[None], n, axis=0)
    t = np.asarray(stamps_s, float)
    for i in range(n):
        if 0 < i < n - 1:
            a, b = i - 1, i + 1
        elif n >= 3:
            a, b = (1, 2) if i == 0 else (n - 2, n - 3)
        else:
            continue
        span = t[b] - t[a]
        if abs(span) < s.min_dt_s:
            span = float(np.copysign(s.min_dt_s, span))
        w = (t[i] - t[a]) / span
        pred[i] = _blend(world_T_cam[a], world_T_cam[b], w)
        dt_a = max(abs(t[i] - t[a]), s.min_dt_s)
        dt_b = max(abs(t[b] - t[i]), s.min_dt_s) if 0 < i < n - 1 else np.inf
        pred_cov[i] = (1 - w) ** 2 * cov[a] + w**2 * cov[b] + _gap_noise(dt_a, dt_b, s)
    return pred, pred_cov


def sign_groups(meas: Measurements) -> list[np.ndarray]:
    """Measurement indices of each sign observation (one frame's one decoded sign)."""
    if len(meas.frame) == 0:
        return []
    key = meas.frame * (int(meas.sign_index.max()) + 1) + meas.sign_index
    order = np.argsort(key, kind="stable")
    cuts = np.nonzero(np.diff(key[order]))[0] + 1
    return np.split(order, cuts)


def innovation_chi2(
    meas: Measurements,
    ids: np.ndarray,
    world_T_cam: np.ndarray,
    cov6: np.ndarray,
    camera: CameraModel,
) -> float:
    """Chi-square of one sign observation's innovation against a predicted pose.

    Args:
        meas: all measurements; ids: (K,) the observation's measurement indices.
        world_T_cam: (4, 4) the predicted pose; cov6: (6, 6) its covariance.
        camera: the camera.

    Returns:
        r^T S^-1 r with S = J P J^T + pixel noise + survey noise (2K dof).
    """
    lm = meas.landmark[ids]
    uv, J_pose, J_point = pixels_and_pose_jacobian(camera, world_T_cam, meas.landmark_world[lm])
    r = (meas.px[ids] - uv).reshape(-1)
    J = J_pose.reshape(-1, 6)
    S = J @ cov6 @ J.T
    for k, (cov_px, sig_m) in enumerate(
        zip(meas.pixel_cov()[ids], meas.landmark_sigma_m[lm], strict=True)
    ):
        block = slice(2 * k, 2 * k + 2)
        S[block, block] += cov_px + sig_m**2 * J_point[k] @ J_point[k].T
    try:
        return float(r @ np.linalg.solve(S, r))
    except np.linalg.LinAlgError:
        return float("inf")


def _group_chi2(
    meas: Measurements,
    groups: np.ndarray,
    pred: np.ndarray,
    pred_cov: np.ndarray,
    camera: CameraModel,
) -> np.ndarray:
    """(G,) innovation chi-square of G sign observations of K keypoints each, (G, K) ids.

    ``innovation_chi2`` for many observations at once.
    """
    g, k = groups.shape
    ids = groups.reshape(-1)
    frame = meas.frame[groups[:, 0]]
    lm = meas.landmark[ids]
    uv, J_pose, J_point = pixels_and_jacobians(
        camera, pred[meas.frame[ids]], meas.landmark_world[lm]
    )
    r = (meas.px[ids] - uv).reshape(g, 2 * k)
    J = J_pose.reshape(g, 2 * k, 6)
    S = J @ pred_cov[frame] @ J.transpose(0, 2, 1)
    noise = (
        meas.pixel_cov()[ids]
        + meas.landmark_sigma_m[lm, None, None] ** 2 * J_point @ J_point.transpose(0, 2, 1)
    ).reshape(g, k, 2, 2)
    for a in range(k):
        S[:, 2 * a : 2 * a + 2, 2 * a : 2 * a + 2] += noise[:, a]
    try:
        x = np.linalg.solve(S, r[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        return np.array(
            [
                innovation_chi2(meas, ids_g, pred[f], pred_cov[f], camera)
                for ids_g, f in zip(groups, frame, strict=True)
            ]
        )
    return np.einsum("gi,gi->g", r, x)


def worst_innovations(
    meas: Measurements,
    active: np.ndarray,
    pred: np.ndarray,
    pred_cov: np.ndarray,
    camera: CameraModel,
    alpha: float,
) -> list[tuple[np.ndarray, float, float]]:
    """The worst failing sign observation of each frame: (ids, chi2, threshold) each.

    Only ``active`` measurements count; an observation whose chi-square
    exceeds its quantile at ``1 - alpha`` fails. Observations with the same
    number of keypoints are tested together.
    """
    by_size: dict[int, list[np.ndarray]] = {}
    for ids in sign_groups(meas):
        ids = ids[active[ids]]
        if len(ids):
            by_size.setdefault(len(ids), []).append(ids)
    worst: dict[int, tuple[float, np.ndarray, float, float]] = {}
    for k, lists in by_size.items():
        groups = np.array(lists)
        chi2 = _group_chi2(meas, groups, pred, pred_cov, camera)
        threshold = chi2_quantile_even(1.0 - alpha, 2 * k)
        for ids, c in zip(groups, chi2, strict=True):
            i = int(meas.frame[ids[0]])
            ratio = c / threshold
            if ratio > 1.0 and (i not in worst or ratio > worst[i][0]):
                worst[i] = (ratio, ids, float(c), threshold)
    return [(ids, chi2, thr) for _, ids, chi2, thr in worst.values()]
