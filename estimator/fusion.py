"""GNSS/IMU fusion in the smoother's factor graph (issue 17).

The vision factors are the smoother's own (``smoother._GraphBuilder``: the
survey, the projection factors, the constant-velocity prior where the IMU has
no samples); added to them:

* GNSS: one factor per fix on the nearest frame's pose, ``z = t + R a + d``
  with ``a`` the antenna in the camera frame (``cam_t_antenna_m``: the
  lever arm) and ``d`` a slowly drifting GNSS error (a ``Point3`` per fix,
  key ``d<k>``, a random walk of ``gnss_drift_rw``): the receiver's error is
  not white, so the signs calibrate it where they are seen and it may not
  pull a bridge by more than its drift. Noise ``Robust(kernel, Diagonal(sigma_h,
  sigma_h, sigma_v))`` with a redescending kernel (Tukey by default): a
  multipath burst near the conductors is an outlier, not Gaussian noise. The
  fix is moved from its time to the frame's by the current velocity.
* IMU: ``CombinedImuFactor`` between consecutive frames from the samples
  between them (each sample held over the half-intervals around it), a bias
  per frame (key ``w<i>``) with the random walks in the factor; the camera is
  the navigation body, the IMU its sensor (``body_P_sensor`` = cam_T_body).
* Gimbal: a weak ``PoseRotationPrior3D`` from the reported yaw/pitch/roll
  (map with an ``origin`` only: the angles are relative to north).

Clock: a frame stamped ``t`` (video) was exposed at telemetry time ``t + offset``
(``estimator.telemetry``). The offset is fixed by ``clock_offset_s`` or
estimated: a scan of offsets scoring the gyro (or, without an IMU, the GNSS)
against the vision trajectory, then a golden-section refinement of the same
cost; its sigma from the cost's curvature (Gauss-Newton).

Frames: world = the map's frame (ENU at its origin), poses ``world_T_cam``
(OpenCV axes), IMU body FLU.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import gtsam
import numpy as np
from signpose.estimator.camera import CameraModel
from signpose.estimator.perframe import PerFrameSettings, run_per_frame
from signpose.estimator.projection import pixels_and_pose_jacobian, whitened
from signpose.estimator.smoother import (
    BIAS_KEY,
    CONSTANT_VELOCITY,
    TUKEY,
    SmootherResult,
    SmootherSettings,
    V,
    X,
    _GraphBuilder,
    _observed_and_signs,
    _sigmas_from,
    _velocities,
    batch_covariances,
    collect_measurements,
    default_pose,
    smooth_batch,
    whitened_chi2,
)
from signpose.estimator.status import PoseStatus, StatusSettings, classify
from signpose.estimator.telemetry import GimbalAngles, ImuSamples, Telemetry
from signpose.frontend.observations import FrameObservations
from signpose.maps.geodesy import enu_from_geodetic
from signpose.maps.loader import SignMap

from signpose.core.errors import InputError

log = logging.getLogger(__name__)

GNSS_KERNELS = ("tukey", "geman-mcclure", "huber", "none")


def W(i: int) -> int:
    """The IMU bias at frame i."""
    return gtsam.symbol("w", i)


def D(k: int) -> int:
    """The GNSS error (drift) at fix k."""
    return gtsam.symbol("d", k)


def _default_body_T_cam() -> tuple[tuple[float, ...], ...]:
    """Camera looking along the body's x (forward), at the IMU: cam x = -y_b, y = -z_b."""
    return ((0.0, 0.0, 1.0, 0.0), (-1.0, 0.0, 0.0, 0.0), (0.0, -1.0, 0.0, 0.0), (0, 0, 0, 1.0))


def _rot_zyx(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """(3, 3) ``Rz(yaw) Ry(pitch) Rx(roll)`` (Z-Y-X Euler angles) [deg]."""
    y, p, r = np.radians([yaw_deg, pitch_deg, roll_deg])
    cz, sz, cy, sy, cx, sx = np.cos(y), np.sin(y), np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1.0]])
    Ry = np.array([[cy, 0, sy], [0, 1.0, 0], [-sy, 0, cy]])
    Rx = np.array([[1.0, 0, 0], [0, cx, -sx], [0, sx, cx]])
    return Rz @ Ry @ Rx


def body_T_cam_from_mounting(roll_deg: float, pitch_deg: float, yaw_deg: float):
    """(4, 4) the camera's pose in the IMU body (FLU) as nested tuples, at the IMU.

    The angles turn the default mounting (camera looking along the body's x,
    image right = body -y, image down = body -z) about the body's axes: the
    camera's rotation is ``Rz(yaw) Ry(pitch) Rx(roll)`` times the default's, so
    (0, 0, 0) is the default and pitch +45 looks 45 deg down (FLU: +y is left,
    a positive turn about it takes x towards -z), yaw +90 looks left.
    """
    T = np.array(_default_body_T_cam(), float)
    T[:3, :3] = _rot_zyx(yaw_deg, pitch_deg, roll_deg) @ T[:3, :3]
    return tuple(tuple(float(x) for x in row) for row in T)


@dataclass(frozen=True)
class FusionSettings:
    """What the fusion uses and how it weighs it.

    Attributes:
        use_gnss / use_imu / use_gimbal: which of the drone's sensors join the
            vision factors.
        cam_t_antenna_m: the GNSS antenna in the camera frame [m] (lever arm).
        body_T_cam: (4, 4) the camera's pose in the IMU body (FLU) [m].
        gnss_kernel: ``"tukey"`` (redescending, the default), ``"geman-mcclure"``
            (redescending), ``"huber"`` or ``"none"``.
        gnss_kernel_k: the kernel's threshold on the whitened 3-D residual
            norm (Tukey: zero weight beyond it).
        gnss_min_sigma_m: a fix's claimed sigma is raised to at least this [m].
        gnss_drift_sigma_m: prior sigma of the GNSS error at the first fix [m].
        gnss_drift_rw: its random walk [m/sqrt(s)].
        gnss_max_dt_s: a fix further than this from every frame is not used [s].
        gyro_noise / accel_noise: IMU white noise densities
            [rad/s/sqrt(Hz)], [m/s^2/sqrt(Hz)].
        gyro_bias_rw / accel_bias_rw: bias random walks [rad/s^2/sqrt(Hz)],
            [m/s^3/sqrt(Hz)].
        gyro_bias_sigma / accel_bias_sigma: prior sigmas of the first bias.
        imu_max_gap_s: an interval with a longer gap between IMU samples gets
            the constant-velocity prior instead [s].
        gravity_m_s2: gravity along -z of the world [m/s^2].
        gimbal_sigma_rad: sigma of the gimbal's rotation prior [rad].
        clock_offset_s: telemetry minus video time [s]; None estimates it.
        clock_search_s: the scan covers +-this around 0 [s].
        clock_step_s: the scan's step [s].
        clock_max_shift: an estimated offset is used only if its sigma times
            the flight's speed is at most this many GNSS sigmas
            (``clock_shift_limit_s``); else the fusion is refused.
        smoother: settings of the vision factors and the motion prior.
        status: when a pose is weak or suspect.
        lm_max_iterations: Levenberg-Marquardt cap per stage.
    """

    use_gnss: bool = True
    use_imu: bool = True
    use_gimbal: bool = True
    cam_t_antenna_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    body_T_cam: tuple[tuple[float, ...], ...] = field(default_factory=_default_body_T_cam)
    gnss_kernel: str = "tukey"
    gnss_kernel_k: float = 3.5
    gnss_min_sigma_m: float = 0.3
    gnss_drift_sigma_m: float = 3.0
    gnss_drift_rw: float = 0.15
    gnss_max_dt_s: float = 0.25
    gyro_noise: float = 1e-3
    accel_noise: float = 8e-3
    gyro_bias_rw: float = 1e-4
    accel_bias_rw: float = 1e-3
    gyro_bias_sigma: float = 0.02
    accel_bias_sigma: float = 0.3
    imu_max_gap_s: float = 0.05
    gravity_m_s2: float = 9.80665
    gimbal_sigma_rad: float = 0.1
    clock_offset_s: float | None = None
    clock_search_s: float = 1.5
    clock_step_s: float = 0.01
    clock_max_shift: float = 1.0
    smoother: SmootherSettings = field(default_factory=lambda: SmootherSettings(kernel=TUKEY))
    status: StatusSettings = field(default_factory=StatusSettings)
    lm_max_iterations: int = 100


