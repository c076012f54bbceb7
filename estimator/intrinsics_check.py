"""Does the video agree with the camera file's focal length and principal point?

A focal length a few per cent off, or a principal point some pixels off, is
the one set-up mistake a flight's keypoints cannot show through their
residuals: the poses absorb it (a longer focal length reads as a camera
farther away) and every keypoint still fits within its sigma. It is not
invisible, though. Seen from several directions, a set of signs at known
places fixes the intrinsics (the planar-target calibration of Zhang, 2000,
with the map as the target): the same fit of every pose, now with fx, fy, cx,
cy and each sign's survey offset free, says how far the file's values are
from the video's, and how well the flight determines them.

``check_intrinsics`` does that fit by Gauss-Newton on the smoother's inlier
measurements, from the smoothed poses and the file's intrinsics. Each
frame's pose is eliminated in closed form (its 6x6 block), leaving a small
system in the intrinsics and the signs' offsets (their survey sigmas as
priors, the file's intrinsics as a weak prior). Its result carries the
estimated change of each intrinsic and its sigma (the measurements' sigmas
carry the flight's pixel noise scale). ``IntrinsicsCheck.disagrees`` is True
when the focal length's relative change exceeds both
``CheckSettings.min_focal_rel`` and ``z`` times its sigma, or a principal
point coordinate's exceeds ``min_principal_px`` and ``z_principal`` times its
sigma; each sigma has a floor for the keypoints' shared biases, which no
flight length averages away, and the uncertainty the user stated added.

The undistorted pixels were made with the file's intrinsics, so the lens's
distortion is taken as the file states it; a focal length error then also
bends the undistortion slightly, which the fit reads as part of the focal
change (first order). A flight that sees its signs from one direction only
determines the focal length poorly: its sigma says so, and the check then
does not fire.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from signpose.estimator.camera import CameraModel, pixel_from_cam_point, undistort_px_jacobian
from signpose.estimator.projection import pixels_and_jacobians
from signpose.estimator.smoother import Measurements

# Parameters of the global block: fx, fy, cx, cy, then 3 per sign.
_N_INTRINSICS = 4
# Whitened residuals beyond this count with a Huber weight (k / |r|).
_HUBER_K = 3.0


@dataclass(frozen=True)
class CheckSettings:
    """When the video's intrinsics disagree with the file's.

    Attributes:
        z: sigmas of the estimated change beyond which it is no noise; for the
            principal point ``z_principal`` (it trades against the pitch and
            yaw of every pose, and takes up any bias of the keypoints that
            the flight shares).
        focal_floor_rel, principal_floor_px: a sigma that no flight length
            averages away, added in quadrature to the fit's: the keypoints'
            shared biases (on correct set-ups, eval_flight's and the demo's
            flights: focal changes up to 3.6 (members) and 4.8 (a fisheye
            orbit) of their sigmas, 0.04-0.28 %; the principal point's v
            -2 to -10 px, up to 11 sigmas on eval_pose_sigma's hard flight:
            zero with true keypoints, so the frontend's).
        min_focal_rel, min_principal_px: the smallest changes acted on; the
            principal point's is above every correct set-up's change seen
            (10.3 px).
        iterations: Gauss-Newton iterations.
        settled_step: the last iteration moves no intrinsic by more than this
            (focal lengths relative to themselves, the principal point to the
            image width), or the fit has not settled.
        plausible_focal_rel, plausible_principal_rel: a change beyond these
            (the same units) is no calibration slip but a fit that ran off
            (a map that does not fit: a moved or swapped sign, wrong
            diameters): the check then claims nothing.
        min_frames: frames with a pose and keypoints needed to check at all.
        max_frames: at most this many frames, evenly spread over the flight,
            are used (the cost stays bounded on long flights).
        prior_focal_rel, prior_principal_rel: sigmas of a weak prior at the
            file's values, focal length relative to itself, principal point
            relative to the image width: a flight that cannot tell (a flat
            face seen square on) leaves the estimate there, its sigma near
            the prior's, instead of a singular system.
    """

    z: float = 5.0
    z_principal: float = 4.0
    focal_floor_rel: float = 0.0025
    principal_floor_px: float = 2.0
    min_focal_rel: float = 0.01
    min_principal_px: float = 12.0
    iterations: int = 6
    settled_step: float = 1e-3
    plausible_focal_rel: float = 0.25
    plausible_principal_rel: float = 0.15
    min_frames: int = 10
    max_frames: int = 400
    prior_focal_rel: float = 0.2
    prior_principal_rel: float = 0.1


@dataclass(frozen=True)
class IntrinsicsCheck:
    """The video's estimate of the camera's intrinsics against the file's.

    Attributes:
        frames: frames used.
        delta: (4,) estimated change of fx, fy, cx, cy from the file's [px].
        sigma: (4,) their sigmas [px] (pixel noise scale applied).
        focal_rel: the focal length's relative change, mean of fx and fy.
        focal_rel_sigma: its sigma.
        settled: the fit converged to a change a calibration slip can make
            (``CheckSettings.plausible_*``); else it claims nothing.
        focal_off: settled, and the focal length's change is beyond noise and
            material (module docstring); principal_off: the principal point's is.
    """

    frames: int
    delta: np.ndarray
    sigma: np.ndarray
    focal_rel: float
    focal_rel_sigma: float
    settled: bool
    focal_off: bool
    principal_off: bool

    @property
    def disagrees(self) -> bool:
        """The video disagrees with the file on the focal length or the principal point."""
        return self.focal_off or self.principal_off

    @property
    def principal_change_px(self) -> float:
        """The larger of the principal point's two changes [px]."""
        return float(np.max(np.abs(self.delta[2:])))

    def as_dict(self) -> dict:
        """The check for report.json."""
        names = ("fx", "fy", "cx", "cy")
        return {
            "frames": self.frames,
            "change_px": {k: round(float(v), 3) for k, v in zip(names, self.delta, strict=True)},
            "sigma_px": {k: round(float(v), 3) for k, v in zip(names, self.sigma, strict=True)},
            "focal_rel": round(self.focal_rel, 5),
            "focal_rel_sigma": round(self.focal_rel_sigma, 5),
            "settled": self.settled,
            "focal_off": self.focal_off,
            "principal_off": self.principal_off,
        }


def _sign_columns(meas: Measurements) -> tuple[np.ndarray, np.ndarray]:
    """Per landmark, the index of its sign's offset (-1: fixed), and each offset's sigma."""
    codes = sorted(set(meas.landmark_code))
    sig = {c: 0.0 for c in codes}
    for c, s in zip(meas.landmark_code, meas.landmark_sigma_m, strict=True):
        sig[c] = max(sig[c], float(s))
    free = [c for c in codes if sig[c] > 0]
    col = {c: i for i, c in enumerate(free)}
    which = np.array([col.get(c, -1) for c in meas.landmark_code], dtype=np.int64)
    return which, np.array([sig[c] for c in free], dtype=float)


def _raw_side(meas: Measurements, camera: CameraModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The measurements back in the raw image: pixels (M, 2), d(raw)/d(undistorted) (M, 2, 2)
    and whiteners (M, 2, 2) (W^T W the inverse of each raw covariance)."""
    cov = meas.cov_uv_px
    if cov is None:
        su = meas.axis_sigmas()
        cov = np.zeros((len(su), 2, 2))
        cov[:, 0, 0] = su[:, 0] ** 2
        cov[:, 1, 1] = su[:, 1] ** 2
    xn = (np.linalg.inv(camera.K) @ np.column_stack([meas.px, np.ones(len(meas.px))]).T).T
    raw = pixel_from_cam_point(camera, xn)
    _px, jac, _valid = undistort_px_jacobian(camera, raw)
    j_dist = np.broadcast_to(np.eye(2), (len(raw), 2, 2)) if jac is None else np.linalg.inv(jac)
    cov_raw = j_dist @ np.asarray(cov, dtype=float) @ j_dist.transpose(0, 2, 1)
    W = np.linalg.cholesky(np.linalg.inv(cov_raw)).transpose(0, 2, 1)
    return raw, np.array(j_dist), W


def _cam_points(world_T_cam: np.ndarray, world_p: np.ndarray) -> np.ndarray:
    """(M, 3) camera-frame points of (M, 3) world points, each seen from its own (M, 4, 4) pose."""
    return np.einsum("mji,mj->mi", world_T_cam[:, :3, :3], world_p - world_T_cam[:, :3, 3])


def _linearised(meas, R, t, world, k, camera, raw, j_dist):
    """Raw-pixel residuals (M, 2) and Jacobians: pose (M, 2, 6), K (M, 2, 4), point (M, 2, 3).

    The prediction is the camera's own projection (its lens) with intrinsics
    ``k`` = (fx, fy, cx, cy); the pinhole's Jacobians (``projection.pixels_and_jacobians``,
    pose perturbation [omega, v]) are carried into the raw image by ``j_dist``.
    """
    K = np.array(camera.K, dtype=float)
    K[0, 0], K[1, 1], K[0, 2], K[1, 2] = k
    at_k = replace(camera, K=K)
    T = np.zeros((len(meas.frame), 4, 4))
    T[:, :3, :3], T[:, :3, 3], T[:, 3, 3] = R[meas.frame], t[meas.frame], 1.0
    _uv, d_pose, d_point = pixels_and_jacobians(at_k, T, world)
    pred = pixel_from_cam_point(at_k, _cam_points(T, world))
    j_k = np.zeros((len(pred), 2, _N_INTRINSICS))
    j_k[:, 0, 0] = (pred[:, 0] - k[2]) / k[0]
    j_k[:, 1, 1] = (pred[:, 1] - k[3]) / k[1]
    j_k[:, 0, 2] = 1.0
    j_k[:, 1, 3] = 1.0
    return raw - pred, j_dist @ d_pose, j_k, j_dist @ d_point


def _normal_blocks(meas, r, j_pose, j_g, W, n_frames):
    """Per-frame A (N, 6, 6), B (N, 6, G), b (N, 6); global H (G, G), g (G,): the
    whitened normal equations, each measurement Huber-weighted at ``_HUBER_K``."""
    rw = np.einsum("mij,mj->mi", W, r)
    norm = np.linalg.norm(rw, axis=1)
    w = np.where(norm > _HUBER_K, _HUBER_K / np.maximum(norm, 1e-12), 1.0)
    jp = np.einsum("mij,mjk->mik", W, j_pose) * np.sqrt(w)[:, None, None]
    jg = np.einsum("mij,mjk->mik", W, j_g) * np.sqrt(w)[:, None, None]
    rr = rw * np.sqrt(w)[:, None]
    G = j_g.shape[2]
    A = np.zeros((n_frames, 6, 6))
    B = np.zeros((n_frames, 6, G))
    b = np.zeros((n_frames, 6))
    np.add.at(A, meas.frame, np.einsum("mki,mkj->mij", jp, jp))
    np.add.at(B, meas.frame, np.einsum("mki,mkj->mij", jp, jg))
    np.add.at(b, meas.frame, np.einsum("mki,mk->mi", jp, rr))
    H = np.einsum("mki,mkj->ij", jg, jg)
    g = np.einsum("mki,mk->i", jg, rr)
    return A, B, b, H, g


def _global_jacobian(j_k, j_point, which, n_signs):
    """(M, 2, 4 + 3 S): the intrinsics' columns, then each sign's offset (its own only)."""
    j_g = np.zeros((len(j_k), 2, _N_INTRINSICS + 3 * n_signs))
    j_g[:, :, :_N_INTRINSICS] = j_k
    m = np.nonzero(which >= 0)[0]
    for a in range(3):
        j_g[m, :, _N_INTRINSICS + 3 * which[m] + a] = j_point[m, :, a]
    return j_g


def _step(A, B, b, H, g, prior):
    """Gauss-Newton step with every pose eliminated: (pose steps (N, 6), global step, S)."""
    Ainv = np.linalg.inv(A + 1e-9 * np.eye(6))
    S = H + np.diag(prior) - np.einsum("nki,nkl,nlj->ij", B, Ainv, B)
    rhs = g - np.einsum("nki,nkl,nl->i", B, Ainv, b)
    dg = np.linalg.solve(S, rhs)
    dp = np.einsum("nij,nj->ni", Ainv, b - np.einsum("nij,j->ni", B, dg))
    return dp, dg, S


def _rotations(w: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices of (N, 3) rotation vectors."""
    return np.array([cv2.Rodrigues(np.asarray(v, float).reshape(3, 1))[0] for v in w])


def _fit(meas, world_T_cam, camera, settings):
    """Gauss-Newton from the poses and the file: (intrinsics (4,), the reduced system
    S over intrinsics and sign offsets, the last step's largest relative move)."""
    R = np.array(world_T_cam[:, :3, :3], dtype=float)
    t = np.array(world_T_cam[:, :3, 3], dtype=float)
    k0 = np.array([camera.fx, camera.fy, camera.cx, camera.cy], dtype=float)
    k = k0.copy()
    which_lm, sig = _sign_columns(meas)
    which = which_lm[meas.landmark]  # per measurement
    offsets = np.zeros((len(sig), 3))
    k_sigma = np.array(
        [settings.prior_focal_rel * k0[0], settings.prior_focal_rel * k0[1]]
        + [settings.prior_principal_rel * camera.width] * 2
    )
    prior = np.concatenate([1.0 / k_sigma**2, np.repeat(1.0 / sig**2, 3)])
    step_scale = np.array([k0[0], k0[1], camera.width, camera.width])
    raw, j_dist, W = _raw_side(meas, camera)
    S, last_step = None, np.inf
    for _ in range(settings.iterations):
        world = meas.landmark_world[meas.landmark].copy()
        moved = which >= 0
        world[moved] += offsets[which[moved]]
        r, j_pose, j_k, j_point = _linearised(meas, R, t, world, k, camera, raw, j_dist)
        j_g = _global_jacobian(j_k, j_point, which, len(sig))
        A, B, b, H, g = _normal_blocks(meas, r, j_pose, j_g, W, len(R))
        g -= prior * np.concatenate([k - k0, offsets.ravel()])  # priors at the file, the map
        idle = np.nonzero(np.einsum("nii->n", A) == 0)[0]
        A[idle] = np.eye(6)
        dp, dg, S = _step(A, B, b, H, g, prior)
        t = t + np.einsum("nij,nj->ni", R, dp[:, 3:])
        R = R @ _rotations(dp[:, :3])
        k = k + dg[:_N_INTRINSICS]
        offsets = offsets + dg[_N_INTRINSICS:].reshape(-1, 3)
        last_step = float(np.max(np.abs(dg[:_N_INTRINSICS]) / step_scale))
    return k, S, last_step


def check_intrinsics(
    meas: Measurements,
    world_T_cam: np.ndarray,
    camera: CameraModel,
    noise_scale: float = 1.0,
    stated: tuple[float, float] = (0.0, 0.0),
    settings: CheckSettings = CheckSettings(),
) -> IntrinsicsCheck | None:
    """The video's intrinsics against the camera file's (module docstring), or None
    with too few frames or a singular fit.

    Args:
        meas: the inlier measurements (undistorted pixels, made with ``camera``).
        world_T_cam: (N, 4, 4) a pose per frame of ``meas`` (the smoothed ones).
        camera: the camera file's model (its lens taken as stated).
        noise_scale: the flight's pose noise scale (multiplies the sigmas; the
            measurements' sigmas carry the pixel noise scale already).
        stated: the uncertainty the user stated for the file's values: focal
            length (relative) and principal point [px] (``--focal-sigma``,
            ``--principal-sigma``); a change within it is no disagreement.
    """
    used = np.unique(meas.frame)
    if len(used) < settings.min_frames:
        return None
    if len(used) > settings.max_frames:
        used = used[np.linspace(0, len(used) - 1, settings.max_frames).round().astype(int)]
        meas = meas.subset(np.isin(meas.frame, used))
    try:
        k, S, last_step = _fit(meas, world_T_cam, camera, settings)
        cov = np.linalg.inv(S) * noise_scale**2
    except np.linalg.LinAlgError:
        return None  # a singular system (centre-only signs, poses seen once): no check
    k0 = np.array([camera.fx, camera.fy, camera.cx, camera.cy], dtype=float)
    var = np.diag(cov)[:_N_INTRINSICS]
    jr = np.array([0.5 / k0[0], 0.5 / k0[1]])
    rel_var = float(jr @ cov[:2, :2] @ jr)
    if not (np.all(np.isfinite(var)) and np.all(var > 0) and np.all(np.isfinite(k))):
        return None  # too little seen to fit (a singular system): no check
    if not rel_var > 0:
        return None
    sigma, rel_sigma, delta = np.sqrt(var), float(np.sqrt(rel_var)), k - k0
    rel = float(0.5 * (delta[0] / k0[0] + delta[1] / k0[1]))
    settled = last_step < settings.settled_step and abs(rel) < settings.plausible_focal_rel
    settled &= bool(np.all(np.abs(delta[2:]) < settings.plausible_principal_rel * camera.width))
    focal_tol = settings.z * np.sqrt(rel_sigma**2 + settings.focal_floor_rel**2 + stated[0] ** 2)
    focal_off = abs(rel) > max(settings.min_focal_rel, focal_tol)
    pp_sd = np.sqrt(sigma[2:] ** 2 + settings.principal_floor_px**2 + stated[1] ** 2)
    pp = np.abs(delta[2:]) > np.maximum(settings.min_principal_px, settings.z_principal * pp_sd)
    return IntrinsicsCheck(
        frames=len(used),
        delta=delta,
        sigma=sigma,
        focal_rel=rel,
        focal_rel_sigma=rel_sigma,
        settled=bool(settled),
        focal_off=bool(settled and focal_off),
        principal_off=bool(settled and pp.any()),
    )


def disagreement(check: IntrinsicsCheck, camera: CameraModel) -> str:
    """The warning for a check that ``disagrees``: what the video says, what was done
    (``estimate._intrinsics_checked``) and what to do."""
    d, sg = check.delta, check.sigma
    seen = (
        f"the video does not fit the camera file's intrinsics: seen from {check.frames} frames "
        f"the focal length is {100 * check.focal_rel:+.1f} % "
        f"(sigma {100 * check.focal_rel_sigma:.1f} %) from the file's "
        f"(fx {camera.fx + d[0]:.0f} for {camera.fx:.0f} px) and the principal point "
        f"({d[2]:+.1f}, {d[3]:+.1f}) px (sigma {sg[2]:.1f}, {sg[3]:.1f}) from it; "
    )
    if check.focal_off:
        done = (
            "poses made with the file's focal length are off by about as much of their range: "
            "every pose is marked suspect. "
        )
    else:
        done = (
            f"the sigmas include a principal point share of {check.principal_change_px:.0f} px "
            "(as --principal-sigma would add). "
        )
    return (
        seen + done + "Recalibrate at this zoom and focus, or state the file's uncertainty "
        "(--focal-sigma, --principal-sigma)"
    )
