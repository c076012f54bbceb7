"""No silent jumps: projection Jacobians, chi-square quantiles and the innovation test."""

import json
from dataclasses import replace

import gtsam
import numpy as np
import pytest
from gtsam.utils.numerical_derivative import numericalDerivative11
from signpose.estimator.camera import pinhole_camera
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.projection import (
    chi2_quantile_even,
    chi2_survival_even,
    pixels_and_pose_jacobian,
)
from signpose.estimator.robust import OutlierSettings, RejectionTest
from signpose.estimator.smoother import SmootherSettings

from signpose.io.results import write_outputs
from signpose.sim.scenarios import ScenarioSettings, build_scenario

SMALL = ScenarioSettings(
    n_frames=90, stretch_start=30, stretch_frames=16, wrong_code_rate=0.0, false_rate=0.0
)


def test_pose_jacobian_matches_numerical_derivative():
    camera = pinhole_camera(1920, 1080, 60.0)
    rng = np.random.default_rng(0)
    pose = gtsam.Pose3(gtsam.Rot3.RzRyRx(0.1, -0.2, 0.3), np.array([1.0, 2.0, -20.0]))
    points = rng.normal(size=(5, 3)) * 2.0
    _, J, J_point = pixels_and_pose_jacobian(camera, pose.matrix(), points)

    def pixels(T: gtsam.Pose3) -> np.ndarray:
        return pixels_and_pose_jacobian(camera, T.matrix(), points)[0].reshape(-1)

    assert np.allclose(J.reshape(-1, 6), numericalDerivative11(pixels, pose), rtol=1e-4, atol=1e-3)
    for k in range(len(points)):

        def pixels_of_point(p: np.ndarray) -> np.ndarray:
            return pixels_and_pose_jacobian(camera, pose.matrix(), p[None])[0].reshape(-1)

        numeric = numericalDerivative11(pixels_of_point, points[k])
        assert np.allclose(J_point[k], numeric, rtol=1e-4, atol=1e-3)


@pytest.mark.parametrize(
    ("p", "dof", "expected"), [(0.999, 2, 13.8155), (0.95, 4, 9.4877), (0.999, 8, 26.1245)]
)
def test_chi2_quantile_even_matches_tables(p, dof, expected):
    x = chi2_quantile_even(p, dof)
    assert abs(x - expected) < 1e-3
    assert abs(chi2_survival_even(x, dof) - (1 - p)) < 1e-9


def _run(scenario, **kw):
    s = EstimatorSettings(
        methods=("smoothed",), smoother=SmootherSettings(compute_sigmas=True), **kw
    )
    return estimate_trajectories(
        scenario.frames, scenario.sign_map, scenario.camera, s, progress=False
    )


def test_a_wrong_code_among_two_centre_only_signs_is_rejected_by_the_innovation_test(tmp_path):
    # RANSAC cannot run on two centres; the neighbours' prediction catches the wrong code.
    scenario = build_scenario(np.random.default_rng(1), faults=True, settings=SMALL)
    planted = [w for w in scenario.wrong_code if w[0] == SMALL.stretch_start + 3]
    assert planted, "the scenario plants a wrong code on the stretch's 4th frame"
    r = _run(scenario)
    hits = [
        x
        for x in r.outliers.rejected
        if x.test is RejectionTest.INNOVATION and (x.frame, x.code) == planted[0][:2]
    ]
    assert len(hits) == 1 and hits[0].statistic > hits[0].threshold
    write_outputs(tmp_path, r)
    listed = json.loads((tmp_path / "report.json").read_text())["outliers"]["rejected"]
    frame, code = planted[0][:2]
    assert {"frame": frame, "code": code, "test": "innovation"}.items() <= next(
        x for x in listed if (x["frame"], x["code"]) == (frame, code)
    ).items()
    clean = _run(build_scenario(np.random.default_rng(1), faults=False, settings=SMALL))
    err = np.linalg.norm(
        r.methods["smoothed"].world_T_cam[:, :3, 3] - scenario.truth.world_t_cam, axis=1
    )
    err_clean = np.linalg.norm(
        clean.methods["smoothed"].world_T_cam[:, :3, 3] - scenario.truth.world_t_cam, axis=1
    )
    assert err.max() < 1.5 * err_clean.max() + 0.02


def test_without_the_innovation_test_the_wrong_code_pulls_the_stretch_further():
    scenario = build_scenario(np.random.default_rng(1), faults=True, settings=SMALL)
    a, b = scenario.stretch
    errs = []
    for kw in ({}, {"outliers": OutlierSettings(rounds=0), "final_kernel": "huber"}):
        r = _run(scenario, **kw)
        p = r.methods["smoothed"].world_T_cam[a:b, :3, 3]
        errs.append(np.linalg.norm(p - scenario.truth.world_t_cam[a:b], axis=1).max())
    assert errs[1] > 1.2 * errs[0]


@pytest.mark.parametrize("kernel", ["tukey", "gnc"])
def test_final_kernels_reject_a_gross_outlier_outright(kernel):
    scenario = build_scenario(np.random.default_rng(2), faults=False, settings=SMALL)
    frames = list(scenario.frames)
    f = frames[60]
    bad = replace(f.signs[0], keypoints_px={"center": (f.signs[0].center_px[0] + 40.0, 300.0)})
    frames[60] = replace(f, signs=(bad, *f.signs[1:]))
    # No innovation rounds and no PnP gate: only the final kernel can remove it.
    r = _run(
        replace(scenario, frames=frames),
        outliers=OutlierSettings(rounds=0),
        final_kernel=kernel,
        gate_px=0.0,
    )
    test = RejectionTest.GNC if kernel == "gnc" else RejectionTest.TUKEY
    assert (60, bad.code) in {(x.frame, x.code) for x in r.outliers.rejected if x.test is test}