def on_smoother(settings: FusionSettings | None, smoother: SmootherSettings) -> FusionSettings:
    """``settings`` with the vision smoother's own settings (the run's landmarks, e.g.
    fixed signs, its motion prior as tuned on the flight, its sigmas switch), the
    fusion's projection kernel kept (``settings.smoother.kernel``, ``tukey_k``).

    Without it the fused graph had the default constant-velocity prior (2 m/s^2):
    on a 30 m/s flight whose tuned prior was 32 m/s^2 it pulled the fused poses
    up to 4.6 m from the truth where the vision ones were within 0.5 m.
    """
    s = settings or FusionSettings()
    own = s.smoother
    return replace(s, smoother=replace(smoother, kernel=own.kernel, tukey_k=own.tukey_k))


@dataclass(frozen=True)
class ClockOffset:
    """The telemetry-minus-video offset [s] and its standard deviation (0 when fixed).

    Attributes:
        source: ``"fixed"``, ``"gyro"`` (the gyro against the vision
            rotations) or ``"gnss"`` (the GNSS against the vision positions).
    """

    offset_s: float
    sigma_s: float
    source: str


@dataclass(frozen=True)
class FusionResult:
    """The fused trajectory ("fused" in outputs).

    Attributes:
        world_T_cam: (N, 4, 4) pose of every frame.
        sigma_xyz: (N, 3) marginal position sigmas, world axes [m] (NaN when not computed).
        cov6: (N, 6, 6) marginal pose covariances (gtsam order), or None.
        status: (N,) PoseStatus per frame: ``bridged`` where no sign was used
            (the pose then comes from the IMU/GNSS, its sigma says how well).
        observed: (N,) True where the frame had projection factors.
        signs_used: (N,) map signs with factors per frame.
        velocity_world_m_s: (N, 3) camera velocity [m/s].
        gyro_bias / accel_bias: (N, 3) the IMU bias per frame (zeros without IMU).
        gnss_drift_m: (G, 3) the estimated GNSS error at each used fix [m].
        gnss_used: (G,) index into the telemetry's fixes of each used fix.
        gnss_outlier: (G,) True for the fixes the kernel rejected.
        clock: the clock offset.
        counts: what went in (``frames``, ``gnss_used``, ``gnss_outliers``,
            ``gnss_outside`` (no frame near), ``imu_factors``, ``cv_factors``,
            ``gimbal_priors``, ``projection_factors``).
        landmarks_world: (L, 3) the landmarks at the solution [m].
        seconds: solve time [s].
        refused: True when nothing was fused because the clock offset could not
            be determined well enough (``clock_shift_limit_s``): the poses are
            the vision ones, "fused" is not a method of the run, ``clock`` is
            0 with sigma NaN (source "none") and the note gives the guess.
        notes: one line each for the user (the refusal and how to avoid it;
            the clock taken from the video's own).
    """

    world_T_cam: np.ndarray
    sigma_xyz: np.ndarray
    cov6: np.ndarray | None
    status: tuple[PoseStatus, ...]
    observed: np.ndarray
    signs_used: np.ndarray
    velocity_world_m_s: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    gnss_drift_m: np.ndarray
    gnss_used: np.ndarray
    gnss_outlier: np.ndarray
    clock: ClockOffset
    counts: dict[str, int]
    landmarks_world: np.ndarray
    seconds: float = 0.0
    refused: bool = False
    notes: tuple[str, ...] = ()


# ----------------------------------------------------------------- GNSS factors


def _gnss_error(z: np.ndarray, arm: np.ndarray):
    """Error function of a fix: t + R arm + d - z on (X(i), D(k)); Jacobians [rot, trans]."""

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H) -> np.ndarray:
        pose = v.atPose3(this.keys()[0])
        d = v.atPoint3(this.keys()[1])
        R = pose.rotation().matrix()
        e = pose.translation() + R @ arm + d - z
        if H is not None:
            ax = np.array([[0, -arm[2], arm[1]], [arm[2], 0, -arm[0]], [-arm[1], arm[0], 0]])
            H[0] = np.hstack([-R @ ax, R])
            H[1] = np.eye(3)
        return e

    return error


def gnss_factor(
    pose_key: int, drift_key: int, z_world: np.ndarray, arm_cam: np.ndarray, noise
) -> gtsam.CustomFactor:
    """A fix ``z_world`` (3,) [m] of the antenna at ``arm_cam`` (3,) in the camera frame."""
    z = np.asarray(z_world, float).copy()
    arm = np.asarray(arm_cam, float).copy()
    return gtsam.CustomFactor(noise, [pose_key, drift_key], _gnss_error(z, arm))


def _gnss_noise(sigma: np.ndarray, kernel: str, k: float):
    base = gtsam.noiseModel.Diagonal.Sigmas(np.asarray(sigma, float))
    est = gtsam.noiseModel.mEstimator
    if kernel == "none":
        return base
    make = {"tukey": est.Tukey, "geman-mcclure": est.GemanMcClure, "huber": est.Huber}[kernel]
    return gtsam.noiseModel.Robust.Create(make.Create(k), base)


@dataclass(frozen=True)
class _Fixes:
    """The fixes attached to frames: local positions, sigmas, frame and time offset."""

    index: np.ndarray  # (G,) into the telemetry's fixes
    z_world: np.ndarray  # (G, 3) [m]
    sigma: np.ndarray  # (G, 3) [m]
    frame: np.ndarray  # (G,) nearest frame
    dt_s: np.ndarray  # (G,) fix time minus frame time (video clock) [s]
    t_s: np.ndarray  # (G,) telemetry time
    outside: int
    screened: np.ndarray | None = None  # (G,) True: a burst found by burst_fixes, no weight


# Burst screening without an IMU (``burst_fixes``): fits over this long each side [s],
# the whitened jump that is a step, the longest burst [s].
BURST_WINDOW_S = 1.0
BURST_STEP = 4.0
BURST_MAX_S = 4.0


