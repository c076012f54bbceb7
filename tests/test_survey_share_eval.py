"""eval_flight's survey draws through a flight's response: an error every pose shares
sends them beyond 3 sigma together, in 0.27 % of draws (one axis), not one by one."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
N_POSES = 50
DRAWS = 100_000
P_BEYOND_3 = 0.0027  # P(|N(0, 1)| > 3)


@pytest.fixture(scope="module")
def eval_flight():
    sys.path.insert(0, str(SCRIPTS))
    try:
        import eval_flight
    finally:
        sys.path.remove(str(SCRIPTS))
    return eval_flight


def _graded(eval_flight, shared: bool):
    """Poses whose x error is sigma_m times one shared survey coordinate or one each."""
    n_coords = 1 if shared else N_POSES
    J = np.zeros((N_POSES, 3, n_coords))
    J[np.arange(N_POSES), 0, 0 if shared else np.arange(N_POSES)] = 1.0
    sigma_m = np.full(n_coords, 0.01)
    sigma_xyz = np.full((N_POSES, 3), 0.01)
    ok = np.ones(N_POSES, bool)
    rng = np.random.default_rng(3)
    return eval_flight.simulated_draws(
        np.zeros((N_POSES, 3)), J, sigma_xyz, ok, sigma_m, DRAWS, rng
    )


def test_a_shared_survey_error_moves_every_pose_beyond_3_sigma_at_once(eval_flight):
    bad, rms_max, pooled = _graded(eval_flight, shared=True)
    assert set(np.unique(bad)) <= {0, N_POSES}  # all or none
    assert abs(np.mean(bad > 0) - P_BEYOND_3) < 6e-4  # 4 sd of the estimate
    assert abs(pooled[0] - 1.0) < 0.01 and np.all(pooled[1:] == 0.0)
    # one draw: its worst-axis rms is |N(0, 1)|, beyond 3 as often
    assert abs(np.mean(rms_max > 3.0) - P_BEYOND_3) < 6e-4


def test_independent_errors_leave_poses_beyond_3_sigma_one_by_one(eval_flight):
    bad, rms_max, pooled = _graded(eval_flight, shared=False)
    p_any = 1 - (1 - P_BEYOND_3) ** N_POSES
    assert abs(np.mean(bad > 0) - p_any) < 0.005
    assert np.max(bad) < 5
    assert abs(pooled[0] - 1.0) < 0.01
    assert np.max(rms_max) < 1.6  # 50 poses average their errors
