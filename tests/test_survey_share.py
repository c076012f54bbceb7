"""The smoothed sigmas' survey share has the survey's shape: with near-exact keypoints
and signs held rigid, a pose's sigma is the sd that the map's N(0, sigma_m) per centre
axis gives it through the smoother, ``sqrt(diag(J Sigma_m J^T))`` (J: the positions'
response to each sign centre), neither less (an error shared by a sign's keypoints
taken as independent) nor more. So pooled over survey draws error / sigma is unit,
though one flight's draw moves all its poses together (scripts/eval_flight.py
``--survey-response``)."""

from dataclasses import replace

import numpy as np
import pytest
from conftest import estimator_scene
from signpose.estimator.marginals import Conditional, selected_covariances_and_shares
from signpose.estimator.smoother import (
    SmootherSettings,
    collect_measurements,
    default_pose,
    smooth_batch,
)
from signpose.maps.loader import SignMap

# Near-exact keypoints and ties: the pixels' and the printing tolerance's shares of a
# pose's variance vanish beside the survey's 1 cm per centre (sigma / share 1.003-1.02
# at 2e-4 px; 1.15-2.95 at 0.02 px, whose pose error alone is 19 mm on this scene; with
# the default 3 mm ties 1.06-1.15 at 2e-3 px: the ties' share).
SHARP_SIGMA_PX = 2e-4
EXACT_TIE_M = 1e-5
STEP_M = 1e-3  # the solve is linear in the survey at this scale
TIGHT_REL_TOL = 1e-12  # solved to convergence: the default 1e-5 stops within a step


def _response(frames, sign_map: SignMap, camera, settings: SmootherSettings, init) -> np.ndarray:
    """(N, 3, 3K) smoothed positions' response to each sign centre's axes [m / m]."""
    stamps = np.array([f.stamp_ns for f in frames], float) * 1e-9
    default = default_pose(sign_map)
    quiet = replace(settings, compute_sigmas=False, lm_rel_tol=TIGHT_REL_TOL)

    def positions(m: SignMap) -> np.ndarray:
        meas = collect_measurements(frames, m, camera)
        return smooth_batch(meas, stamps, init, camera, quiet, default).world_T_cam[:, :3, 3]

    base = positions(sign_map)
    J = np.zeros((len(base), 3, 3 * len(sign_map.signs)))
    for k, sign in enumerate(sign_map.signs):
        for axis in range(3):
            signs = list(sign_map.signs)
            centre = np.asarray(sign.center_m, float).copy()
            centre[axis] += STEP_M
            signs[k] = replace(sign, center_m=centre)
            J[:, :, 3 * k + axis] = (
                positions(replace(sign_map, signs=tuple(signs))) - base
            ) / STEP_M
    return J


@pytest.mark.parametrize(("landmarks", "honest"), [("rigid", True), ("keypoints", False)])
def test_smoothed_sigma_is_the_survey_share_with_sharp_keypoints(landmarks, honest):
    sign_map, camera, frames, gt, _ = estimator_scene(
        n_frames=20, sigma_px=SHARP_SIGMA_PX, seed=3, flat=False
    )
    init = list(gt.world_T_cam())
    stamps = np.array([f.stamp_ns for f in frames], float) * 1e-9
    s = SmootherSettings(landmarks=landmarks, rigid_tie_sigma_m=EXACT_TIE_M)
    J = _response(frames, sign_map, camera, s, init)
    sigma_m = np.repeat([sign.sigma_m for sign in sign_map.signs], 3)
    share = np.sqrt(np.einsum("nij,nij->ni", J * sigma_m, J * sigma_m))
    meas = collect_measurements(frames, sign_map, camera)
    sigma = smooth_batch(meas, stamps, init, camera, s, default_pose(sign_map)).sigma_xyz
    ratio = sigma / share
    # rigid: 1.003-1.02; keypoints: ~0.5, each keypoint's own 1 cm prior averages
    # a sign's shared offset away.
    inside = bool(np.all((ratio >= 0.98) & (ratio <= 1.05)))
    assert inside == honest, (landmarks, ratio.min(), ratio.max())
    # Pooled over survey draws, the error / sigma of every pose is then unit: one
    # flight's draw moves all its poses together, so a single draw may not be.
    rng = np.random.default_rng(7)
    draws = rng.normal(size=(4000, len(sigma_m))) * sigma_m
    z = np.einsum("nij,kj->kni", J, draws) / sigma[None]
    rms = np.sqrt(np.mean(z**2, axis=(0, 1)))
    assert bool(np.all(np.abs(rms - 1.0) < 0.05)) == honest, (landmarks, rms)


