"""A principal point the video cannot check: its stated sigma in the pose sigmas.

A principal point ``c`` px off moves every keypoint by ``c`` px; the pose fit
takes that up partly as a rotation and partly as a shift of the camera across
its view (``estimator.intrinsics_share``). The share added for
``principal_sigma_px`` must match the position change a shifted principal
point really makes (to first order), cover the error it leaves, and change
nothing at its default 0.
"""

import json
from dataclasses import replace

import numpy as np
import pytest
from conftest import estimator_scene
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.intrinsics_share import principal_point_response, with_principal_share
from signpose.estimator.status import PoseStatus
from signpose.maps.loader import write_map

from signpose.cli import main
from signpose.io.camera_file import write_camera_info
from signpose.io.observations import write_observations

SHIFT_PX = 5.0  # small: a first-order check
FAULT_PX = 15.0  # scripts/eval_setup_faults.py's principal_15px


def _shifted(camera, du_px: float, dv_px: float):
    K = camera.K.copy()
    K[0, 2] += du_px
    K[1, 2] += dv_px
    return replace(camera, K=K)


def _settings(principal_sigma_px: float = 0.0) -> EstimatorSettings:
    s = replace(EstimatorSettings(), methods=("pnp", "smoothed"))
    s = replace(s, principal_sigma_px=principal_sigma_px)
    return replace(s, smoother=replace(s.smoother, landmarks="fixed"))


@pytest.fixture(scope="module")
def flight():
    sign_map, camera, frames, gt, _ = estimator_scene(n_frames=30, sigma_px=0.2, seed=5)
    right = estimate_trajectories(frames, sign_map, camera, _settings(), False)
    moved_u = estimate_trajectories(
        frames, sign_map, _shifted(camera, SHIFT_PX, 0.0), _settings(), False
    )
    moved_v = estimate_trajectories(
        frames, sign_map, _shifted(camera, 0.0, SHIFT_PX), _settings(), False
    )
    return sign_map, camera, frames, gt, right, moved_u, moved_v


@pytest.mark.parametrize("name", ["pnp", "smoothed"])
def test_the_share_is_the_position_change_to_first_order(flight, name):
    sign_map, camera, frames, _, right, moved_u, moved_v = flight
    m = right.methods[name]
    both = m.valid & moved_u.methods[name].valid & moved_v.methods[name].valid
    assert both.mean() > 0.9
    du = moved_u.methods[name].world_T_cam[:, :3, 3] - m.world_T_cam[:, :3, 3]
    dv = moved_v.methods[name].world_T_cam[:, :3, 3] - m.world_T_cam[:, :3, 3]
    shared = with_principal_share(m, frames, sign_map, camera, SHIFT_PX, weak_sigma_m=np.inf)
    share = np.sqrt(shared.sigma_xyz**2 - m.sigma_xyz**2)  # (N, 3) per world axis [m]
    actual = np.sqrt(du**2 + dv**2)  # what a u and a v shift of SHIFT_PX did, per axis
    ratio = np.linalg.norm(actual[both], axis=1) / np.linalg.norm(share[both], axis=1)
    assert np.all((ratio > 0.7) & (ratio < 1.3)), ratio
    assert 0.9 < np.median(ratio) < 1.1
    # per axis too, against the size of the change
    err = np.abs(actual[both] - share[both])
    assert np.all(err <= 0.3 * np.linalg.norm(actual[both], axis=1)[:, None])
    # the u shift alone: along the response's u row
    for i in np.flatnonzero(both)[::5]:
        a = principal_point_response(frames[i], sign_map, camera, m.world_T_cam[i])
        cos = abs(du[i] @ a[0]) / np.linalg.norm(du[i]) / np.linalg.norm(a[0])
        assert cos > 0.95
        assert np.linalg.norm(du[i]) == pytest.approx(SHIFT_PX * np.linalg.norm(a[0]), rel=0.3)


@pytest.fixture(scope="module")
def faulty(flight):
    sign_map, camera, frames, gt, *_ = flight
    wrong = _shifted(camera, FAULT_PX, 0.0)
    silent = estimate_trajectories(frames, sign_map, wrong, _settings(), False)
    told = estimate_trajectories(frames, sign_map, wrong, _settings(FAULT_PX), False)
    return gt, silent, told


def _beyond_3_sigma(method, gt) -> tuple[np.ndarray, np.ndarray]:
    """Which poses are ok or weak, and which of all are beyond 3 sigma on some axis."""
    trusted = np.array([st in (PoseStatus.OK, PoseStatus.WEAK) for st in method.status])
    z = np.abs(method.world_T_cam[:, :3, 3] - gt.world_t_cam) / method.sigma_xyz
    return trusted, np.max(z, axis=1) > 3


