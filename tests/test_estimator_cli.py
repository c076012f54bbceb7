"""The estimate/compare commands: outputs, round trips and bad input."""

import json

import numpy as np
import pytest
from conftest import estimator_scene
from signpose.estimator.camera import pinhole_camera
from signpose.maps.loader import bundled_map_path

from signpose.cli import main
from signpose.io.camera_file import write_camera_info
from signpose.io.observations import write_observations
from signpose.io.results import read_trajectory_csv
from signpose.io.tum import read_tum, write_tum


@pytest.fixture
def flight(tmp_path):
    sign_map, camera, frames, gt, _ = estimator_scene(n_frames=25, sigma_px=0.3, flat=False)
    obs = tmp_path / "obs.jsonl"
    write_observations(obs, frames)
    cam = tmp_path / "cam.yaml"
    write_camera_info(cam, camera)
    gt_path = tmp_path / "gt.tum"
    write_tum(gt_path, gt)
    return obs, cam, gt_path, gt


def test_estimate_then_compare_round_trip(flight, tmp_path, capsys):
    obs, cam, gt_path, gt = flight
    out = tmp_path / "out"
    args = [str(obs), "--map", str(bundled_map_path()), "--camera", str(cam), "--out", str(out)]
    assert main(["estimate", *args, "--method", "all", "--quiet"]) == 0
    for name in ("baseline", "pnp", "smoothed"):
        assert (out / f"{name}.tum").exists()
    csv = read_trajectory_csv(out / "trajectory.csv")
    sm = read_tum(out / "smoothed.tum")
    assert np.allclose(csv["smoothed"]["x_m"], sm.world_t_cam[:, 0], atol=1e-6)
    assert np.all(np.isfinite(csv["smoothed"]["sigma_x_m"]))
    assert np.allclose(sm.world_t_cam, gt.world_t_cam, atol=0.5)
    base = csv["baseline"]
    posed = ~np.isnan(base["x_m"])
    assert len(read_tum(out / "baseline.tum")) == posed.sum()
    report = json.loads((out / "report.json").read_text())
    assert report["coverage"]["smoothed"]["coverage"] == 1.0
    assert {"settings", "versions", "outliers"} <= set(report)
    capsys.readouterr()
    assert main(["compare", str(out), "--gt", str(gt_path)]) == 0
    table = capsys.readouterr().out
    assert "smoothed" in table and "MAE x" in table
    report = json.loads((out / "report.json").read_text())
    assert report["metrics"]["methods"]["smoothed"]["coverage"] == 1.0
    assert report["coverage"]["smoothed"]["posed"] == 25  # earlier content kept


def _run_error(argv, capsys) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    return err


def _estimate_argv(obs, sign_map, cam, out) -> list[str]:
    return [
        "estimate",
        str(obs),
        "--map",
        str(sign_map),
        "--camera",
        str(cam),
        "--out",
        str(out),
        "--quiet",
    ]


def test_malformed_observation_line(flight, tmp_path, capsys):
    obs, cam, _, _ = flight
    lines = obs.read_text().splitlines()
    lines[3] = '{"frame": 3, "signs": 5}'
    obs.write_text("\n".join(lines) + "\n")
    err = _run_error(
        _estimate_argv(obs, bundled_map_path(), cam, tmp_path / "o"),
        capsys,
    )
    assert "line 4" in err and str(obs) in err


def test_camera_size_mismatch(flight, tmp_path, capsys):
    obs, _, _, _ = flight
    cam = tmp_path / "small.yaml"
    write_camera_info(cam, pinhole_camera(1280, 720))
    err = _run_error(
        _estimate_argv(obs, bundled_map_path(), cam, tmp_path / "o"),
        capsys,
    )
    assert "1920x1080" in err and "1280x720" in err


def test_map_without_shared_code(flight, tmp_path, capsys):
    obs, cam, _, _ = flight
    m = tmp_path / "other.yaml"
    m.write_text(
        'frame: other\nsigns:\n  - code: "1111"\n    center_m: [0, 0, 10]\n'
        "    diameter_m: 0.8\n    sigma_m: 0.01\n"
    )
    err = _run_error(
        _estimate_argv(obs, m, cam, tmp_path / "o"),
        capsys,
    )
    assert str(m) in err and "no code" in err


def test_compare_without_estimates(tmp_path, capsys):
    gt = tmp_path / "gt.tum"
    gt.write_text("0 0 0 0 0 0 0 1\n")
    err = _run_error(["compare", str(tmp_path), "--gt", str(gt)], capsys)
    assert "signpose estimate" in err


def test_map_fixed_and_fixed_motion_prior_options(flight, tmp_path, capsys):
    obs, cam, _, _ = flight
    out = tmp_path / "fixed"
    argv = _estimate_argv(obs, bundled_map_path(), cam, out)
    assert main([*argv, "--map-fixed", "--fixed-motion-prior"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["settings"]["smoother"]["landmarks"] == "fixed"
    assert report["motion_prior"] is None
    statuses = set(read_trajectory_csv(out / "trajectory.csv")["smoothed"]["status"])
    assert statuses <= {"ok", "weak", "bridged", "suspect"} and "ok" in statuses


def _edited_map(tmp_path, edit) -> str:
    from dataclasses import replace

    from signpose.maps.loader import load_map, write_map

    m = load_map(bundled_map_path())
    path = tmp_path / "edited.yaml"
    write_map(path, replace(m, signs=tuple(edit(s) for s in m.signs)))
    return path


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        (lambda s: s if s.code != "0010" else _flipped(s, normal=True), ("0010", "behind")),
        (lambda s: s if s.code != "0100" else _flipped(s, normal=False), ("0100", "orientation")),
    ],
)
def test_map_orientation_inconsistent_with_the_flight(flight, tmp_path, capsys, edit, words):
    obs, cam, _, _ = flight
    path = _edited_map(tmp_path, edit)
    err = _run_error(_estimate_argv(obs, path, cam, tmp_path / "o"), capsys)
    assert str(path) in err and all(w in err for w in words)


def _flipped(sign, normal: bool):
    from dataclasses import replace

    if normal:  # the normal into the face: the flight sees the sign from behind
        return replace(sign, normal=-sign.normal)
    return replace(sign, up=-sign.up)  # turned 180 degrees about its normal


def test_flight_sharing_fewer_than_three_signs(flight, tmp_path, capsys):
    obs, cam, _, _ = flight
    m = tmp_path / "two.yaml"
    m.write_text(
        'frame: two\nsigns:\n  - code: "0001"\n    center_m: [-1.8, 0, 17.5]\n'
        '    diameter_m: 0.8\n    sigma_m: 0.01\n  - code: "0010"\n    center_m: [0.2, 0.3, 18]\n'
        "    diameter_m: 0.8\n    sigma_m: 0.01\n"
    )
    err = _run_error(_estimate_argv(obs, m, cam, tmp_path / "o"), capsys)
    assert str(m) in err and "0001, 0010" in err and "at least 3" in err
