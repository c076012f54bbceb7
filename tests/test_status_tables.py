"""Pose status shares and unit-named errors in the table, summary.csv, report.json, plots."""

import csv
import json
import re
from dataclasses import replace

import numpy as np
import pytest
from conftest import estimator_scene
from matplotlib.image import imread
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.metrics import compute_metrics, format_table
from signpose.estimator.trajectory import Trajectory
from signpose.maps import bundled_map_path
from signpose.maps.loader import load_map

from signpose import batch
from signpose.io.results import (
    CSV_HEADER,
    compare_dir,
    read_trajectory_csv,
    status_shares,
    write_outputs,
)
from signpose.io.tum import write_tum
from signpose.pipeline import RunResult
from signpose.plots import STATUS_COLORS, PlotData, plot_signs_per_frame, plot_views

BRIDGED_FRAMES = (14, 15, 16)  # frames without any sign: bridged by the motion prior
N_FRAMES = 30


@pytest.fixture(scope="module")
def three_bridged(tmp_path_factory):
    """(estimate folder, EstimateResult): a 30-frame flight whose frames 14-16 see no sign."""
    sign_map, camera, frames, gt, _ = estimator_scene(
        n_frames=N_FRAMES, sigma_px=0.2, seed=4, flat=False
    )
    for k in BRIDGED_FRAMES:
        frames[k] = replace(frames[k], signs=())
    result = estimate_trajectories(
        frames, sign_map, camera, EstimatorSettings(methods=("pnp", "smoothed")), progress=False
    )
    out = tmp_path_factory.mktemp("three_bridged")
    write_outputs(out, result)
    write_tum(out / "gt.tum", gt)
    compare_dir(out, out / "gt.tum")
    return out, result


def test_three_bridged_poses_are_3_of_n_in_the_table_and_report(three_bridged):
    out, result = three_bridged
    smoothed = [st.value for st in result.methods["smoothed"].status]
    assert [k for k, t in enumerate(smoothed) if t == "bridged"] == list(BRIDGED_FRAMES)
    report = json.loads((out / "report.json").read_text())
    table = report["metrics"]["table"].splitlines()
    head = table[0].split()
    assert head[-4:] == ["ok", "weak", "bridged", "suspect"] and "deg" in head
    row = next(line for line in table if line.startswith("smoothed")).split()
    assert row[-2] == f"{100 * 3 / N_FRAMES:.1f}%"  # ..., ok, weak, bridged, suspect
    pnp = next(line for line in table if line.startswith("pnp")).split()
    assert pnp[-2] == "0.0%"  # PnP has no pose there (few_points), none bridged
    metrics = report["metrics"]["methods"]["smoothed"]
    assert {"mae_xyz_m", "ate_rmse_m", "ate_rmse_aligned_m", "rot_rmse_deg"} <= set(metrics)
    assert not {"mae_xyz", "ate_rmse", "ate_rmse_aligned"} & set(metrics)
    assert 0 < metrics["rot_rmse_deg"] < 1.0
    assert report["versions"]["gtsam"] not in ("", "unknown")
    assert report["versions"]["cv2"] not in ("", "unknown")


def test_trajectory_csv_names_units_and_its_status_is_a_token(three_bridged):
    out, _ = three_bridged
    lines = (out / "trajectory.csv").read_text().splitlines()
    assert lines[0] == (
        "method,frame,t_s,x_m,y_m,z_m,qw,qx,qy,qz,sigma_x_m,sigma_y_m,sigma_z_m,signs_used,status"
    )
    rows = list(csv.reader(lines[1:]))
    assert all(len(r) == len(CSV_HEADER) for r in rows)
    tokens = {r[-1] for r in rows}
    assert all(re.fullmatch(r"[a-z_]+", t) for t in tokens), tokens
    assert {"bridged", "few_points"} <= tokens
    cols = read_trajectory_csv(out / "trajectory.csv")
    assert np.isnan(cols["pnp"]["x_m"][BRIDGED_FRAMES[0]])
    assert np.isfinite(cols["smoothed"]["x_m"][BRIDGED_FRAMES[0]])


def test_a_trajectory_csv_with_the_old_header_reads_under_the_new_names(tmp_path):
    old = "method,frame,t,x,y,z,qw,qx,qy,qz,sigma_x,sigma_y,sigma_z,signs_used,status\n"
    row = "smoothed,0,0.5,1.0,2.0,3.0,1,0,0,0,0.1,,0.3,4,ok\n"
    (tmp_path / "trajectory.csv").write_text(old + row)
    cols = read_trajectory_csv(tmp_path / "trajectory.csv")["smoothed"]
    assert cols["t_s"][0] == 0.5 and cols["z_m"][0] == 3.0 and np.isnan(cols["sigma_y_m"][0])
    assert list(cols["status"]) == ["ok"]