@pytest.mark.parametrize("name", ["pnp", "smoothed"])
def test_a_principal_point_off_is_silent_without_its_sigma_and_covered_with_it(faulty, name):
    gt, silent, told = faulty
    ok = np.array([st is PoseStatus.OK for st in silent.methods[name].status])
    _, far = _beyond_3_sigma(silent.methods[name], gt)
    assert ok.mean() > 0.8  # the poses look fine
    assert np.mean(far[ok]) > 0.1
    trusted, far = _beyond_3_sigma(told.methods[name], gt)
    assert trusted.mean() > 0.8
    assert np.mean(far[trusted]) <= 0.05
    # only the sigmas change, not the poses
    np.testing.assert_array_equal(told.methods[name].world_T_cam, silent.methods[name].world_T_cam)
    assert np.all(told.methods[name].sigma_xyz[trusted] > silent.methods[name].sigma_xyz[trusted])


def test_an_ok_pose_beyond_the_weak_limit_becomes_weak(flight):
    sign_map, camera, frames, _, right, *_ = flight
    m = right.methods["pnp"]
    assert with_principal_share(m, frames, sign_map, camera, 0.0, weak_sigma_m=0.0) is m
    loose = with_principal_share(m, frames, sign_map, camera, 5.0, weak_sigma_m=np.inf)
    assert loose.status == m.status
    tight = with_principal_share(m, frames, sign_map, camera, 5.0, weak_sigma_m=0.0)
    assert any(st is PoseStatus.OK for st in m.status)
    for before, after in zip(m.status, tight.status, strict=True):
        assert after is (PoseStatus.WEAK if before is PoseStatus.OK else before)


def test_a_frame_without_signs_takes_its_neighbours_share(flight):
    sign_map, camera, frames, _, right, *_ = flight
    m = right.methods["smoothed"]
    blind = list(frames)
    blind[7] = replace(frames[7], signs=())
    shared = with_principal_share(m, blind, sign_map, camera, 5.0, weak_sigma_m=np.inf)
    share = shared.sigma_xyz**2 - m.sigma_xyz**2
    assert np.all(np.isfinite(share[7]))
    np.testing.assert_allclose(share[7], share[6], rtol=1e-12)


def _estimate_files(tmp_path, flight, extra: list[str]) -> dict[str, bytes]:
    sign_map, camera, frames, *_ = flight
    src = tmp_path / "in"
    if not src.exists():
        src.mkdir()
        write_map(src / "map.yaml", sign_map)
        write_camera_info(src / "camera.yaml", camera)
        write_observations(src / "obs.jsonl", frames)
    out = tmp_path / f"out{len(list(tmp_path.iterdir()))}"
    args = ["estimate", str(src / "obs.jsonl"), "--map", str(src / "map.yaml")]
    args += ["--camera", str(src / "camera.yaml"), "--out", str(out), "--method", "all", "-q"]
    assert main(args + extra) == 0
    files = {p.name: p.read_bytes() for p in sorted(out.iterdir())}
    report = json.loads(files.pop("report.json"))
    report.pop("timing_s")  # the only part of a rerun that differs
    return files | {"report.json": json.dumps(report).encode()}


def test_the_default_zero_leaves_every_output_as_it_was(tmp_path, flight):
    plain = _estimate_files(tmp_path, flight, [])
    zero = _estimate_files(tmp_path, flight, ["--principal-sigma", "0"])
    assert plain == zero
    # report.json's settings as before the option existed: no new key
    settings = json.loads(plain["report.json"])["settings"]
    assert "principal_sigma_px" not in settings
    assert "focal_sigma_rel" in settings
    stated = _estimate_files(tmp_path, flight, ["--principal-sigma", "5"])
    assert json.loads(stated["report.json"])["settings"]["principal_sigma_px"] == 5.0
    assert stated["trajectory.csv"] != plain["trajectory.csv"]  # the sigma columns
    assert stated["pnp.tum"] == plain["pnp.tum"]  # the poses are the same


@pytest.mark.parametrize("command", ["run", "estimate", "batch"])
@pytest.mark.parametrize("value", ["-1", "nan", "1000"])
def test_a_bad_principal_sigma_is_one_line(tmp_path, capsys, flight, command, value):
    _estimate_files(tmp_path, flight, [])  # the inputs, so that only the option is wrong
    src = tmp_path / "in"
    args = [command, str(src / "obs.jsonl"), "--map", str(src / "map.yaml")]
    args += ["--camera", str(src / "camera.yaml"), "--out", str(tmp_path / "bad")]
    capsys.readouterr()
    code = main([*args, "--principal-sigma", value, "-q"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "--principal-sigma" in err[0], err
    assert not (tmp_path / "bad").exists()
