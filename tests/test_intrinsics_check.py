"""The video's check of the camera file's focal length and principal point.

A flight that sees its signs from several directions fixes the intrinsics
(``estimator.intrinsics_check``): a file 3 % off in focal length, or 15 px off
in the principal point, is named; the correct file is not; a flight that sees
the signs from one direction only cannot tell, and says so by its sigma.
"""

from dataclasses import replace

import numpy as np
import pytest
from conftest import estimator_scene
from signpose.estimator.camera import (
    CameraModel,
    pixel_from_cam_point,
    undistort_px_jacobian,
)
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.intrinsics_check import check_intrinsics, disagreement
from signpose.estimator.smoother import Measurements
from signpose.estimator.status import PoseStatus

SIGMA_PX = 0.2
SURVEY_M = 0.01


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """world_T_cam of a camera at ``eye`` looking at ``target`` (z forward, y down)."""
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, -1.0])
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = eye
    return T


def _signs(rng, off_plane_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Ten signs on a pylon face (x-z plane, up to ``off_plane_m`` off it), 5 keypoints each."""
    off = rng.uniform(-off_plane_m, off_plane_m, 10)
    centres = np.column_stack([rng.uniform(-3, 3, 10), off, rng.uniform(8, 16, 10)])
    offs = np.array([[0, 0, 0], [0.2, 0, 0], [-0.2, 0, 0], [0, 0, 0.2], [0, 0, -0.2]])
    pts = (centres[:, None, :] + offs[None]).reshape(-1, 3)
    return pts, np.repeat(np.arange(10), 5)


def _flight(spread_deg: float, n: int, rng, pan_m: float) -> np.ndarray:
    """(n, 4, 4): a weave 25 m from the face's centre, +-spread_deg about its normal
    sideways and half that up and down."""
    target = np.array([0.0, 0.0, 12.0])
    poses = []
    for k, a in enumerate(np.radians(np.linspace(-spread_deg, spread_deg, n))):
        e = 0.5 * np.radians(spread_deg) * np.sin(6 * np.pi * k / n)
        eye = target + 25 * np.array([np.sin(a) * np.cos(e), -np.cos(a) * np.cos(e), np.sin(e)])
        poses.append(_look_at(eye, target + rng.normal(0, pan_m, 3)))
    return np.array(poses)


def _measurements(
    truth: CameraModel, told: CameraModel, spread_deg: float = 40, pan_m: float = 3.0, off=0.3
):
    """Keypoints seen through ``truth``, undistorted with ``told`` (the camera file),
    from a flight ``spread_deg`` around the face that pans ``pan_m`` about its centre."""
    rng = np.random.default_rng(1)
    pts, sign = _signs(rng, off)
    survey = pts + np.repeat(rng.normal(0, SURVEY_M, (10, 3)), 5, axis=0)  # the map
    poses = _flight(spread_deg, 60, rng, pan_m)
    fr, lm, raw = [], [], []
    for i, T in enumerate(poses):
        pc = (pts - T[:3, 3]) @ T[:3, :3]
        uv = pixel_from_cam_point(truth, pc) + rng.normal(0, SIGMA_PX, (len(pts), 2))
        inside = (uv[:, 0] > 0) & (uv[:, 0] < truth.width) & (uv[:, 1] > 0)
        inside &= uv[:, 1] < truth.height
        fr += [i] * int(inside.sum())
        lm += list(np.nonzero(inside)[0])
        raw.append(uv[inside])
    raw = np.concatenate(raw)
    px, jac, _ = undistort_px_jacobian(told, raw)
    cov = np.eye(2) * SIGMA_PX**2
    cov = (
        np.broadcast_to(cov, (len(px), 2, 2)) if jac is None else jac @ cov @ jac.transpose(0, 2, 1)
    )
    meas = Measurements(
        landmark_code=tuple(f"{s:04b}" for s in sign),
        landmark_name=tuple("k" for _ in sign),
        landmark_world=survey,
        landmark_sigma_m=np.full(len(pts), SURVEY_M),
        frame=np.array(fr),
        landmark=np.array(lm),
        px=px,
        sigma_px=np.full(len(px), SIGMA_PX),
        sign_index=np.zeros(len(px), dtype=int),
        n_frames=len(poses),
        sigma_uv_px=np.full((len(px), 2), SIGMA_PX),
        cov_uv_px=None if jac is None else np.array(cov),
    )
    return meas, poses


def _camera(dist=(0.0, 0.0, 0.0, 0.0, 0.0)) -> CameraModel:
    K = np.array([[1100.0, 0, 640], [0, 1100.0, 360], [0, 0, 1]])
    return CameraModel(1280, 720, K, np.array(dist, dtype=float))


def _scaled(camera: CameraModel, focal: float = 1.0, du: float = 0.0) -> CameraModel:
    K = camera.K.copy()
    K[0, 0] *= focal
    K[1, 1] *= focal
    K[0, 2] += du
    return replace(camera, K=K)


LENSES = {"pinhole": (0.0,) * 5, "plumb_bob": (-0.25, 0.07, 0.0004, -0.0002, 0.0)}


@pytest.mark.parametrize("lens", LENSES)
def test_the_correct_file_agrees(lens):
    cam = _camera(LENSES[lens])
    meas, poses = _measurements(cam, cam)
    c = check_intrinsics(meas, poses, cam)
    assert not c.disagrees
    assert abs(c.focal_rel) < 3 * c.focal_rel_sigma
    assert np.all(np.abs(c.delta) < 4 * c.sigma)


@pytest.mark.parametrize("lens", LENSES)
def test_a_focal_length_3_percent_off_is_named(lens):
    cam = _camera(LENSES[lens])
    wrong = _scaled(cam, 1.03)
    meas, poses = _measurements(cam, wrong)
    c = check_intrinsics(meas, poses, wrong)
    assert c.disagrees
    truth = 1 / 1.03 - 1
    assert abs(c.focal_rel - truth) < 3 * c.focal_rel_sigma + 0.002
    assert "the focal length is -" in disagreement(c, wrong)


def test_a_principal_point_40_px_off_is_named():
    cam = _camera(LENSES["plumb_bob"])
    wrong = _scaled(cam, du=40.0)
    meas, poses = _measurements(cam, wrong)
    c = check_intrinsics(meas, poses, wrong)
    assert c.disagrees
    assert abs(c.delta[2] + 40.0) < 3 * c.sigma[2] + 1.0
    assert abs(c.focal_rel) < 4 * c.focal_rel_sigma


def test_a_stated_uncertainty_that_covers_the_change_is_no_disagreement():
    cam = _camera()
    wrong = _scaled(cam, 1.03)
    meas, poses = _measurements(cam, wrong)
    assert not check_intrinsics(meas, poses, wrong, stated=(0.03, 0.0)).disagrees


def test_a_flat_face_seen_square_on_cannot_tell_and_says_so():
    """Signs on one plane, every view square on to it: only f / range is seen."""
    cam = _camera()
    wrong = _scaled(cam, 1.03)
    meas, poses = _measurements(cam, wrong, spread_deg=0.0, pan_m=0.0, off=0.0)
    seen = _measurements(cam, wrong)
    square_on = check_intrinsics(meas, poses, wrong)
    around = check_intrinsics(*seen, wrong)
    assert not square_on.disagrees
    assert square_on.focal_rel_sigma > 10 * around.focal_rel_sigma
    assert around.disagrees


def test_too_few_frames_are_not_checked():
    cam = _camera()
    meas, poses = _measurements(cam, cam)
    few = meas.subset(meas.frame < 5)
    assert check_intrinsics(few, poses, cam) is None


@pytest.fixture(scope="module")
def estimated():
    """A 20 s flight around the bundled map, with the right camera and one 8 % off."""
    sign_map, camera, frames, _gt, _ = estimator_scene(
        n_frames=60, sigma_px=0.2, seed=5, flat=False, duration_s=20
    )
    s = replace(EstimatorSettings(), methods=("pnp", "smoothed"))
    right = estimate_trajectories(frames, sign_map, camera, s, False)
    wrong = estimate_trajectories(frames, sign_map, _scaled(camera, 1.08), s, False)
    return right, wrong


def test_the_run_marks_every_pose_suspect_when_the_file_is_off(estimated):
    right, wrong = estimated
    assert not right.intrinsics.disagrees
    assert not any("intrinsics" in w for w in right.warnings)
    assert any(st is PoseStatus.OK for st in right.methods["smoothed"].status)
    assert wrong.intrinsics.disagrees
    assert sum("the camera file's intrinsics" in w for w in wrong.warnings) == 1
    for m in wrong.methods.values():
        assert not any(st in (PoseStatus.OK, PoseStatus.WEAK) for st in m.status)
    # what the video says is the camera's own focal length
    assert abs(wrong.intrinsics.focal_rel - (1 / 1.08 - 1)) < 3 * wrong.intrinsics.focal_rel_sigma


def test_a_principal_point_off_widens_the_sigmas_instead(estimated):
    """The principal point mostly turns the poses: its share covers what it moves."""
    sign_map, camera, frames, gt, _ = estimator_scene(
        n_frames=60, sigma_px=0.2, seed=5, flat=False, duration_s=20
    )
    s = replace(EstimatorSettings(), methods=("pnp", "smoothed"))
    wrong = estimate_trajectories(frames, sign_map, _scaled(camera, du=40.0), s, False)
    right = estimated[0].methods["smoothed"]
    c = wrong.intrinsics
    assert c.principal_off and not c.focal_off
    assert sum("principal point share of" in w for w in wrong.warnings) == 1
    m = wrong.methods["smoothed"]
    trusted = np.array([st in (PoseStatus.OK, PoseStatus.WEAK) for st in m.status])
    assert trusted.mean() > 0.8  # not refused
    z = np.abs(m.world_T_cam[:, :3, 3] - gt.world_t_cam)[trusted] / m.sigma_xyz[trusted]
    assert np.mean(z.max(axis=1) > 3) < 0.05
    # the share: the same flight's sigmas with the right camera are 2-11x smaller
    assert np.all(np.median(m.sigma_xyz / right.sigma_xyz, axis=0) > 1.8)


@pytest.mark.parametrize("fault", ["sign_1m", "diameters_10pct"])
def test_a_map_that_does_not_fit_is_not_blamed_on_the_intrinsics(fault):
    """A moved sign or wrong diameters pull the intrinsics' fit off (it would
    read a focal length tens of per cent off): it claims nothing then."""
    sign_map, camera, frames, _gt, _ = estimator_scene(
        n_frames=60, sigma_px=0.2, seed=5, flat=False, duration_s=20
    )
    if fault == "sign_1m":
        first = sign_map.signs[0]
        moved = replace(first, center_m=np.asarray(first.center_m, float) + [1.0, 0, 0])
        bad = replace(sign_map, signs=(moved, *sign_map.signs[1:]))
    else:
        bad = replace(
            sign_map, signs=tuple(replace(g, diameter_m=g.diameter_m * 1.1) for g in sign_map.signs)
        )
    s = replace(EstimatorSettings(), methods=("pnp", "smoothed"))
    r = estimate_trajectories(frames, bad, camera, s, False)
    assert not any("the camera file's intrinsics" in w for w in r.warnings)