def _line_at(t: np.ndarray, z: np.ndarray, t0: float) -> np.ndarray:
    """(3,) a least-squares line through (t, z (K, 3)) evaluated at t0."""
    A = np.stack([np.ones_like(t), t - t0], axis=1)
    return np.linalg.lstsq(A, z, rcond=None)[0][0]


def _steps(t: np.ndarray, z: np.ndarray, sigma: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """(i, jump (3,)) where the track jumps between fix i-1 and i: a line through the
    fixes of the window before and one through the window after disagree there by
    more than ``BURST_STEP`` whitened (local maxima only)."""
    score = np.zeros(len(t))
    jump = np.zeros((len(t), 3))
    for i in range(1, len(t)):
        tb = 0.5 * (t[i - 1] + t[i])
        a = (t >= tb - BURST_WINDOW_S) & (t < tb)
        b = (t >= tb) & (t < tb + BURST_WINDOW_S)
        if a.sum() < 4 or b.sum() < 4:
            continue
        jump[i] = _line_at(t[b], z[b], tb) - _line_at(t[a], z[a], tb)
        score[i] = float(np.linalg.norm(jump[i] / (0.9 * sigma[i])))
    out = []
    for i in np.nonzero(score > BURST_STEP)[0]:
        near = np.abs(t - t[i]) < BURST_WINDOW_S
        if score[i] >= score[near].max():
            out.append((int(i), jump[i]))
    return out


def burst_fixes(t_s: np.ndarray, z_world: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """(G,) True for the fixes inside a multipath burst, told from the track alone.

    A burst is a step of the track and a step back within ``BURST_MAX_S``
    (jumps of opposite sense, their whitened sum under half the larger): the fixes
    between are flagged. For flights without an IMU, where the constant-velocity
    prior lets a 5-20 m burst in a sign-free stretch pass for motion.
    """
    t = np.asarray(t_s, float)
    sigma = np.asarray(sigma, float)
    out = np.zeros(len(t), bool)
    steps = _steps(t, np.asarray(z_world, float), sigma)
    used: set[int] = set()
    for m, (i, ja) in enumerate(steps):
        if m in used:
            continue
        for n in range(m + 1, len(steps)):
            j, jb = steps[n]
            if t[j] - t[i] > BURST_MAX_S:
                break
            wa, wb = ja / sigma[i], jb / sigma[i]  # whitened: a noisy vertical weighs less
            if n not in used and np.linalg.norm(wa + wb) < 0.5 * max(
                np.linalg.norm(wa), np.linalg.norm(wb)
            ):
                out[i:j] = True
                used.update((m, n))
                break
    return out


def _nearest(stamps: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(K,) index of the stamp (N,) nearest to each time t (K,)."""
    j = np.clip(np.searchsorted(stamps, t), 1, max(len(stamps) - 1, 1))
    if len(stamps) < 2:
        return np.zeros(len(t), np.int64)
    return np.where(np.abs(stamps[j - 1] - t) <= np.abs(stamps[j] - t), j - 1, j)


def _attach_fixes(
    telemetry: Telemetry, sign_map: SignMap, stamps: np.ndarray, offset: float, s: FusionSettings
) -> _Fixes | None:
    """The fixes in the map's frame, each on its nearest frame (None without GNSS).

    Raises:
        InputError: GNSS to fuse but the map has no origin.
    """
    g = telemetry.gnss
    if g is None or len(g) == 0 or not s.use_gnss:
        return None
    if sign_map.origin is None:
        raise InputError(
            f"{sign_map.source or 'map'}: the map has no 'origin' (WGS84 anchor) to put the GNSS "
            f"of {telemetry.source} in its frame; add origin: {{lat_deg, lon_deg, height_m}}"
        )
    tv = np.asarray(g.t_s, float) - offset
    frame = _nearest(stamps, tv)
    dt = tv - stamps[frame]
    ok = np.abs(dt) <= s.gnss_max_dt_s
    z = enu_from_geodetic(sign_map.origin, g.lat_deg, g.lon_deg, g.height_m)
    sig = np.stack([g.sigma_h_m, g.sigma_h_m, g.sigma_v_m], axis=1)
    sig = np.maximum(np.asarray(sig, float), s.gnss_min_sigma_m)
    idx = np.nonzero(ok)[0]
    return _Fixes(
        idx, z[idx], sig[idx], frame[idx], dt[idx], np.asarray(g.t_s)[idx], int((~ok).sum())
    )


def _screen(fixes: _Fixes | None, use_imu: bool) -> _Fixes | None:
    """Without an IMU, the fixes in bursts (``burst_fixes``) flagged: no weight, outliers."""
    if fixes is None or use_imu or len(fixes.index) < 8:
        return fixes
    return replace(fixes, screened=burst_fixes(fixes.t_s, fixes.z_world, fixes.sigma))


def _add_gnss(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    fixes: _Fixes,
    vel: np.ndarray,
    s: FusionSettings,
    kernel: str,
) -> list[int]:
    """GNSS factors and the drift chain; returns each fix's factor index."""
    arm = np.asarray(s.cam_t_antenna_m, float)
    out = []
    for k in range(len(fixes.index)):
        # The fix was taken dt after the frame: move it back by the velocity.
        z = fixes.z_world[k] - vel[fixes.frame[k]] * fixes.dt_s[k]
        screened = fixes.screened is not None and fixes.screened[k]
        noise = _gnss_noise(fixes.sigma[k] * (1e3 if screened else 1.0), kernel, s.gnss_kernel_k)
        out.append(graph.size())
        graph.add(gnss_factor(X(int(fixes.frame[k])), D(k), z, arm, noise))
        values.insert(D(k), np.zeros(3))
        if k == 0:
            prior = gtsam.noiseModel.Isotropic.Sigma(3, s.gnss_drift_sigma_m)
            graph.add(gtsam.PriorFactorPoint3(D(0), np.zeros(3), prior))
        else:
            step = max(float(fixes.t_s[k] - fixes.t_s[k - 1]), 1e-3)
            rw = gtsam.noiseModel.Isotropic.Sigma(3, s.gnss_drift_rw * math.sqrt(step))
            graph.add(gtsam.BetweenFactorPoint3(D(k - 1), D(k), np.zeros(3), rw))
    return out


# ----------------------------------------------------------------- IMU factors


def _imu_params(s: FusionSettings) -> gtsam.PreintegrationCombinedParams:
    p = gtsam.PreintegrationCombinedParams.MakeSharedU(s.gravity_m_s2)
    p.setGyroscopeCovariance(np.eye(3) * s.gyro_noise**2)
    p.setAccelerometerCovariance(np.eye(3) * s.accel_noise**2)
    p.setIntegrationCovariance(np.eye(3) * 1e-8)
    p.setBiasOmegaCovariance(np.eye(3) * s.gyro_bias_rw**2)
    p.setBiasAccCovariance(np.eye(3) * s.accel_bias_rw**2)
    p.setBodyPSensor(gtsam.Pose3(np.linalg.inv(np.asarray(s.body_T_cam, float))))
    return p


def _preintegrate(pim, imu: ImuSamples, ta: float, tb: float, max_gap: float) -> bool:
    """Integrate the samples over telemetry times [ta, tb]; False when they do not cover it.

    Sample k holds over [mid(k-1, k), mid(k, k+1)]: no half-sample delay.
    """
    t = imu.t_s
    if len(t) < 2 or ta < t[0] or tb > t[-1]:
        return False
    k0 = int(np.searchsorted(t, ta)) - 1
    k1 = int(np.searchsorted(t, tb)) + 1
    k0, k1 = max(k0, 0), min(k1, len(t))
    if np.any(np.diff(t[k0:k1]) > max_gap):
        return False
    tt = t[k0:k1]
    edges = np.concatenate([[-np.inf], 0.5 * (tt[1:] + tt[:-1]), [np.inf]])
    lo = np.maximum(edges[:-1], ta)
    hi = np.minimum(edges[1:], tb)
    acc, gyro = imu.accel_m_s2, imu.gyro_rad_s
    for m in np.nonzero(hi > lo)[0]:
        pim.integrateMeasurement(acc[k0 + m], gyro[k0 + m], float(hi[m] - lo[m]))
    return True


def _pims(imu: ImuSamples, tel_stamps: np.ndarray, s: FusionSettings) -> list:
    """Per frame i, the preintegrated samples from frame i-1 to i, or None (i = 0, gaps)."""
    params = _imu_params(s)
    zero = gtsam.imuBias.ConstantBias()
    out: list = [None]
    for i in range(1, len(tel_stamps)):
        pim = gtsam.PreintegratedCombinedMeasurements(params, zero)
        ok = _preintegrate(pim, imu, tel_stamps[i - 1], tel_stamps[i], s.imu_max_gap_s)
        out.append(pim if ok else None)
    return out


def _add_imu(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    b: _GraphBuilder,
    pims: list,
    s: FusionSettings,
) -> tuple[int, int]:
    """IMU factors between frames (the CV prior where not covered); (imu, cv) counts."""
    zero = gtsam.imuBias.ConstantBias()
    sig = np.array([s.accel_bias_sigma] * 3 + [s.gyro_bias_sigma] * 3)
    graph.add(gtsam.PriorFactorConstantBias(W(0), zero, gtsam.noiseModel.Diagonal.Sigmas(sig)))
    values.insert(W(0), zero)
    n_imu = n_cv = 0
    for i in range(1, len(pims)):
        values.insert(W(i), zero)
        if pims[i] is not None:
            graph.add(
                gtsam.CombinedImuFactor(X(i - 1), V(i - 1), X(i), V(i), W(i - 1), W(i), pims[i])
            )
            n_imu += 1
            continue
        b.motion_factor(i, graph)
        rw = np.array([s.accel_bias_rw] * 3 + [s.gyro_bias_rw] * 3) * math.sqrt(b.dt(i))
        noise = gtsam.noiseModel.Diagonal.Sigmas(np.maximum(rw, 1e-9))
        graph.add(gtsam.BetweenFactorConstantBias(W(i - 1), W(i), zero, noise))
        n_cv += 1
    return n_imu, n_cv


# ----------------------------------------------------------------- gimbal


# ENU from NED axes, and the camera's (OpenCV) axes in the gimbal's FRD frame.
_ENU_R_NED = np.array([[0, 1.0, 0], [1.0, 0, 0], [0, 0, -1.0]])
_FRD_R_CAM = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, 1.0, 0]])


