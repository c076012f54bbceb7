"""report.json says how much of each smoothed pose's variance is the map's survey error."""

from dataclasses import replace

import numpy as np
from conftest import estimator_scene
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories

from signpose.io.results import report_dict


def test_the_survey_share_of_the_smoothed_variance_is_reported():
    sign_map, camera, frames, _, _ = estimator_scene(n_frames=30, sigma_px=0.2, seed=2)
    s = replace(EstimatorSettings(), methods=("pnp", "smoothed"))
    surveyed = estimate_trajectories(frames, sign_map, camera, s, False)
    share = report_dict(surveyed)["coverage"]["smoothed"]["survey_share"]
    assert 0.0 < share["of_variance_median"] < 1.0
    m = surveyed.methods["smoothed"]
    ok = m.valid
    assert np.all(m.survey_sigma_xyz[ok] <= m.sigma_xyz[ok] + 1e-12)
    # PnP has no such split; the map taken as exact leaves no survey share
    assert "survey_share" not in report_dict(surveyed)["coverage"]["pnp"]
    fixed = replace(s, smoother=replace(s.smoother, landmarks="fixed"))
    exact = estimate_trajectories(frames, sign_map, camera, fixed, False)
    share = report_dict(exact)["coverage"]["smoothed"].get("survey_share")
    assert share is None or share["of_variance_median"] < 1e-6
