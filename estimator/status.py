"""Status of each estimated pose, written to trajectory.csv and report.json as its token.

A method's pose for a frame is either one of ``PoseStatus`` (it has a pose) or,
for the per-frame methods, the ``PoseFailure`` that says why it has none.
"""

from __future__ import annotations

import enum

from signpose.estimator.perframe import PoseFailure


class PoseStatus(enum.Enum):
    """How far a pose can be trusted; the value is the token in the output files.

    OK: the frame's signs fix the pose and its residuals pass the chi-square test.
    WEAK: too few keypoints to fix the pose alone, or an ill-conditioned
        geometry (worst-axis sigma above the setting).
    BRIDGED: no sign seen; the pose comes from the motion prior.
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
