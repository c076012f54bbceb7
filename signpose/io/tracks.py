"""Estimated trajectories as per-stamp pose look-ups, for the writers of result logs.

``result.mcap`` (``signpose.io.mcap_write``) and the ROS 2 result bag
(``signpose.io.rosbag_write``) write one pose per frame: the pose of the
trajectory whose stamp matches the frame's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from signpose.estimator.trajectory import Trajectory

# Trajectory stamps are float seconds: a frame's stamp comes back within this.
MATCH_TOLERANCE_NS = 1_000_000


@dataclass(frozen=True)
class PoseTrack:
    """One method's valid poses.

    Attributes:
        stamps_ns: (N,) increasing stamps [ns].
        world_T_cams: (N, 4, 4) camera poses in the world frame at those stamps.
    """

    stamps_ns: np.ndarray
    world_T_cams: np.ndarray

    def at(self, stamp_ns: int, tol_ns: int = MATCH_TOLERANCE_NS) -> np.ndarray | None:
        """The (4, 4) pose nearest ``stamp_ns`` if within ``tol_ns``, else None."""
        i = int(np.searchsorted(self.stamps_ns, stamp_ns))
        near = [j for j in (i - 1, i) if 0 <= j < len(self.stamps_ns)]
        if not near:
            return None
        j = min(near, key=lambda k: abs(int(self.stamps_ns[k]) - int(stamp_ns)))
        ok = abs(int(self.stamps_ns[j]) - int(stamp_ns)) <= tol_ns
        return self.world_T_cams[j] if ok else None


def pose_tracks(trajectories: dict[str, Trajectory]) -> dict[str, PoseTrack]:
    """Method name -> its poses with a finite position and rotation (NaN frames left out)."""
    tracks = {}
    for name, traj in trajectories.items():
        Ts = traj.world_T_cam()
        ok = np.all(np.isfinite(Ts.reshape(len(Ts), 16)), axis=1)
        tracks[name] = PoseTrack(np.round(traj.stamps_s[ok] * 1e9).astype(np.int64), Ts[ok])
    return tracks
