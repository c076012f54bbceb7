"""Status of each estimated pose, written to trajectory.csv and report.json as its token.

A method's pose for a frame is either one of ``PoseStatus`` (it has a pose) or,
for the per-frame methods, the ``PoseFailure`` that says why it has none.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
from signpose.estimator.perframe import PoseFailure
from signpose.estimator.projection import chi2_quantile_even, position_cov_world


class PoseStatus(enum.Enum):
    """How far a pose can be trusted; the value is the token in the output files.

    OK: the frame's signs fix the pose and its residuals pass the chi-square test.
    WEAK: too few keypoints to fix the pose alone, or an ill-conditioned
        geometry (worst-axis sigma above the setting).
    BRIDGED: no sign seen; the pose comes from the motion prior (for the
        "fused" method from the IMU/GNSS: its sigma, the fusion's marginal,
        says how well).
    SUSPECT: its residuals fail the chi-square test after the solve.
    """

    OK = "ok"
    WEAK = "weak"
    BRIDGED = "bridged"
    SUSPECT = "suspect"


PoseState = PoseStatus | PoseFailure
_BY_TOKEN: dict[str, PoseState] = {
    **{m.value: m for m in PoseStatus},
    **{m.value: m for m in PoseFailure},
}


def state_from_token(token: str) -> PoseState:
    """The status or failure written as ``token``; ValueError when it is neither."""
    try:
        return _BY_TOKEN[token]
    except KeyError:
        raise ValueError(f"unknown pose status {token!r}") from None


@dataclass(frozen=True)
class StatusSettings:
    """When a pose is ``weak`` or ``suspect``.

    Attributes:
        min_keypoints: a frame with fewer inlier keypoints cannot fix its pose
            alone (three points have up to four P3P solutions): ``weak``.
        weak_sigma_m: ... nor can one whose own keypoints leave a position
            sigma above this on some axis [m] (ill-conditioned geometry).
        alpha: false alarm rate of the chi-square test on a pose's residuals
            (``suspect``).
    """

    min_keypoints: int = 4
    weak_sigma_m: float = 0.5
    alpha: float = 1e-3


def worst_axis_sigma(cov6: np.ndarray | None, world_R_cam: np.ndarray) -> float:
    """Largest world-axis position sigma [m] of a (6, 6) pose covariance (inf without one)."""
    if cov6 is None or not np.all(np.isfinite(cov6)):
        return float("inf")
    return float(np.sqrt(np.max(np.diag(position_cov_world(cov6, world_R_cam)))))


def classify(
    keypoints: int, worst_sigma_m: float, chi2: float, dof: int, s: StatusSettings
) -> PoseStatus:
    """The status of a pose from its own keypoints.

    Args:
        keypoints: inlier keypoints of the frame (0: bridged).
        worst_sigma_m: worst-axis position sigma from those keypoints alone [m].
        chi2: sum of their whitened squared residuals at the pose.
        dof: its degrees of freedom (even; 0 skips the test).
        s: the thresholds.
    """
    if keypoints == 0:
        return PoseStatus.BRIDGED
    if dof > 0 and chi2 > chi2_quantile_even(1.0 - s.alpha, dof):
        return PoseStatus.SUSPECT
    if keypoints < s.min_keypoints or not worst_sigma_m <= s.weak_sigma_m:
        return PoseStatus.WEAK
    return PoseStatus.OK