def world_R_cam_from_gimbal(yaw_deg: float, pitch_deg: float, roll_deg: float) -> np.ndarray:
    """(3, 3) camera (OpenCV axes) in ENU from DJI gimbal angles (yaw from north, clockwise;
    pitch negative looking down; Z-Y-X Euler angles of the gimbal's FRD frame in NED)."""
    return _ENU_R_NED @ _rot_zyx(yaw_deg, pitch_deg, roll_deg) @ _FRD_R_CAM


def gimbal_from_world_R_cam(world_R_cam: np.ndarray) -> tuple[float, float, float]:
    """DJI (yaw, pitch, roll) [deg] of a camera rotation in ENU (inverse of the above)."""
    R = _ENU_R_NED.T @ np.asarray(world_R_cam, float) @ _FRD_R_CAM.T
    pitch = -math.asin(max(-1.0, min(1.0, R[2, 0])))
    yaw = math.atan2(R[1, 0], R[0, 0])
    roll = math.atan2(R[2, 1], R[2, 2])
    return math.degrees(yaw), math.degrees(pitch), math.degrees(roll)


# A frame takes the gimbal sample nearest in time if within this [s].
GIMBAL_MAX_DT_S = 0.1


def _add_gimbal(
    graph: gtsam.NonlinearFactorGraph,
    gimbal: GimbalAngles,
    tel_stamps: np.ndarray,
    s: FusionSettings,
) -> int:
    if len(gimbal) == 0:
        return 0
    noise = gtsam.noiseModel.Isotropic.Sigma(3, s.gimbal_sigma_rad)
    t = np.asarray(gimbal.t_s, float)
    nearest = _nearest(t, np.asarray(tel_stamps, float))
    n = 0
    for i, ti in enumerate(tel_stamps):
        k = int(nearest[i])
        if abs(t[k] - ti) > GIMBAL_MAX_DT_S:
            continue
        R = world_R_cam_from_gimbal(gimbal.yaw_deg[k], gimbal.pitch_deg[k], gimbal.roll_deg[k])
        graph.add(gtsam.PoseRotationPrior3D(X(i), gtsam.Rot3(R), noise))
        n += 1
    return n


# ----------------------------------------------------------------- clock offset