def test_survey_sigma_is_the_sd_the_centres_response_gives():
    """``survey_sigma_xyz`` (from the joint covariance: Sigma_xP Lambda_P Sigma_Px) is the
    finite-difference share at the default 3 mm ties and 0.3 px, where the pixels and the
    ties add 10-180 % to the sigma."""
    sign_map, camera, frames, gt, _ = estimator_scene(n_frames=20, sigma_px=0.3, seed=3, flat=False)
    init = list(gt.world_T_cam())
    stamps = np.array([f.stamp_ns for f in frames], float) * 1e-9
    s = SmootherSettings()
    J = _response(frames, sign_map, camera, s, init)
    sigma_m = np.repeat([sign.sigma_m for sign in sign_map.signs], 3)
    share = np.sqrt(np.einsum("nij,nij->ni", J * sigma_m, J * sigma_m))
    meas = collect_measurements(frames, sign_map, camera)
    r = smooth_batch(meas, stamps, init, camera, s, default_pose(sign_map))
    ratio = r.survey_sigma_xyz / share
    assert np.all((ratio > 0.97) & (ratio < 1.03)), (ratio.min(), ratio.max())  # 0.980-1.001
    assert np.all(r.survey_sigma_xyz < r.sigma_xyz)
    # the survey as exact: no share
    fixed = smooth_batch(
        meas, stamps, init, camera, replace(s, landmarks="fixed"), r.world_T_cam[0]
    )
    assert np.all(fixed.survey_sigma_xyz < 1e-3 * share)


def test_prior_shares_match_a_dense_inverse_on_a_random_chordal_net():
    """Sigma_iP Lambda_P Sigma_Pi for every block, against the dense inverse: a banded
    chain of blocks with an arrow of three dense tail blocks, priors on two of them."""
    rng = np.random.default_rng(8)
    dims = [3, 2, 4, 1, 3, 2, 3, 2, 2, 3, 5, 3]
    n_chain = 9
    off = np.concatenate([[0], np.cumsum(dims)])
    rows = []
    for k in range(len(dims)):
        cols = [k] + [j for j in (k + 1, k + 2) if j < n_chain] + list(range(n_chain, len(dims)))
        for _ in range(3):
            row = np.zeros(off[-1])
            for j in cols:
                row[off[j] : off[j + 1]] = rng.normal(size=dims[j])
            rows.append(row)
    H = np.array(rows).T @ np.array(rows) + 0.1 * np.eye(off[-1])
    R = np.linalg.cholesky(H).T
    conds = []
    for k in range(len(dims)):
        block = [(j, R[off[k] : off[k + 1], off[j] : off[j + 1]]) for j in range(k + 1, len(dims))]
        parents = [(j, b) for j, b in block if np.abs(b).max() > 0]
        S = np.hstack([b for _, b in parents]) if parents else np.zeros((dims[k], 0))
        conds.append(
            Conditional(
                k, R[off[k] : off[k + 1], off[k] : off[k + 1]], tuple(j for j, _ in parents), S
            )
        )
    priors = {}
    for k in (9, 11):
        a = rng.normal(size=(dims[k], dims[k]))
        priors[k] = a @ a.T + np.eye(dims[k])
    got, shares = selected_covariances_and_shares(conds, n_chain, list(range(len(dims))), priors)
    Sigma = np.linalg.inv(H)
    for k in range(len(dims)):
        blk = slice(off[k], off[k + 1])
        want = sum(
            Sigma[blk, off[j] : off[j + 1]] @ lam @ Sigma[off[j] : off[j + 1], blk]
            for j, lam in priors.items()
        )
        assert np.abs(shares[k] - want).max() <= 1e-9 * np.abs(want).max(), k
        assert np.abs(got[k] - Sigma[blk, blk]).max() <= 1e-9 * np.abs(Sigma[blk, blk]).max(), k
