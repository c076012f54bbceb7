"""Pose status tokens (ok / weak / bridged / suspect) and per-frame PnP sigmas."""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import estimator_scene
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.perframe import PoseFailure
from signpose.estimator.status import (
    PoseStatus,
    StatusSettings,
    classify,
    state_from_token,
)

from signpose.cli.run import print_result
from signpose.io.results import read_trajectory_csv, write_outputs
from signpose.pipeline import RunResult


@pytest.mark.parametrize(
    ("keypoints", "sigma", "chi2", "dof", "expected"),
    [
        (0, np.inf, 0.0, 0, PoseStatus.BRIDGED),
        (8, 0.05, 10.0, 16, PoseStatus.OK),
        (8, 0.05, 60.0, 16, PoseStatus.SUSPECT),
        (3, 0.05, 1.0, 6, PoseStatus.WEAK),
        (8, 0.8, 10.0, 16, PoseStatus.WEAK),
        (8, np.inf, 10.0, 16, PoseStatus.WEAK),
    ],
)
def test_classify(keypoints, sigma, chi2, dof, expected):
    assert classify(keypoints, sigma, chi2, dof, StatusSettings()) is expected


def test_tokens_round_trip():
    for state in (*PoseStatus, *PoseFailure):
        assert state_from_token(state.value) is state
    with pytest.raises(ValueError, match="unknown pose status"):
        state_from_token("bridged: no sign seen")


def test_a_frame_with_five_times_the_noise_is_suspect_and_files_carry_tokens(tmp_path):
    sign_map, camera, frames, gt, _ = estimator_scene(n_frames=40, sigma_px=0.3, seed=3, flat=False)
    rng = np.random.default_rng(0)
    f = frames[20]
    noisy = tuple(
        replace(
            o,
            keypoints_px={
                k: (u + rng.normal(0, 1.5), v + rng.normal(0, 1.5))
                for k, (u, v) in o.keypoints_px.items()
            },
        )
        for o in f.signs
    )
    frames[20] = replace(f, signs=noisy)
    frames[30] = replace(frames[30], signs=())
    r = estimate_trajectories(
        frames, sign_map, camera, EstimatorSettings(methods=("pnp", "smoothed")), progress=False
    )
    for name in ("pnp", "smoothed"):
        m = r.methods[name]
        assert m.status[20] is PoseStatus.SUSPECT
        assert sum(st in (PoseStatus.OK, PoseStatus.WEAK) for st in m.status) >= 35
    assert r.methods["smoothed"].status[30] is PoseStatus.BRIDGED
    assert r.methods["pnp"].status[30] is PoseFailure.FEW_POINTS
    # Per-frame PnP has its sigma now: finite where posed.
    pnp = r.methods["pnp"]
    assert np.all(np.isfinite(pnp.sigma_xyz[pnp.valid])) and np.all(pnp.sigma_xyz[pnp.valid] > 0)
    write_outputs(tmp_path, r)
    csv = read_trajectory_csv(tmp_path / "trajectory.csv")
    assert csv["smoothed"]["status"][20] == "suspect" and csv["pnp"]["status"][30] == "few_points"
    assert np.isfinite(csv["pnp"]["sigma_x_m"][0])
    report = json.loads((tmp_path / "report.json").read_text())
    shares = report["coverage"]["smoothed"]["status"]
    assert shares["bridged"] == pytest.approx(1 / 40) and shares["suspect"] == pytest.approx(1 / 40)
    assert sum(shares.values()) == pytest.approx(1.0)


def test_a_frame_with_one_centre_is_weak_and_its_neighbours_ok():
    sign_map, camera, frames, _, _ = estimator_scene(n_frames=30, sigma_px=0.3, seed=2, flat=False)
    one = frames[12].signs[0]
    frames[12] = replace(
        frames[12], signs=(replace(one, keypoints_px={"center": one.keypoints_px["center"]}),)
    )
    r = estimate_trajectories(
        frames, sign_map, camera, EstimatorSettings(methods=("smoothed",)), progress=False
    )
    status = r.methods["smoothed"].status
    assert status[12] is PoseStatus.WEAK
    assert status[11] is PoseStatus.OK and status[13] is PoseStatus.OK


def test_run_summary_prints_the_status_shares(capsys):
    result = RunResult(
        out_dir=Path("out"),
        n_frames=4,
        coverage={"smoothed": 1.0},
        position_rmse_m={},
        comparison=None,
        comparison_table="",
        timing_s={"total": 1.0},
        fps=4.0,
        problems=(),
        files=(),
        status={"smoothed": {"ok": 0.75, "weak": 0.0, "bridged": 0.25}},
    )
    print_result(result, quiet=True)
    lines = capsys.readouterr().out.splitlines()
    assert "pose status: smoothed ok 75.0% weak 0.0% bridged 25.0%" in lines
