"""Trajectory metrics against hand-computed values."""

import numpy as np
from conftest import estimator_scene
from signpose.estimator.metrics import (
    associate,
    compute_metrics,
    ground_truth_at,
    rpe_translation,
    umeyama_se3,
)
from signpose.estimator.trajectory import Trajectory


def _line_traj(n: int = 11, step: float = 0.5) -> Trajectory:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = np.arange(n) * step
    return Trajectory.from_matrices(np.arange(n) * 0.1, T)


def _rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_identical_trajectories_have_zero_error():
    gt = _line_traj()
    m = compute_metrics(gt, gt)
    assert m.n_matched == 11 and m.coverage == 1.0 and m.rot_rmse_deg < 1e-6
    assert max(m.mae_xyz_m) == 0 and m.ate_rmse_m == 0 and m.rpe_trans_per_m == 0


def test_rigid_offset_is_removed_by_alignment():
    _, _, _, gt, _ = estimator_scene(n_frames=30)
    R = _rot_z(0.3)
    t = np.array([1.0, -2.0, 0.5])
    T = gt.world_T_cam().copy()
    G = np.eye(4)
    G[:3, :3], G[:3, 3] = R, t
    est = Trajectory.from_matrices(gt.stamps_s, G @ T)
    m = compute_metrics(est, gt)
    assert m.ate_rmse_aligned_m < 1e-9
    assert m.ate_rmse_m > 1.0
    # RPE compares relative motions: a global rigid transform leaves it at zero.
    assert m.rpe_trans_per_m < 1e-9
    R2, t2 = umeyama_se3(est.world_t_cam, gt.world_t_cam)
    assert np.allclose(R2, R.T, atol=1e-9) and np.allclose(t2, -R.T @ t, atol=1e-9)


def test_mae_and_ate_by_hand():
    gt = _line_traj(4)
    p = gt.world_t_cam.copy()
    p += np.array([[0.1, 0, 0], [0, -0.2, 0], [0, 0, 0.3], [0.1, 0.2, 0.0]])
    est = Trajectory(gt.stamps_s, p, gt.quat_xyzw)
    m = compute_metrics(est, gt)
    assert np.allclose(m.mae_xyz_m, [0.05, 0.1, 0.075])
    assert np.isclose(m.ate_rmse_m, np.sqrt((0.01 + 0.04 + 0.09 + 0.05) / 4))


def test_rpe_per_metre_by_hand():
    # Ground truth moves 0.5 m per pose: checkpoints every 2 poses (1 m).
    gt = _line_traj(9)
    T = gt.world_T_cam().copy()
    T[:, 0, 3] *= 1.1  # the estimate travels 10 % further
    errs, n = rpe_translation(T, gt.world_T_cam(), delta_m=1.0)
    assert n == 4 and np.allclose(errs, 0.1)
    m = compute_metrics(Trajectory.from_matrices(gt.stamps_s, T), gt)
    assert np.isclose(m.rpe_trans_per_m, 0.1)


def test_association_and_coverage():
    gt = _line_traj(10)
    keep = np.array([0, 2, 3, 7])
    est = Trajectory(gt.stamps_s[keep] + 0.004, gt.world_t_cam[keep], gt.quat_xyzw[keep])
    ie, ig = associate(est.stamps_s, gt.stamps_s, 0.01)
    assert ie.tolist() == [0, 1, 2, 3] and ig.tolist() == keep.tolist()
    m = compute_metrics(est, gt)
    assert m.coverage == 0.4
    # Ground truth 0.3 s apart is not interpolated: 0.05 s from it is no match.
    sparse = Trajectory(gt.stamps_s[::3], gt.world_t_cam[::3], gt.quat_xyzw[::3])
    far = Trajectory(gt.stamps_s[keep] + 0.05, gt.world_t_cam[keep], gt.quat_xyzw[keep])
    assert compute_metrics(far, sparse).n_matched == 0


def _curve(stamps_s: np.ndarray) -> Trajectory:
    """A turning, climbing flight at about 5 m/s: pose at each stamp, exactly."""
    t = np.asarray(stamps_s, dtype=float)
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, 0, 3] = 10.0 * np.sin(0.5 * t)
    T[:, 1, 3] = 10.0 * np.cos(0.5 * t)
    T[:, 2, 3] = 0.3 * t**2
    for i, a in enumerate(0.5 * t):
        T[i, :3, :3] = _rot_z(a)
    return Trajectory.from_matrices(t, T)


def test_dense_ground_truth_is_interpolated_at_the_frames():
    # A 100 Hz motion capture against 30 fps frames, 3 ms off the capture's clock.
    gt = _curve(np.arange(0, 4.0, 0.01))
    frames = np.arange(0.003, 3.9, 1 / 30)
    est = _curve(frames)  # the true poses at the frames: every error should be ~0
    m = compute_metrics(est, gt, reference_stamps_s=frames)
    assert m.ate_rmse_m < 1e-3 and m.rot_rmse_deg < 0.01
    # Nearest-stamp pairing takes poses up to 5 ms away: about 2.5 cm at 5 m/s.
    ie, ig = associate(est.stamps_s, gt.stamps_s, 0.01)
    d = est.world_t_cam[ie] - gt.world_t_cam[ig]
    assert np.sqrt(np.mean(np.sum(d * d, axis=1))) > 0.005
    # Coverage counts frames, not capture samples (the nearest pairing gave 30 %).
    assert m.coverage == 1.0 and m.n_matched == len(frames)
    half = Trajectory(est.stamps_s[::2], est.world_t_cam[::2], est.quat_xyzw[::2])
    assert abs(compute_metrics(half, gt, reference_stamps_s=frames).coverage - 0.5) < 0.01


def test_ground_truth_at_its_own_stamps_is_taken_as_it_is():
    gt = _curve(np.arange(0, 2.0, 1 / 30))
    idx, T = ground_truth_at(gt, gt.stamps_s)
    assert idx.tolist() == list(range(len(gt)))
    assert np.array_equal(T, gt.world_T_cam())


def test_compare_against_a_motion_capture_counts_frames(tmp_path):
    # `signpose compare DIR --gt mocap.tum`: a 100 Hz ground truth on its own clock.
    from signpose.io.results import compare_dir
    from signpose.io.tum import write_tum

    frames = np.arange(0.003, 3.9, 1 / 30)
    write_tum(tmp_path / "smoothed.tum", _curve(frames))
    write_tum(tmp_path / "pnp.tum", _curve(frames[::3]))
    write_tum(tmp_path / "mocap.tum", _curve(np.arange(0, 4.0, 0.01)))
    out = compare_dir(tmp_path, tmp_path / "mocap.tum")
    assert out["smoothed"]["coverage"] == 1.0 and out["smoothed"]["ate_rmse_m"] < 1e-3
    assert abs(out["pnp"]["coverage"] - 1 / 3) < 0.01
