"""The batch solve (Gauss-Newton, its last Bayes net kept for the marginals) against gtsam's LM."""

from dataclasses import replace

import gtsam
import numpy as np
import pytest
from conftest import estimator_scene
from signpose.estimator import smoother as sm
from signpose.estimator.perframe import run_per_frame


@pytest.fixture(scope="module")
def flight():
    sign_map, camera, frames, _, _ = estimator_scene(n_frames=40, sigma_px=0.4, seed=3, flat=False)
    meas = sm.collect_measurements(frames, sign_map, camera)
    stamps = np.array([f.stamp_ns for f in frames], float) * 1e-9
    init = [p.world_T_cam for p in run_per_frame(frames, sign_map, camera, "pnp")]
    return meas, stamps, init, camera, sm.default_pose(sign_map)


def _converged(meas, stamps, init, camera, s, default):
    """gtsam's Levenberg-Marquardt converged far past the settings' tolerance."""
    b = sm._GraphBuilder(meas, stamps, camera, s)
    g = sm._batch_graph(b, sm._fill_initial(init, default), stamps)
    params = sm._lm_params(b)
    params.setRelativeErrorTol(1e-14)
    params.setAbsoluteErrorTol(0.0)
    return g, gtsam.LevenbergMarquardtOptimizer(g.graph, g.values, params).optimize()


@pytest.mark.parametrize(
    "motion, landmarks",
    [(sm.CONSTANT_VELOCITY, sm.RIGID), (sm.RANDOM_WALK, sm.KEYPOINTS)],
)
def test_solution_and_sigmas_match_converged_lm(flight, motion, landmarks):
    meas, stamps, init, camera, default = flight
    s = sm.SmootherSettings(motion=motion, landmarks=landmarks)
    r = sm.smooth_batch(meas, stamps, init, camera, s, default)
    g, best = _converged(meas, stamps, init, camera, s, default)
    want = np.array([best.atPose3(sm.X(i)).translation() for i in range(meas.n_frames)])
    # lm_rel_tol 1e-5 leaves a solve a tenth of a millimetre from the optimum:
    # no further than gtsam's LM with the same tolerance.
    params = sm._lm_params(sm._GraphBuilder(meas, stamps, camera, s))
    params.setAbsoluteErrorTol(1e-9)
    lm = gtsam.LevenbergMarquardtOptimizer(g.graph, g.values, params).optimize()
    lm_t = np.array([lm.atPose3(sm.X(i)).translation() for i in range(meas.n_frames)])
    off = np.abs(r.world_T_cam[:, :3, 3] - want).max()
    assert off < 3e-4
    assert off <= np.abs(lm_t - want).max() + 1e-6
    assert r.iterations >= 2
    # Sigmas from the net one step before the solution: the optimum's to 0.1 %.
    marg = gtsam.Marginals(g.graph, best)
    for i in range(meas.n_frames):
        cov = marg.marginalCovariance(sm.X(i))
        assert np.abs(r.cov6[i] - cov).max() <= 1e-3 * np.abs(cov).max(), i
    # Without sigmas the same solve: the same poses.
    r0 = sm.smooth_batch(meas, stamps, init, camera, replace(s, compute_sigmas=False), default)
    assert np.array_equal(r0.world_T_cam, r.world_T_cam)
    assert np.all(np.isnan(r0.sigma_xyz))


def test_a_far_start_still_reaches_the_optimum(flight):
    # Every frame starts at the default pose (metres off): Gauss-Newton either
    # converges or hands over to Levenberg-Marquardt; the result is the optimum.
    meas, stamps, init, camera, default = flight
    s = sm.SmootherSettings()
    far = [None] * meas.n_frames
    r = sm.smooth_batch(meas, stamps, far, camera, s, default)
    _, best = _converged(meas, stamps, init, camera, s, default)
    want = np.array([best.atPose3(sm.X(i)).translation() for i in range(meas.n_frames)])
    assert np.abs(r.world_T_cam[:, :3, 3] - want).max() < 1e-3
    assert np.all(np.isfinite(r.sigma_xyz)) and np.all(r.sigma_xyz > 0)


def test_a_failing_step_hands_over_to_levenberg_marquardt(flight):
    # Every frame starts turned 1.5 rad off the default pose: the first
    # elimination fails (signs behind the camera), so the solve is gtsam's LM
    # from the start, exactly.
    meas, stamps, _, camera, default = flight
    s = sm.SmootherSettings()
    turned = default.copy()
    turned[:3, :3] = default[:3, :3] @ gtsam.Rot3.Rx(1.5).matrix()
    b = sm._GraphBuilder(meas, stamps, camera, s)
    g = sm._batch_graph(b, sm._fill_initial([None] * meas.n_frames, turned), stamps)
    assert sm._gauss_newton(g, b, 1e-9).net is None  # the fallback ran
    params = sm._lm_params(b)
    params.setAbsoluteErrorTol(1e-9)
    lm = gtsam.LevenbergMarquardtOptimizer(g.graph, g.values, params).optimize()
    want = np.array([lm.atPose3(sm.X(i)).matrix() for i in range(meas.n_frames)])
    r = sm.smooth_batch(meas, stamps, [None] * meas.n_frames, camera, s, turned)
    assert np.array_equal(r.world_T_cam, want)


def _reference_evidence(meas, stamps, init, camera, s, default):
    """The Laplace evidence written out: LM converged, a multifrontal log det, every factor's
    normaliser from its own preintegrated covariance."""
    g, best = _converged(meas, stamps, init, camera, s, default)
    b = sm._GraphBuilder(meas, stamps, camera, s)
    tree = g.graph.linearize(best).eliminateMultifrontal()
    log_det = 0.0
    for k in range(g.graph.size()):
        f = g.graph.at(k)
        if isinstance(f, gtsam.ImuFactor):
            log_det += np.linalg.slogdet(f.preintegratedMeasurements().preintMeasCov())[1]
    assert b.m.n_frames - 1 == sum(
        isinstance(g.graph.at(k), gtsam.ImuFactor) for k in range(g.graph.size())
    )
    return -g.graph.error(best) - 0.5 * log_det - tree.logDeterminant()


def test_evidence_matches_its_definition_and_a_warm_start(flight):
    meas, stamps, init, camera, default = flight
    s = sm.SmootherSettings()
    got = sm.log_evidence(meas, stamps, init, camera, s, default)
    want = _reference_evidence(meas, stamps, init, camera, s, default)
    # The solve stops at lm_rel_tol: the error is then within 1e-5 of the optimum's.
    assert abs(got - want) < 1e-5 * abs(want)
    # Another prior's solution as the start: the same evidence, in fewer steps.
    graph = sm.EvidenceGraph(meas, stamps, sm._fill_initial(init, default), camera, s)
    _, other = graph.evidence(replace(s, cv_sigma_acc=4.0))
    warm, _ = graph.evidence(s, other)
    assert abs(warm - got) < 1e-5 * abs(want)
    # And a different prior weighs differently (the test can fail).
    assert abs(graph.evidence(replace(s, cv_sigma_acc=64.0))[0] - got) > 1.0
