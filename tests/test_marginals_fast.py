"""One-pass marginals (estimator.marginals) against gtsam.Marginals and a dense inverse."""

import gtsam
import numpy as np
import pytest
from conftest import estimator_scene
from signpose.estimator import smoother as sm
from signpose.estimator.marginals import Conditional, selected_covariances
from signpose.estimator.perframe import run_per_frame


def _graph(motion: str, landmarks: str, kernel: str = sm.HUBER, n: int = 25):
    sign_map, camera, frames, _, _ = estimator_scene(n_frames=n, sigma_px=0.4, seed=2, flat=False)
    meas = sm.collect_measurements(frames, sign_map, camera)
    stamps = np.array([f.stamp_ns for f in frames], float) * 1e-9
    init = [p.world_T_cam for p in run_per_frame(frames, sign_map, camera, "pnp")]
    s = sm.SmootherSettings(motion=motion, landmarks=landmarks, kernel=kernel)
    r = sm.smooth_batch(meas, stamps, init, camera, s, sm.default_pose(sign_map))
    b = sm._GraphBuilder(meas, stamps, camera, s)
    # Linearised at the smoothed poses, landmarks at the survey, velocities by differences.
    g = sm._batch_graph(b, r.world_T_cam, stamps)
    order = b.ordered(sm.chain_ordering(n, len(meas.landmark_code), motion))
    return g, order, n, r


@pytest.mark.parametrize(
    "motion, landmarks",
    [
        (sm.CONSTANT_VELOCITY, sm.RIGID),
        (sm.RANDOM_WALK, sm.KEYPOINTS),
        (sm.CONSTANT_VELOCITY, sm.FIXED),
    ],
)
def test_one_pass_pose_covariances_equal_gtsam_marginals(motion, landmarks):
    g, order, n, r = _graph(motion, landmarks)
    fast = sm.batch_covariances(g.graph, g.values, n, order)
    assert sm._chain_covariances(g.graph.linearize(g.values), order, n) is not None  # one pass
    ref = gtsam.Marginals(g.graph, g.values)
    for i in range(n):
        want = ref.marginalCovariance(sm.X(i))
        scale = np.abs(want).max()
        assert np.abs(fast[i] - want).max() <= 1e-9 * scale, i
    # The smoother's sigmas come from the same pass: finite, positive.
    assert np.all(np.isfinite(r.sigma_xyz)) and np.all(r.sigma_xyz > 0)


def test_one_pass_matches_dense_inverse_on_a_random_chordal_net():
    # Blocks of mixed sizes: a banded chain (bandwidth 2 blocks) with an arrow of
    # three dense tail blocks; the Cholesky factor's fill is the chordal pattern.
    rng = np.random.default_rng(4)
    dims = [3, 2, 4, 1, 3, 2, 3, 2, 2, 4, 5, 3]
    n_chain = 9
    off = np.concatenate([[0], np.cumsum(dims)])
    n = off[-1]
    J = []
    for k in range(len(dims)):  # each block tied to the next two and to the tail
        cols = [k] + [j for j in (k + 1, k + 2) if j < n_chain] + list(range(n_chain, len(dims)))
        for _ in range(3):
            row = np.zeros(n)
            for j in cols:
                row[off[j] : off[j + 1]] = rng.normal(size=dims[j])
            J.append(row)
    H = np.array(J).T @ np.array(J) + 0.1 * np.eye(n)
    R = np.linalg.cholesky(H).T  # H = R^T R, R upper triangular
    conds = []
    for k in range(len(dims)):
        parents = [
            j
            for j in range(k + 1, len(dims))
            if np.abs(R[off[k] : off[k + 1], off[j] : off[j + 1]]).max() > 0
        ]
        S = (
            np.hstack([R[off[k] : off[k + 1], off[j] : off[j + 1]] for j in parents])
            if parents
            else np.zeros((dims[k], 0))
        )
        conds.append(Conditional(k, R[off[k] : off[k + 1], off[k] : off[k + 1]], tuple(parents), S))
    got = selected_covariances(conds, n_chain, list(range(len(dims))))
    Sigma = np.linalg.inv(H)
    for k in range(len(dims)):
        want = Sigma[off[k] : off[k + 1], off[k] : off[k + 1]]
        assert np.abs(got[k] - want).max() <= 1e-9 * np.abs(want).max(), k