def test_summary_csv_has_status_shares_bridged_count_and_errors(three_bridged, tmp_path):
    out, result = three_bridged
    report = json.loads((out / "report.json").read_text())
    shares = {name: status_shares(m) for name, m in result.methods.items()}
    outcome = batch.FlightOutcome(
        "f1",
        batch.FlightStatus.OK,
        frames=N_FRAMES,
        coverage={"pnp": 0.9, "smoothed": 1.0},
        position_rmse_m={"smoothed": 0.05},
        pose_status=shares,
        errors={k: batch.errors_from_metrics(v) for k, v in report["metrics"]["methods"].items()},
    )
    failed = batch.FlightOutcome("f2", batch.FlightStatus.FAILED, message="no such file")
    batch.write_summary(tmp_path / "summary.csv", [outcome, failed])
    with open(tmp_path / "summary.csv", newline="") as f:
        rows = {r["flight"]: r for r in csv.DictReader(f)}
    row = rows["f1"]
    assert row["bridged_smoothed"] == "3" and row["bridged_pnp"] == "0"
    assert float(row["share_bridged_smoothed"]) == pytest.approx(3 / N_FRAMES, abs=1e-4)
    assert sum(float(row[f"share_{t}_smoothed"]) for t in batch.STATUS_TOKENS) == pytest.approx(1)
    metrics = report["metrics"]["methods"]["smoothed"]
    for axis, k in zip("xyz", range(3), strict=True):
        assert float(row[f"mae_{axis}_m_smoothed"]) == pytest.approx(
            metrics["mae_xyz_m"][k], abs=1e-4
        )
    assert float(row["ate_aligned_m_smoothed"]) == pytest.approx(
        metrics["ate_rmse_aligned_m"], abs=1e-4
    )
    assert float(row["rot_rmse_deg_smoothed"]) == pytest.approx(metrics["rot_rmse_deg"], abs=1e-4)
    assert rows["f2"]["bridged_smoothed"] == "" and rows["f2"]["share_ok_smoothed"] == ""


def test_rotation_error_in_degrees_and_table_without_statuses():
    n = 10
    stamps = np.arange(n) * 0.1
    pos = np.stack([np.arange(n, dtype=float), np.zeros(n), np.zeros(n)], axis=1)
    gt = Trajectory(stamps, pos, np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)))
    half = np.radians(2.0) / 2  # every estimate turned 2 deg about z
    est = Trajectory(stamps, pos, np.tile([0.0, 0.0, np.sin(half), np.cos(half)], (n, 1)))
    m = compute_metrics(est, gt)
    assert m.rot_rmse_deg == pytest.approx(2.0, abs=1e-6)
    table = format_table({"smoothed": m})
    assert "bridged" not in table and "2.0000" in table
    dashed = format_table({"smoothed": m}, {"pnp": {"ok": 1.0}})
    assert dashed.splitlines()[-1].split()[-4:] == ["-", "-", "-", "-"]


def _status_plot_data(tokens: list[str]) -> PlotData:
    n = len(tokens)
    stamps = np.arange(n) * 0.1
    pos = np.stack([np.linspace(-5, 5, n), np.full(n, -12.0), np.full(n, 8.0)], axis=1)
    traj = Trajectory(stamps, pos, np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)))
    return PlotData(
        sign_map=load_map(bundled_map_path()),
        trajectories={"smoothed": traj},
        frame_stamps_s=stamps,
        signs_per_frame=np.array([0 if t == "bridged" else 3 for t in tokens]),
        statuses={"smoothed": tuple(tokens)},
    )


def _has_colour(png, hex_colour: str) -> bool:
    rgb = np.array([int(hex_colour[i : i + 2], 16) for i in (1, 3, 5)]) / 255
    img = imread(png)[..., :3]
    return bool(np.any(np.all(np.abs(img - rgb) < 0.02, axis=-1)))


def test_plots_colour_poses_by_status(tmp_path):
    suspect = STATUS_COLORS["suspect"]
    tokens = ["ok"] * 12 + ["bridged"] * 3 + ["suspect"] + ["ok"] * 4
    plot_views(tmp_path / "views.png", _status_plot_data(tokens))
    plot_signs_per_frame(tmp_path / "signs.png", _status_plot_data(tokens))
    assert _has_colour(tmp_path / "views.png", suspect)
    assert _has_colour(tmp_path / "signs.png", suspect)
    assert _has_colour(tmp_path / "signs.png", STATUS_COLORS["bridged"])
    clean = ["ok"] * 20
    plot_views(tmp_path / "views_ok.png", _status_plot_data(clean))
    plot_signs_per_frame(tmp_path / "signs_ok.png", _status_plot_data(clean))
    assert not _has_colour(tmp_path / "views_ok.png", suspect)
    assert not _has_colour(tmp_path / "signs_ok.png", suspect)
    assert _has_colour(tmp_path / "signs_ok.png", STATUS_COLORS["ok"])


def test_run_flight_keeps_the_runs_status_shares_and_errors(tmp_path, monkeypatch):
    gt_metrics = {
        "mae_xyz_m": [0.01, 0.02, 0.03],
        "ate_rmse_m": 0.05,
        "ate_rmse_aligned_m": 0.04,
        "rot_rmse_deg": 0.5,
    }

    def fake_run(input_path, sign_map, out_dir, **kw):
        return RunResult(
            out_dir=out_dir,
            n_frames=20,
            coverage={"smoothed": 1.0},
            position_rmse_m={"smoothed": 0.05},
            comparison={"smoothed": gt_metrics},
            comparison_table="",
            timing_s={"total": 1.0},
            fps=20.0,
            problems=(),
            files=(),
            status={"smoothed": {"ok": 0.85, "weak": 0.0, "bridged": 0.15}},
        )

    monkeypatch.setattr(batch, "run", fake_run)
    (tmp_path / "video.mp4").write_bytes(b"")
    job = batch.FlightJob(
        flight="f",
        input_path=str(tmp_path / "video.mp4"),
        map_path=str(bundled_map_path()),
        out_dir=str(tmp_path / "out"),
    )
    outcome = batch.run_flight(job)
    assert outcome.status is batch.FlightStatus.OK, outcome.message
    assert outcome.bridged("smoothed") == 3
    assert outcome.errors["smoothed"] == {
        "mae_x_m": 0.01,
        "mae_y_m": 0.02,
        "mae_z_m": 0.03,
        "ate_aligned_m": 0.04,
        "rot_rmse_deg": 0.5,
    }
    assert batch.read_done(tmp_path / "out").pose_status == outcome.pose_status