def log_so3(R: np.ndarray) -> np.ndarray:
    """(N, 3) rotation vectors of (N, 3, 3) rotations (angles below pi)."""
    c = np.clip((np.trace(R, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    angle = np.arccos(c)
    w = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], 1)
    scale = np.where(angle < 1e-9, 0.5, angle / (2 * np.sin(np.maximum(angle, 1e-9))))
    return scale[:, None] * w


def _gyro_residuals(
    world_T_cam: np.ndarray, stamps: np.ndarray, observed: np.ndarray, imu: ImuSamples, s
):
    """r(offset) -> (P, 3): vision angular rates minus the mean gyro over each interval.

    Pairs of consecutive observed frames; rates in the camera frame [rad/s];
    the gyro bias (constant) is removed as the mean residual.
    """
    pair = np.nonzero(observed[1:] & observed[:-1])[0] + 1
    R = world_T_cam[:, :3, :3]
    dt = np.maximum(stamps[pair] - stamps[pair - 1], 1e-6)
    w_vis = log_so3(np.swapaxes(R[pair - 1], 1, 2) @ R[pair]) / dt[:, None]
    t = np.asarray(imu.t_s, float)
    g = np.asarray(imu.gyro_rad_s, float)
    cum = np.concatenate(
        [np.zeros((1, 3)), np.cumsum(0.5 * (g[1:] + g[:-1]) * np.diff(t)[:, None], 0)]
    )
    cam_R_body = np.asarray(s.body_T_cam, float)[:3, :3].T

    def residuals(offset: float, keep: np.ndarray | None = None) -> np.ndarray:
        ta, tb = stamps[pair - 1] + offset, stamps[pair] + offset
        inside = (ta >= t[0]) & (tb <= t[-1])
        if keep is not None:
            inside &= np.isin(np.arange(len(pair)), keep)
        G = np.stack(
            [np.interp(tb, t, cum[:, a]) - np.interp(ta, t, cum[:, a]) for a in range(3)], 1
        )
        r = w_vis - (G / dt[:, None]) @ cam_R_body.T
        r = r[inside]
        return (r - r.mean(axis=0) if len(r) else r), np.nonzero(inside)[0]

    return residuals


def _gnss_residuals(
    world_T_cam: np.ndarray,
    stamps: np.ndarray,
    observed: np.ndarray,
    z: np.ndarray,
    tz: np.ndarray,
    s,
):
    """r(offset) -> (G, 3): GNSS fixes minus the vision antenna at the fix time (mean removed)."""
    arm = np.asarray(s.cam_t_antenna_m, float)
    ant = world_T_cam[:, :3, 3] + world_T_cam[:, :3, :3] @ arm
    seen = np.nonzero(observed)[0]

    def residuals(offset: float, keep: np.ndarray | None = None) -> np.ndarray:
        tv = tz - offset
        j = np.searchsorted(stamps[seen], tv)
        ok = (j > 0) & (j < len(seen))
        ok[ok] &= seen[j[ok]] - seen[j[ok] - 1] == 1  # between two observed neighbours
        if keep is not None:
            ok &= np.isin(np.arange(len(tz)), keep)
        if not ok.any():
            return np.zeros((0, 3)), np.zeros(0, np.int64)
        a, b = seen[j[ok] - 1], seen[j[ok]]
        u = ((tv[ok] - stamps[a]) / np.maximum(stamps[b] - stamps[a], 1e-9))[:, None]
        r = z[ok] - ((1 - u) * ant[a] + u * ant[b])
        r = r - np.median(r, axis=0)
        n = np.linalg.norm(r, axis=1, keepdims=True)
        bound = GNSS_CLOCK_BOUND_M
        r = np.where(n > bound, r * bound / np.maximum(n, 1e-9), r)  # multipath bounded
        return r, np.nonzero(ok)[0]

    return residuals


# The GNSS clock scan bounds each residual's norm to this [m] (multipath).
GNSS_CLOCK_BOUND_M = 5.0


def _golden(f, a: float, b: float, tol: float = 1e-5) -> float:
    """Minimiser of a unimodal f on [a, b] (golden-section search)."""
    g = (math.sqrt(5) - 1) / 2
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = f(c), f(d)
    while b - a > tol:
        if fc < fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = f(c)
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = f(d)
    return 0.5 * (a + b)


def _gauss_newton_sigma(
    residuals, best: float, ids: np.ndarray, noise_sigma: float | None
) -> float:
    """The offset's sigma from the cost's curvature, on the items in all three evaluations.

    Moving the offset by +-h can move a fix or a frame pair across the edge of
    the overlap (GNSS: between two observed frames; gyro: inside the IMU's
    span), so the residuals at best+-h may hold other items than at best: the
    derivative is taken on the items common to the three (NaN when none).
    The residuals' scale is their own RMS, at least ``noise_sigma`` when given
    (the fixes' claimed sigma: a fit to few fixes looks better than they are).
    """
    h = 1e-3
    common = np.intersect1d(np.intersect1d(ids, residuals(best + h)[1]), residuals(best - h)[1])
    if len(common) == 0:
        return float("nan")
    # The mean/median each residual function removes is over the items it has:
    # the same items at the three offsets, else it jumps when one item enters.
    (r, _), (rp, _), (rm, _) = (residuals(o, common) for o in (best, best + h, best - h))
    jac = ((rp - rm) / (2 * h)).reshape(-1)
    if not np.any(jac):
        return float("inf")
    var = float(np.sum(r**2)) / max(r.size - 4, 1)
    if noise_sigma is not None:
        var = max(var, noise_sigma**2)
    return math.sqrt(var / float(jac @ jac))


def _scan_and_refine(
    residuals,
    s: FusionSettings,
    source: str,
    noise_sigma: float | None = None,
    missing_cost: float | None = None,
) -> ClockOffset:
    """Coarse scan of the mean squared residual, golden refinement; the sigma by a
    block jackknife (the residuals are correlated in time: drift, shared poses),
    at least the Gauss-Newton one (``_gauss_newton_sigma``). A minimum within
    two steps of the scan's edge is no minimum: sigma inf.

    ``residuals(offset, keep=None)`` gives ((P, 3) residuals, (P,) their item
    ids, sorted), on the items ``keep`` only when given. With ``missing_cost``
    an item the scan matches at some offset but not at this one costs that
    (its bounded residual's worst): the mean over fewer items would favour the
    offsets where the fixes barely overlap the frames (a GNSS-only scan then
    ends at its edge).
    """
    grid = np.arange(-s.clock_search_s, s.clock_search_s + 0.5 * s.clock_step_s, s.clock_step_s)
    at_grid = [residuals(float(o)) for o in grid]  # every scan's grid: computed once
    universe = np.zeros(0, np.int64)
    if missing_cost is not None:
        universe = np.unique(np.concatenate([ids for _, ids in at_grid]))

    def cost(offset: float, drop: np.ndarray | None = None, got=None) -> float:
        r, ids = residuals(offset) if got is None else got
        if drop is not None:
            r = r[~np.isin(ids, drop)]
        if missing_cost is None:
            return float(np.mean(r**2)) if r.size else float("inf")
        n_all = len(universe) - (0 if drop is None else int(np.isin(universe, drop).sum()))
        if not r.size or n_all == 0:
            return float("inf")
        return (float(np.sum(r**2)) + (n_all - len(r)) * missing_cost) / (3 * n_all)

    def scan(drop: np.ndarray | None = None) -> float:
        costs = np.array([cost(float(o), drop, at_grid[m]) for m, o in enumerate(grid)])
        if not np.isfinite(costs).any():
            return float("nan")
        k = int(np.nanargmin(costs))
        lo, hi = float(grid[k]) - s.clock_step_s, float(grid[k]) + s.clock_step_s
        return _golden(lambda o: cost(o, drop), lo, hi)

    best = scan()
    if not math.isfinite(best):
        log.warning("clock offset: no overlap of telemetry and vision; using 0")
        return ClockOffset(0.0, float("nan"), source)
    if abs(best) >= s.clock_search_s - 2.5 * s.clock_step_s:
        log.warning("clock offset: the scan's best %+.3f s is at its edge; not determined", best)
        return ClockOffset(best, float("inf"), source)
    ids = residuals(best)[1]
    gn = _gauss_newton_sigma(residuals, best, ids, noise_sigma)
    if len(ids) < 2 * JACKKNIFE_BLOCKS:
        return ClockOffset(best, gn, source)
    est = np.array([scan(b) for b in np.array_split(np.unique(ids), JACKKNIFE_BLOCKS)])
    jack = math.sqrt((len(est) - 1) / len(est) * float(np.sum((est - est.mean()) ** 2)))
    return ClockOffset(best, float(np.nanmax([jack, gn])), source)


# Contiguous blocks of the clock residuals left out in turn for the offset's sigma.
JACKKNIFE_BLOCKS = 10


def _gnss_sigma_h(sigma_h_m: np.ndarray, s: FusionSettings) -> float:
    """The fixes' typical horizontal sigma [m] (median claimed, at least the floor)."""
    return max(float(np.median(sigma_h_m)), s.gnss_min_sigma_m) if len(sigma_h_m) else math.inf


def _gnss_speed(telemetry: Telemetry, sign_map: SignMap, baseline_s: float = 2.0) -> float:
    """The fixes' 75th-percentile speed over ``baseline_s`` [m/s] (0 without GNSS).

    Over the whole flight (the fused GNSS matters most where no sign is seen,
    and the vision poses there are a guess); the baseline keeps white noise
    from reading as speed; noise left makes it larger: the stricter limit.
    """
    g = telemetry.gnss
    if g is None or len(g) < 2 or sign_map.origin is None:
        return 0.0
    t = np.asarray(g.t_s, float)
    z = enu_from_geodetic(sign_map.origin, g.lat_deg, g.lon_deg, g.height_m)
    j = np.searchsorted(t, t + baseline_s)
    ok = j < len(t)
    if not ok.any():
        j, ok = np.full(len(t), len(t) - 1), np.arange(len(t)) == 0
    dt = np.maximum(t[j[ok]] - t[ok], 1e-6)
    v = np.linalg.norm((z[j[ok]] - z[ok])[:, :2], axis=1) / dt
    return float(np.percentile(v, 75))


def clock_shift_limit_s(
    world_T_cam: np.ndarray,
    stamps_s: np.ndarray,
    observed: np.ndarray,
    sigma_h_m: float,
    s,
    gnss_speed_m_s: float = 0.0,
) -> float:
    """The largest clock sigma [s] the fusion accepts on this flight.

    A clock error dt puts every fix v dt along the track from where it was
    taken; the fused graph has no clock state, so that shift is read as GNSS
    error it does not know of, and the fused sigmas do not include it. Allowed:
    ``clock_max_shift`` times the fixes' sigma at the flight's fast speed: the
    90th percentile of the vision speed over observed frames or the GNSS
    track's speed (``_gnss_speed``), whichever is larger, at least 0.1 m/s.
    Without GNSS the floor ``gnss_min_sigma_m`` stands for the sigma.
    """
    seen = np.nonzero(observed)[0]
    pair = seen[1:][np.diff(seen) == 1]
    speed = max(gnss_speed_m_s, 0.1)
    if len(pair):
        dt = np.maximum(stamps_s[pair] - stamps_s[pair - 1], 1e-6)
        v = np.linalg.norm(world_T_cam[pair, :3, 3] - world_T_cam[pair - 1, :3, 3], axis=1) / dt
        speed = max(speed, float(np.percentile(v, 90)))
    return s.clock_max_shift * sigma_h_m / speed


def _fuses_imu(telemetry: Telemetry, s: FusionSettings) -> bool:
    """The IMU is used (clock scan, factors): asked for and at least two samples."""
    return s.use_imu and telemetry.imu is not None and len(telemetry.imu) > 1


def estimate_clock_offset(
    world_T_cam: np.ndarray,
    stamps_s: np.ndarray,
    observed: np.ndarray,
    telemetry: Telemetry,
    sign_map: SignMap,
    settings: FusionSettings,
) -> ClockOffset:
    """The telemetry-minus-video offset from a vision trajectory (gyro first, else GNSS).

    Args:
        world_T_cam: (N, 4, 4) vision poses; stamps_s: (N,) video times [s];
        observed: (N,) True where the pose is from signs (not bridged).
    """
    s = settings
    if s.clock_offset_s is not None:
        return ClockOffset(float(s.clock_offset_s), 0.0, "fixed")
    if telemetry.clock_is_video:
        return ClockOffset(0.0, 0.0, "video")
    if _fuses_imu(telemetry, s):
        res = _gyro_residuals(world_T_cam, stamps_s, observed, telemetry.imu, s)
        return _scan_and_refine(res, s, "gyro")
    g = telemetry.gnss
    if s.use_gnss and g is not None and len(g) > 1 and sign_map.origin is not None:
        z = enu_from_geodetic(sign_map.origin, g.lat_deg, g.lon_deg, g.height_m)
        res = _gnss_residuals(world_T_cam, stamps_s, observed, z, np.asarray(g.t_s, float), s)
        sig = _gnss_sigma_h(g.sigma_h_m, s)
        return _scan_and_refine(res, s, "gnss", sig, GNSS_CLOCK_BOUND_M**2)
    return ClockOffset(0.0, float("nan"), "none")


# ----------------------------------------------------------------- the solve


def vision_solve(
    observations: Sequence[FrameObservations],
    sign_map: SignMap,
    camera: CameraModel,
    stamps_s: np.ndarray,
    settings: SmootherSettings,
) -> SmootherResult:
    """The vision-only smoother from per-frame PnP: a Huber solve, then ``settings``' kernel."""
    meas = collect_measurements(observations, sign_map, camera)
    pnp = run_per_frame(observations, sign_map, camera, "pnp", PerFrameSettings())
    init = [p.world_T_cam for p in pnp]
    default = default_pose(sign_map)
    r = smooth_batch(meas, stamps_s, init, camera, replace(settings, kernel="huber"), default)
    return smooth_batch(meas, stamps_s, list(r.world_T_cam), camera, settings, default)


def _inliers(meas, vision: SmootherResult, camera: CameraModel, s: FusionSettings):
    """The measurements the vision solution keeps (residual whitened per axis, as the
    factors whiten it, within Tukey's k)."""
    if len(meas.frame) == 0:
        return meas
    res = np.sqrt(whitened_chi2(meas, vision, camera))
    return meas.subset(res <= s.smoother.tukey_k)


def _initial(
    vision_T: np.ndarray, observed: np.ndarray, stamps: np.ndarray, pims: list | None
) -> tuple[np.ndarray, np.ndarray]:
    """Initial poses and velocities: vision where signs were seen, IMU dead reckoning between."""
    poses = np.array(vision_T, float)
    vel = _velocities(poses, stamps)
    if pims is None:
        return poses, vel
    zero = gtsam.imuBias.ConstantBias()
    for i in range(1, len(poses)):
        if observed[i] or pims[i] is None:
            continue
        state = pims[i].predict(gtsam.NavState(gtsam.Pose3(poses[i - 1]), vel[i - 1]), zero)
        poses[i] = state.pose().matrix()
        vel[i] = state.velocity()
    return poses, vel


@dataclass(frozen=True)
class _Graph:
    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    gnss_factor: list[int]
    counts: dict[str, int]


@dataclass(frozen=True)
class _Problem:
    b: _GraphBuilder
    telemetry: Telemetry
    tel_stamps: np.ndarray
    fixes: _Fixes | None
    pims: list | None
    enu: bool  # the map has an origin: its frame is ENU (the gimbal's yaw is from north)
    s: FusionSettings


def _build(p: _Problem, poses: np.ndarray, vel: np.ndarray, kernel: str) -> _Graph:
    """Every factor of the fused graph and the initial values."""
    b, s = p.b, p.s
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    b.landmark_factors(graph, values)
    b.first_priors(gtsam.Pose3(poses[0]), graph, 0)
    values.insert(BIAS_KEY, gtsam.imuBias.ConstantBias())
    n_proj = 0
    for i in range(len(poses)):
        values.insert(X(i), gtsam.Pose3(poses[i]))
        values.insert(V(i), vel[i])
        before = graph.size()
        b.projection_factors(i, graph)
        n_proj += graph.size() - before
    if p.pims is not None:
        n_imu, n_cv = _add_imu(graph, values, b, p.pims, s)
    else:
        for i in range(1, len(poses)):
            b.motion_factor(i, graph)
        n_imu, n_cv = 0, len(poses) - 1
    gnss = [] if p.fixes is None else _add_gnss(graph, values, p.fixes, vel, s, kernel)
    n_gimbal = 0
    if s.use_gimbal and p.telemetry.gimbal is not None and p.enu:
        n_gimbal = _add_gimbal(graph, p.telemetry.gimbal, p.tel_stamps, s)
    counts = {
        "frames": len(poses),
        "projection_factors": n_proj,
        "imu_factors": n_imu,
        "cv_factors": n_cv,
        "gnss_used": len(gnss),
        "gnss_outside": 0 if p.fixes is None else p.fixes.outside,
        "gimbal_priors": n_gimbal,
    }
    return _Graph(graph, values, gnss, counts)


def _ordering(p: _Problem, n: int) -> gtsam.Ordering:
    """Time order (each frame's GNSS drifts, pose, velocity, IMU bias), then the rest.

    The chain ordering of the smoother (``smoother.chain_ordering``) with the
    fusion's keys in their frames: LM and the one-pass marginals
    (``smoother.batch_covariances``) both want it.
    """
    order = gtsam.Ordering()
    by_frame: dict[int, list[int]] = {}
    if p.fixes is not None:
        for k, i in enumerate(p.fixes.frame.tolist()):
            by_frame.setdefault(int(i), []).append(k)
    for i in range(n):
        for k in by_frame.get(i, ()):
            order.push_back(D(k))
        order.push_back(X(i))
        order.push_back(V(i))
        if p.pims is not None:
            order.push_back(W(i))
    order.push_back(BIAS_KEY)
    for j in range(len(p.b.m.landmark_code)):
        order.push_back(gtsam.symbol("l", j))
    return p.b.ordered(order)


def _solve(g: _Graph, order: gtsam.Ordering, s: FusionSettings) -> gtsam.Values:
    params = gtsam.LevenbergMarquardtParams()
    params.setOrdering(order)
    params.setMaxIterations(s.lm_max_iterations)
    params.setRelativeErrorTol(1e-7)
    params.setAbsoluteErrorTol(1e-9)
    opt = gtsam.LevenbergMarquardtOptimizer(g.graph, g.values, params)
    result = opt.optimize()
    log.debug("fusion LM: %d iterations, error %.6g", opt.iterations(), opt.error())
    return result


def pose_statuses(
    kept, poses: np.ndarray, landmarks: np.ndarray, sigma_xyz: np.ndarray, camera, st, own=None
) -> tuple[PoseStatus, ...]:
    """Per frame: ``bridged`` without kept keypoints, else ``classify`` on its residuals
    and its marginal's worst axis (the smoothed and the fused methods' statuses).

    Where the marginal is not finite the worst axis is ``own(ids, world_T_cam,
    world_points)`` (how well the frame's own keypoints fix it), inf without ``own``.
    """
    order = np.argsort(kept.frame, kind="stable")
    starts = np.searchsorted(kept.frame[order], np.arange(len(poses) + 1))
    noise = kept.pixel_noise()  # per keypoint, as the factors have it
    out = []
    for i in range(len(poses)):
        ids = order[starts[i] : starts[i + 1]]
        if len(ids) == 0:
            out.append(PoseStatus.BRIDGED)
            continue
        world = landmarks[kept.landmark[ids]]
        uv, _, _ = pixels_and_pose_jacobian(camera, poses[i], world)
        chi2 = float(np.sum(whitened(kept.px[ids] - uv, noise[ids]) ** 2))
        if np.all(np.isfinite(sigma_xyz[i])):  # the marginal: what the user is given
            worst = float(np.max(sigma_xyz[i]))
        else:
            worst = math.inf if own is None else own(ids, poses[i], world)
        out.append(classify(len(ids), worst, chi2, 2 * len(ids), st))
    return tuple(out)


def _gnss_outliers(g: _Graph, result: gtsam.Values, fixes: _Fixes | None, k: float) -> np.ndarray:
    if fixes is None:
        return np.zeros(0, bool)
    out = np.zeros(len(g.gnss_factor), bool)
    for m, idx in enumerate(g.gnss_factor):
        e = np.asarray(g.graph.at(idx).unwhitenedError(result))
        out[m] = float(np.linalg.norm(e / fixes.sigma[m])) > k
    return out if fixes.screened is None else out | fixes.screened


def _usable(telemetry: Telemetry | None, s: FusionSettings) -> bool:
    if telemetry is None:
        return False
    streams = [
        (s.use_gnss, telemetry.gnss),
        (s.use_imu, telemetry.imu),
        (s.use_gimbal, telemetry.gimbal),
    ]
    return any(use and x is not None and len(x) > 0 for use, x in streams)


def _unestimated_clock(s: FusionSettings) -> ClockOffset:
    """The offset when nothing is fused: the given one, else 0 with an unknown sigma."""
    if s.clock_offset_s is not None:
        return ClockOffset(float(s.clock_offset_s), 0.0, "fixed")
    return ClockOffset(0.0, float("nan"), "none")


def _vision_only(
    vision: SmootherResult,
    kept,
    camera,
    stamps,
    s: FusionSettings,
    t0: float,
    failed: int = 0,
    refused: str = "",
):
    """The vision result as a FusionResult (no telemetry, the fused solve failed, or
    the fusion refused with the note ``refused``)."""
    n = len(vision.world_T_cam)
    extra = {"failed": failed} if failed else {}
    return FusionResult(
        world_T_cam=vision.world_T_cam.copy(),
        sigma_xyz=vision.sigma_xyz.copy(),
        cov6=vision.cov6,
        status=pose_statuses(
            kept, vision.world_T_cam, vision.landmarks_world, vision.sigma_xyz, camera, s.status
        ),
        observed=vision.observed.copy(),
        signs_used=vision.signs_used.copy(),
        velocity_world_m_s=_velocities(vision.world_T_cam, stamps),
        gyro_bias=np.zeros((n, 3)),
        accel_bias=np.zeros((n, 3)),
        gnss_drift_m=np.zeros((0, 3)),
        gnss_used=np.zeros(0, np.int64),
        gnss_outlier=np.zeros(0, bool),
        clock=_unestimated_clock(s),
        counts={"frames": n, **extra, **({"refused": 1} if refused else {})},
        landmarks_world=vision.landmarks_world.copy(),
        seconds=time.perf_counter() - t0,
        refused=bool(refused),
        notes=(refused,) if refused else (),
    )


_CLOCK_FROM = {"gnss": "from GNSS alone", "gyro": "from the gyro", "none": "(nothing to scan)"}


def _clock_refusal(
    clock: ClockOffset, vision: SmootherResult, stamps, telemetry: Telemetry, sign_map, s
) -> str:
    """The note refusing the fusion on an undetermined clock, or "" when it is good enough."""
    if clock.source in ("fixed", "video"):
        return ""
    g = telemetry.gnss
    sigma_h = _gnss_sigma_h(g.sigma_h_m, s) if g is not None and len(g) else s.gnss_min_sigma_m
    v = _gnss_speed(telemetry, sign_map)
    limit = clock_shift_limit_s(vision.world_T_cam, stamps, vision.observed, sigma_h, s, v)
    if math.isfinite(clock.sigma_s) and clock.sigma_s <= limit:
        return ""
    pm = f"+-{clock.sigma_s:.2f} s" if math.isfinite(clock.sigma_s) else "no minimum"
    return (
        f"fused: not computed: the clock offset between the video and {telemetry.source} is not "
        f"determined {_CLOCK_FROM.get(clock.source, '')} ({pm}, {limit:.2f} s needed at this "
        "flight's speed): give --telemetry-offset S; the results are vision only"
    )


def _video_clock_note(clock: ClockOffset, telemetry: Telemetry) -> tuple[str, ...]:
    if clock.source != "video":
        return ()
    return (
        f"clock: {telemetry.source} is on the video's own clock (one subtitle per frame): "
        "offset 0, not estimated (--telemetry-offset S to change it)",
    )


def _extract(result: gtsam.Values, n: int) -> tuple[np.ndarray, np.ndarray]:
    poses = np.array([result.atPose3(X(i)).matrix() for i in range(n)])
    vel = np.array([result.atVector(V(i)) for i in range(n)]).reshape(n, 3)
    return poses, vel


def _fused_result(
    p: _Problem,
    g: _Graph,
    result: gtsam.Values,
    order: gtsam.Ordering,
    clock: ClockOffset,
    camera,
    t0,
):
    b, s = p.b, p.s
    n = len(p.tel_stamps)
    poses, vel = _extract(result, n)
    n_lm = len(b.m.landmark_code)
    lms = np.array([result.atPoint3(gtsam.symbol("l", j)) for j in range(n_lm)]).reshape(-1, 3)
    cov6 = batch_covariances(g.graph, result, n, order) if s.smoother.compute_sigmas else None
    sigma = _sigmas_from(cov6, poses)
    gb, ab = np.zeros((n, 3)), np.zeros((n, 3))
    if p.pims is not None:
        for i in range(n):
            bias = result.atConstantBias(W(i))
            gb[i], ab[i] = bias.gyroscope(), bias.accelerometer()
    n_fix = 0 if p.fixes is None else len(p.fixes.index)
    drift = np.array([result.atPoint3(D(k)) for k in range(n_fix)]).reshape(-1, 3)
    outlier = _gnss_outliers(g, result, p.fixes, s.gnss_kernel_k)
    observed, signs = _observed_and_signs(b.m)
    counts = dict(g.counts, gnss_outliers=int(outlier.sum()))
    return FusionResult(
        world_T_cam=poses,
        sigma_xyz=sigma,
        cov6=cov6,
        status=pose_statuses(b.m, poses, lms, sigma, camera, s.status),
        observed=observed,
        signs_used=signs,
        velocity_world_m_s=vel,
        gyro_bias=gb,
        accel_bias=ab,
        gnss_drift_m=drift,
        gnss_used=np.zeros(0, np.int64) if p.fixes is None else p.fixes.index.copy(),
        gnss_outlier=outlier,
        clock=clock,
        counts=counts,
        landmarks_world=lms,
        seconds=time.perf_counter() - t0,
    )


def fuse_trajectory(
    observations: Sequence[FrameObservations],
    sign_map: SignMap,
    camera: CameraModel,
    frame_stamps_s: np.ndarray,
    telemetry: Telemetry | None,
    settings: FusionSettings | None = None,
    vision_result: SmootherResult | None = None,
) -> FusionResult:
    """The trajectory from the signs and the drone's GNSS, IMU and gimbal.

    Args:
        observations: the flight's observations (raw pixels), one per frame.
        sign_map: the surveyed signs (with an ``origin`` for GNSS and gimbal).
        camera: the camera.
        frame_stamps_s: (N,) video time of each frame [s].
        telemetry: the drone's sensors, or None.
        settings: what to fuse and how.
        vision_result: the vision-only smoothed result (initial values, the
            keypoints it keeps, the clock scan); solved here when None.

    Returns:
        The FusionResult; without usable telemetry, the vision result as is.
    """
    s = settings or FusionSettings()
    t0 = time.perf_counter()
    stamps = np.asarray(frame_stamps_s, float)
    meas = collect_measurements(observations, sign_map, camera)
    vision = vision_result
    if vision is None:
        vision = vision_solve(observations, sign_map, camera, stamps, s.smoother)
    kept = _inliers(meas, vision, camera, s)
    if not _usable(telemetry, s):
        return _vision_only(vision, kept, camera, stamps, s, t0)
    clock = estimate_clock_offset(
        vision.world_T_cam, stamps, vision.observed, telemetry, sign_map, s
    )
    refusal = _clock_refusal(clock, vision, stamps, telemetry, sign_map, s)
    if refusal:
        log.warning("%s", refusal)
        # The clock stays undetermined (0, sigma NaN): the guess is in the note only, and
        # the GNSS track of the geodetic outputs is not placed on it either.
        return _vision_only(vision, kept, camera, stamps, s, t0, refused=refusal)
    tel_stamps = stamps + clock.offset_s
    use_imu = _fuses_imu(telemetry, s)
    p = _Problem(
        b=_GraphBuilder(kept, stamps, camera, replace(s.smoother, motion=CONSTANT_VELOCITY)),
        telemetry=telemetry,
        tel_stamps=tel_stamps,
        fixes=_screen(_attach_fixes(telemetry, sign_map, stamps, clock.offset_s, s), use_imu),
        pims=_pims(telemetry.imu, tel_stamps, s) if use_imu else None,
        enu=sign_map.origin is not None,
        s=s,
    )
    poses, vel = _initial(vision.world_T_cam, _observed_and_signs(kept)[0], stamps, p.pims)
    # A redescending kernel needs a good start: a Huber solve first.
    kernels = [s.gnss_kernel] if s.gnss_kernel in ("huber", "none") else ["huber", s.gnss_kernel]
    order = _ordering(p, len(stamps))
    try:
        for kernel in kernels if p.fixes is not None else kernels[-1:]:
            g = _build(p, poses, vel, kernel)
            result = _solve(g, order, s)
            poses, vel = _extract(result, len(stamps))
    except RuntimeError as exc:  # gtsam: an indeterminant system; the flight goes on
        log.warning("fusion failed (%s); the fused poses are the vision-only ones", exc)
        return _vision_only(vision, kept, camera, stamps, s, t0, failed=1)
    return replace(
        _fused_result(p, g, result, order, clock, camera, t0),
        notes=_video_clock_note(clock, telemetry),
    )
