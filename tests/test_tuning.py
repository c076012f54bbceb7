"""The motion prior chosen from the flight."""

import json

import numpy as np
from conftest import estimator_scene
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.smoother import SmootherSettings, collect_measurements, default_pose
from signpose.estimator.trajectory import Trajectory
from signpose.estimator.tuning import TuningSettings, _evidence_score, tune_motion_prior

from signpose.io.results import write_outputs
from signpose.sim.observations import SyntheticSettings, synthesize_observations


def test_a_hovering_camera_gets_the_stiffest_prior():
    sign_map, camera, _, gt, _ = estimator_scene(n_frames=40, flat=False)
    still = np.repeat(gt.world_T_cam()[20][None], 40, axis=0)
    truth = Trajectory.from_matrices(np.arange(40) / 30.0, still)
    frames, _ = synthesize_observations(
        sign_map, camera, truth, np.random.default_rng(0), SyntheticSettings(sigma_px=0.3)
    )
    meas = collect_measurements(frames, sign_map, camera)
    tuning = TuningSettings(position_grid=(0.25, 2.0, 16.0))
    choice = tune_motion_prior(
        meas, truth.stamps_s, still, camera, SmootherSettings(), default_pose(sign_map), tuning
    )
    assert choice.position == 0.25 and choice.default_position == 2.0
    assert [v for _, v, _ in choice.scores] == [0.25, 2.0, 16.0]
    assert choice.settings.cv_sigma_acc == 0.25


def test_the_chosen_prior_is_in_the_report(tmp_path):
    sign_map, camera, frames, _, _ = estimator_scene(n_frames=30, sigma_px=0.3, flat=False)
    tuning = TuningSettings(position_grid=(0.5, 2.0))
    s = EstimatorSettings(methods=("smoothed",), tuning=tuning)
    r = estimate_trajectories(frames, sign_map, camera, s, progress=False)
    write_outputs(tmp_path, r)
    motion = json.loads((tmp_path / "report.json").read_text())["motion_prior"]
    assert motion["position"] in (0.5, 2.0) and motion["default_position"] == 2.0
    assert len(motion["scores"]) == 2
    off = estimate_trajectories(
        frames,
        sign_map,
        camera,
        EstimatorSettings(methods=("smoothed",), tune_motion=False),
        progress=False,
    )
    assert off.motion is None


class _Flaky:
    """An EvidenceGraph stand-in: indeterminate from ``bad`` starts."""

    def __init__(self, bad):
        self.bad, self.calls = bad, []

    def evidence(self, trial, start):
        self.calls.append(start)
        if start in self.bad:
            raise RuntimeError("Indeterminate linear system detected")
        return 5.0, "solution"


def test_an_indeterminate_candidate_is_solved_again_cold_or_never_chosen():

    g = _Flaky(bad={"warm"})
    assert _evidence_score(g, None, "warm") == (-5.0, "solution")
    assert g.calls == ["warm", None]
    g = _Flaky(bad={"warm", None})
    score, start = _evidence_score(g, None, "warm")
    assert score == float("inf") and start == "warm"
    g = _Flaky(bad=set())
    assert _evidence_score(g, None, None) == (-5.0, "solution") and g.calls == [None]
