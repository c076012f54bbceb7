"""Library entry point: every method's trajectory from a flight's observations.

``estimate_trajectories`` runs the paper's per-frame baseline, per-frame PnP
and the gtsam smoother (batch or iSAM2) and builds the outlier report;
``signpose.io.results`` writes the result. The pipeline calls these; the
CLI is a thin layer over them.

The smoother's path: keypoints far from the frame's RANSAC PnP pose are
gated; a Huber solve; rounds of the innovation test against the pose the
neighbours predict (``estimator.robust``); the motion prior chosen from the
flight (``estimator.tuning``); the final solve with a redescending kernel.
Each pose then gets its status (``estimator.status``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace

import numpy as np
from signpose.estimator.camera import (
    CameraModel,
    undistort_px_jacobian,
    undistorted_sigmas,
)
from signpose.estimator.fusion import (
    FusionResult,
    FusionSettings,
    fuse_trajectory,
    on_smoother,
    pose_statuses,
)
from signpose.estimator.intrinsics_check import IntrinsicsCheck, check_intrinsics, disagreement
from signpose.estimator.intrinsics_share import with_intrinsics_shares, with_principal_share
from signpose.estimator.noise_scale import (
    exact_map_pose,
    inflated_pose,
    pixel_noise_scale,
    pose_noise_scale,
    residual_noise_scale,
    scaled_frames,
    scaled_pose,
)
from signpose.estimator.perframe import (
    PER_FRAME_METHODS,
    FramePose,
    PerFrameRun,
    PerFrameSettings,
    PoseFailure,
    SolvedPnP,
    run_per_frame,
)
from signpose.estimator.projection import (
    MIN_DEPTH_M,
    cam_points,
    pixels_and_pose_jacobian,
    pose_covariance,
    position_cov_world,
)
from signpose.estimator.robust import (
    OutlierSettings,
    Rejection,
    RejectionTest,
    predict_from_neighbours,
    sign_groups,
    worst_innovations,
)
from signpose.estimator.smoother import (
    FIXED,
    GNC,
    HUBER,
    TUKEY,
    Measurements,
    SmootherResult,
    SmootherSettings,
    collect_measurements,
    default_pose,
    project,
    residuals_px,
    smooth_batch,
    smooth_isam2,
    whitened_chi2,
)
from signpose.estimator.status import (
    PoseState,
    PoseStatus,
    StatusSettings,
    classify,
    worst_axis_sigma,
)
from signpose.estimator.telemetry import Telemetry
from signpose.estimator.tuning import MotionChoice, TuningSettings, tune_motion_prior
from signpose.frontend.observations import FrameObservations, SignObservation
from signpose.maps.loader import MapSign, SignMap

from signpose.core.errors import InputError

log = logging.getLogger(__name__)

METHODS = ("baseline", "pnp", "smoothed")
SOLVERS = ("batch", "isam2")


@dataclass(frozen=True)
class EstimatorSettings:
    """What to estimate and how.

    Attributes:
        methods: which of "baseline", "pnp", "smoothed" to run.
        solver: "batch" (Levenberg-Marquardt) or "isam2" (also gives the
            causal per-frame result as method "causal").
        per_frame: settings of the baseline and PnP.
        smoother: settings of the factor graph.
        misdecode_ratio: an observation "looks mis-decoded" when another
            sign's centre fits it at least this many times better.
        gate_px: keypoints further than this from where the frame's own
            per-frame (RANSAC PnP) pose projects their landmark are left out of
            the smoother (0 disables). Huber bounds each outlier's pull but not
            their sum: a few hundred gross outliers (false detections, wrong
            codes) pulling with constant force moved a 120-frame flight by
            1.5 m along the weakly observed lateral/rotation direction in our
            tests (30 deg lens, 6-7 signs per frame). They stay in the report.
        outliers: the innovation test against the neighbours' prediction.
        status: when a pose is ``weak`` or ``suspect``.
        tune_motion: choose the motion prior's densities from the flight
            (held-out frames, ``estimator.tuning``) instead of the smoother
            settings' fixed values.
        tuning: the candidates and the hold-out.
        final_kernel: the kernel of the final solve after the Huber rounds:
            ``"tukey"`` (redescending), ``"gnc"`` (truncated least squares by
            graduated non-convexity) or ``"huber"`` (no final solve). Tukey:
            on the fault scenario (scripts/eval_estimator.py, seeds 0-4) its
            worst-axis MAE was lower than GNC's on 4 of 5 flights (0.039 vs
            0.041 m on seed 0) and it is cheaper (one LM solve, not GNC's
            sequence of them).
        scale_pixel_noise: scale every keypoint sigma up by the flight's own
            a posteriori noise factor from the PnP residuals
            (``estimator.noise_scale``) before the statuses and the smoother.
        focal_sigma_rel: the camera calibration's focal length sigma, as a
            fraction of it (0.01: 1 %), added to the position sigmas of every
            method that has them (``estimator.intrinsics_share``: the video
            cannot show a focal length error; 0: the calibration is exact).
        principal_sigma_px: the calibration's principal point sigma on each
            image axis [px], added the same way (``intrinsics_share``); 0: exact,
            and left out of ``to_dict`` (report.json as before the option).
    """

    methods: tuple[str, ...] = METHODS
    solver: str = "batch"
    per_frame: PerFrameSettings = field(default_factory=PerFrameSettings)
    smoother: SmootherSettings = field(default_factory=SmootherSettings)
    misdecode_ratio: float = 5.0
    gate_px: float = 30.0
    outliers: OutlierSettings = field(default_factory=OutlierSettings)
    status: StatusSettings = field(default_factory=StatusSettings)
    tune_motion: bool = True
    tuning: TuningSettings = field(default_factory=TuningSettings)
    final_kernel: str = TUKEY
    scale_pixel_noise: bool = True
    focal_sigma_rel: float = 0.0
    principal_sigma_px: float = 0.0

    def to_dict(self) -> dict:
        d = asdict(self)
        if not self.principal_sigma_px:
            del d["principal_sigma_px"]
        return d


def settings_from_options(
    solver: str = "batch",
    map_fixed: bool = False,
    sigmas: bool = True,
    focal_sigma_rel: float = 0.0,
    principal_sigma_px: float = 0.0,
) -> EstimatorSettings:
    """The settings that ``signpose run``'s and ``batch``'s estimator options make
    (--solver, --map-fixed, --no-sigmas, --focal-sigma, --principal-sigma)."""
    smoother = SmootherSettings(compute_sigmas=sigmas)
    if map_fixed:
        smoother = replace(smoother, landmarks=FIXED)
    return EstimatorSettings(
        solver=solver,
        smoother=smoother,
        focal_sigma_rel=focal_sigma_rel,
        principal_sigma_px=principal_sigma_px,
    )


@dataclass(frozen=True)
class MethodEstimate:
    """One method's trajectory over all frames.

    Attributes:
        name: "baseline", "pnp", "smoothed", "causal" or "fused".
        stamps_s: (N,) frame times [s].
        world_T_cam: (N, 4, 4) camera poses; identity where not ``valid``.
        valid: (N,) True where the method gives a pose.
        sigma_xyz: (N, 3) position standard deviation, world axes [m]; NaN
            where unknown (sigmas not computed, the baseline: see
            ``BASELINE_SIGMAS``). PnP's is the pixel noise and, unless the map
            is taken as exact, the survey error of the signs the frame sees
            (the same error for every frame that sees them: it does not
            average out over frames); the smoother's is its marginal.
        signs_used: (N,) distinct map signs used per frame.
        status: (N,) how far each pose can be trusted (a PoseStatus), or why
            there is none (a PoseFailure).
        survey_sigma_xyz: (N, 3) the survey's share of ``sigma_xyz`` [m]
            (``SmootherResult.survey_sigma_xyz``: the part of the error that
            every frame seeing the same signs shares), or None (per-frame
            methods, no marginals).
    """

    name: str
    stamps_s: np.ndarray
    world_T_cam: np.ndarray
    valid: np.ndarray
    sigma_xyz: np.ndarray
    signs_used: np.ndarray
    status: tuple[PoseState, ...]
    survey_sigma_xyz: np.ndarray | None = None

    @property
    def coverage(self) -> float:
        return float(np.mean(self.valid)) if len(self.valid) else 0.0


@dataclass(frozen=True)
class Outlier:
    """A measurement the Huber kernel down-weights.

    Attributes:
        frame: frame index; code/keypoint: what was observed;
        residual_px: reprojection residual at the solution [px];
        weight: the Huber weight (< 1).
    """

    frame: int
    code: str
    keypoint: str
    residual_px: float
    weight: float


@dataclass(frozen=True)
class Misdecode:
    """An observation whose pixels fit another sign far better than its decoded code's.

    Attributes:
        frame: frame index; code: the decoded code; likely_code: the better fit;
        residual_px / likely_residual_px: centre residuals for both [px].
    """

    frame: int
    code: str
    likely_code: str
    residual_px: float
    likely_residual_px: float


@dataclass(frozen=True)
class OutlierReport:
    """Outliers of a run (see ``estimate_trajectories``)."""

    downweighted: tuple[Outlier, ...]
    misdecoded: tuple[Misdecode, ...]
    baseline_rejected: tuple[tuple[int, PoseFailure], ...]
    unknown_codes: tuple[tuple[int, str], ...]
    rejected: tuple[Rejection, ...] = ()

    def to_dict(self) -> dict:
        return {
            "rejected": [r.to_dict() for r in self.rejected],
            "downweighted": [asdict(o) for o in self.downweighted],
            "misdecoded": [asdict(o) for o in self.misdecoded],
            "baseline_rejected": [
                {"frame": f, "reason": r.value} for f, r in self.baseline_rejected
            ],
            "unknown_codes": [{"frame": f, "code": c} for f, c in self.unknown_codes],
        }


@dataclass(frozen=True)
class EstimateResult:
    """Everything ``estimate_trajectories`` found.

    Attributes:
        methods: name -> MethodEstimate, in run order.
        frames: (N,) frame indices.
        signs_seen: (N,) observations per frame whose code is in the map.
        settings: the settings used.
        outliers: the outlier report (empty when the smoother did not run).
        timing_s: stage -> seconds.
        motion: the motion prior chosen from the flight, or None.
        fusion: the GNSS/IMU fusion (clock offset, GNSS outliers, counts), or
            None without telemetry.
        pixel_noise_scale: the factor (>= 1) every keypoint sigma was scaled
            by (``estimator.noise_scale``: PnP's residuals', then, with the
            smoother, its own residuals' on top; 1.0: none).
        pose_noise_scale: the factor (>= 1) the PnP and smoothed pose sigmas
            were scaled by after that, from PnP's scatter about the smoothed
            trajectory (``noise_scale.pose_noise_scale``; map taken as exact
            only; 1.0: none).
        warnings: what the user must be told about the whole flight (one
            line each), e.g. a noise scale too large to be noise.
    """

    methods: dict[str, MethodEstimate]
    frames: np.ndarray
    signs_seen: np.ndarray
    settings: EstimatorSettings
    outliers: OutlierReport
    timing_s: dict[str, float]
    motion: MotionChoice | None = None
    fusion: FusionResult | None = None
    pixel_noise_scale: float = 1.0
    pose_noise_scale: float = 1.0
    warnings: tuple[str, ...] = ()
    intrinsics: IntrinsicsCheck | None = None


# A pixel noise scale above this is not noise the decoder misjudged but a model
# that does not fit the video (``distrusted``). Measured: correct camera files
# 1.0-1.45 (the demo; scripts/eval_flight.py's 5 flights through a lens 1.0);
# the same flights with the lens's distortion left out of camera.yaml 4.4-16,
# where the scaled sigmas still left 100 % of the `ok` poses beyond 3 sigma
# at 2-9 m RMSE (``eval_flight.py --drop-lens-model``).
MAX_PIXEL_NOISE_SCALE = 3.0
# Above this (and up to the one above) the sigmas are scaled and no pose is
# ``ok``: correct set-ups gave at most 1.19 (the demo 1.15, eval_pose_sigma's
# 24 runs 1.0-1.19, eval_flight's 8 flights and eval_setup_faults' references
# 1.0), while a map claiming sigma_m 1 mm for a 1 cm survey gave 2.48 with 75
# of 119 smoothed ``ok`` poses beyond 3 sigma (scripts/eval_setup_faults.py
# ``survey_sigma_1mm``): an error every frame shares, which scaled pixel
# sigmas average away, is the likely cause at that size.
WEAK_PIXEL_NOISE_SCALE = 2.0


# A per-frame pose spends six of its residuals' degrees of freedom on itself.
POSE_DOF = 6
# The baseline writes no sigmas (empty fields): the paper's homography method
# has no noise model to propagate. Its errors come from the method (signs off
# one plane, the decomposition's fix-ups), not the keypoint noise: the inverse
# Fisher information of its keypoints claimed 8-370x less than its errors on
# rendered orbits (scripts/eval_pose_sigma.py), and a sigma a user cannot bet
# on is worse than none. Its status still tests its residuals.
BASELINE_SIGMAS = False


def _position_sigmas(cov6: np.ndarray | None, world_T_cam: np.ndarray) -> np.ndarray:
    """(3,) world-axis position sigmas [m] of a pose covariance (NaN without one)."""
    if cov6 is None:
        return np.full(3, np.nan)
    c = position_cov_world(cov6, world_T_cam[:3, :3])
    return np.sqrt(np.maximum(np.diag(c), 0.0))


def _from_frame_poses(
    name: str, stamps: np.ndarray, poses: list[FramePose], st: StatusSettings
) -> MethodEstimate:
    """A per-frame method's trajectory; statuses test ``chi2_map`` (the map as it is taken)."""
    n = len(poses)
    write_sigma = name != "baseline" or BASELINE_SIGMAS
    T = np.tile(np.eye(4), (n, 1, 1))
    valid = np.zeros(n, bool)
    sigma = np.full((n, 3), np.nan)
    status: list[PoseState] = []
    for i, p in enumerate(poses):
        if p.world_T_cam is not None and np.all(np.isfinite(p.world_T_cam)):
            T[i] = p.world_T_cam
            valid[i] = True
            if write_sigma:
                sigma[i] = _position_sigmas(p.cov6, p.world_T_cam)
            # without a sigma to bet on, no pose is ok: weak unless its residuals fail
            worst = worst_axis_sigma(p.cov6 if write_sigma else None, p.world_T_cam[:3, :3])
            dof = max(2 * p.keypoints_used - POSE_DOF, 0)
            status.append(classify(p.keypoints_used, worst, p.chi2_map, dof, st))
        else:
            status.append(p.reason or PoseFailure.NONFINITE)
    return MethodEstimate(
        name=name,
        stamps_s=stamps,
        world_T_cam=T,
        valid=valid,
        sigma_xyz=sigma,
        signs_used=np.array([p.signs_used for p in poses], dtype=np.int64),
        status=tuple(status),
    )


def _smoothed_status(
    kept: Measurements, r: SmootherResult, camera: CameraModel, st: StatusSettings
) -> tuple[PoseStatus, ...]:
    """Each smoothed pose's status from the measurements the final solve kept.

    Ill-conditioned means a worst-axis marginal sigma above the setting (the
    frame's own keypoints' when the marginals were not computed).
    """

    def own(ids: np.ndarray, T: np.ndarray, world: np.ndarray) -> float:
        # No marginals: how well the frame's own keypoints fix it.
        lm = kept.landmark[ids]
        sign_id = np.unique(np.asarray(kept.landmark_code)[lm], return_inverse=True)[1]
        cov = pose_covariance(
            camera, T, world, kept.pixel_noise()[ids], kept.landmark_sigma_m[lm], sign_id
        )
        return worst_axis_sigma(cov, T[:3, :3])

    return pose_statuses(kept, r.world_T_cam, r.landmarks_world, r.sigma_xyz, camera, st, own)


def _from_smoother(
    name: str,
    stamps: np.ndarray,
    r: SmootherResult,
    causal: bool = False,
    status: tuple[PoseStatus, ...] | None = None,
) -> MethodEstimate:
    T = r.causal_world_T_cam if causal else r.world_T_cam
    valid = np.all(np.isfinite(T.reshape(len(T), -1)), axis=1)
    T = np.where(valid[:, None, None], T, np.eye(4))
    if status is None:
        status = tuple(PoseStatus.OK if o else PoseStatus.BRIDGED for o in r.observed)
    sigma = r.sigma_xyz
    if causal:
        sigma = np.full_like(sigma, np.nan) if r.causal_sigma_xyz is None else r.causal_sigma_xyz
    return MethodEstimate(
        name=name,
        stamps_s=stamps,
        world_T_cam=T,
        valid=valid,
        sigma_xyz=sigma,
        survey_sigma_xyz=None if causal else getattr(r, "survey_sigma_xyz", None),  # fused: none
        signs_used=r.signs_used.copy(),
        status=status,
    )


def check_inputs(
    frames: Sequence[FrameObservations], sign_map: SignMap, camera: CameraModel, obs_source: str
) -> None:
    """InputError when the camera's image size or the map's codes do not fit the observations."""
    if not frames:
        raise InputError(f"{obs_source}: no frames")
    sizes = {tuple(f.image_size) for f in frames}
    for w, h in sizes:
        if (w, h) != (camera.width, camera.height):
            raise InputError(
                f"{obs_source}: images are {w}x{h} but the camera file says "
                f"{camera.width}x{camera.height}; pass the calibration of this camera"
            )
    seen = {s.code for f in frames for s in f.signs}
    if not seen:
        raise InputError(
            f"{obs_source}: no sign was decoded in any of its {len(frames)} frames; "
            "nothing to estimate from (check the input, --codes and the detector)"
        )
    if not seen & set(sign_map.codes):
        src = sign_map.source or "map"
        raise InputError(
            f"{src}: the map shares no code with the observations in {obs_source} "
            f"(observed {', '.join(sorted(seen))}); pass the map of this site"
        )
    shared = sorted(seen & set(sign_map.codes))
    if seen and len(shared) < MIN_SHARED_SIGNS:
        src = sign_map.source or "map"
        raise InputError(
            f"{src}: the observations in {obs_source} share only sign {', '.join(shared)} "
            f"with the map (at least {MIN_SHARED_SIGNS} are needed); pass the map of this site"
        )


# A flight must share this many signs with the map: fewer cannot fix a pose.
MIN_SHARED_SIGNS = 3
# An oriented sign is wrong in the map when the camera is behind it in more than
# this share of the frames that see it, or when the median residual of its
# off-centre keypoints exceeds this share of its apparent diameter while its
# centre fits (a sign turned 180 degrees moves them by most of a diameter; in
# diameters, not sigmas, so that a decoder's optimistic sigma_px cannot trip it).
ORIENTATION_MAX_BEHIND = 0.5
ORIENTATION_MAX_DIAMETERS = 0.25
ORIENTATION_MIN_FRAMES = 5
ORIENTATION_MAX_FRAMES = 200  # evenly spaced observations of a sign suffice for a median


def _median(values: list[float]) -> float:
    return float(np.median(values)) if values else 0.0


def _sign_fit(
    sign: MapSign,
    uses: list[tuple[int, SignObservation]],
    world_T_cam: np.ndarray,
    camera: CameraModel,
) -> tuple[float, float, float]:
    """(share of frames seen from behind, median centre and off-centre residual [diameters])."""
    kps = sign.keypoints_world()
    behind, centre_d, other_d = [], [], []
    for i, obs in uses:
        T = world_T_cam[i]
        behind.append(float(sign.normal @ (T[:3, 3] - sign.center_m)) <= 0.0)
        names = [n for n in obs.keypoints_px if n in kps]
        raw = np.array([obs.keypoints_px[n] for n in names], dtype=float).reshape(-1, 2)
        uv, _, _ = pixels_and_pose_jacobian(camera, T, np.array([kps[n] for n in names]))
        depth = max(float(cam_points(T, sign.center_m[None])[0, 2]), MIN_DEPTH_M)
        diameter_px = sign.diameter_m * camera.fx / depth
        und, _, valid = undistort_px_jacobian(camera, raw)
        d = np.linalg.norm(und - uv, axis=1) / diameter_px
        valid = np.ones(len(d), bool) if valid is None else valid
        for n, dk, ok in zip(names, d, valid, strict=True):
            if ok:  # a keypoint the lens model cannot undistort tells nothing
                (centre_d if n == "center" else other_d).append(float(dk))
    return float(np.mean(behind)), _median(centre_d), _median(other_d)


def check_orientations(
    frames: Sequence[FrameObservations],
    sign_map: SignMap,
    camera: CameraModel,
    m: MethodEstimate,
    bent: bool = False,
) -> None:
    """InputError naming an oriented sign that the flight sees from behind or turned.

    Args:
        frames: the observations; sign_map: the map; camera: the camera.
        m: a method's trajectory (the smoothed one) to look from.
        bent: the keypoints miss by more than noise (``distrusted``): a sign
            whose centre misses by over half ``ORIENTATION_MAX_DIAMETERS`` is
            then not called turned (the camera file's lens may be the cause).
    """
    uses: dict[str, list] = {}
    for i, f in enumerate(frames):
        if m.valid[i] and m.status[i] is PoseStatus.OK:
            for obs in f.signs:
                uses.setdefault(obs.code, []).append((i, obs))
    src = sign_map.source or "map"
    for sign in sign_map.signs:
        seen = uses.get(sign.code, [])
        if not sign.oriented or len(seen) < ORIENTATION_MIN_FRAMES:
            continue
        step = max(1, len(seen) // ORIENTATION_MAX_FRAMES)
        behind, centre_d, other_d = _sign_fit(sign, seen[::step], m.world_T_cam, camera)
        if behind > ORIENTATION_MAX_BEHIND:
            raise InputError(
                f"{src}: sign {sign.code} is seen from behind in {100 * behind:.0f} % of the "
                "frames that see it; check its 'normal' (it points into the face?)"
            )
        if other_d > ORIENTATION_MAX_DIAMETERS > centre_d:
            # Centres that miss too (by over half the limit) may be the lens's doing.
            lens = centre_d > ORIENTATION_MAX_DIAMETERS / 2
            if lens and bent:
                continue
            raise InputError(
                f"{src}: the keypoints of sign {sign.code} do not fit its orientation "
                f"(median miss {other_d:.2f} sign diameters, its centre {centre_d:.2f}); "
                "check its 'up' and 'normal'"
                + (", and the camera file's lens distortion" if lens else "")
            )


def _outliers(
    meas: Measurements,
    r: SmootherResult,
    frames: Sequence[FrameObservations],
    sign_map: SignMap,
    camera: CameraModel,
    settings: EstimatorSettings,
    gated: np.ndarray | None = None,
) -> tuple[tuple[Outlier, ...], tuple[Misdecode, ...]]:
    k = settings.smoother.huber_k
    res = residuals_px(meas, r, camera)
    whitened = np.sqrt(whitened_chi2(meas, r, camera))
    gated = np.zeros(len(res), bool) if gated is None else gated
    down = np.nonzero((whitened > k) | gated)[0]
    outliers = tuple(
        Outlier(
            int(frames[meas.frame[m]].frame),
            meas.landmark_code[meas.landmark[m]],
            meas.landmark_name[meas.landmark[m]],
            float(res[m]),
            0.0 if gated[m] else float(k / whitened[m]),
        )
        for m in down
    )
    # Mis-decoding: the observation's centre against every map sign's centre.
    centres = {sign.code: sign.center_m for sign in sign_map.signs}
    codes = list(centres)
    C = np.array([centres[c] for c in codes])
    suspects = sorted(
        (i, si)
        for i, si in {(int(meas.frame[m]), int(meas.sign_index[m])) for m in down}
        if frames[i].signs[si].code in centres
    )
    # Every suspect's centre undistorted in one call, its raw-pixel sigma with it.
    raw = np.array([frames[i].signs[si].center_px for i, si in suspects], dtype=float)
    centre_uv, jac, valid = undistort_px_jacobian(camera, raw.reshape(-1, 2))
    sig = np.array([frames[i].signs[si].sigma_px for i, si in suspects], dtype=float)
    if jac is not None:  # the geometric mean of the axes' sigmas, as sigma_px is
        sig_uv = undistorted_sigmas(jac, np.repeat(sig.reshape(-1, 1), 2, axis=1))
        sig = np.sqrt(sig_uv[:, 0] * sig_uv[:, 1])
    valid = np.ones(len(suspects), bool) if valid is None else valid
    mis = []
    for (i, si), uv, sigma, ok in zip(suspects, centre_uv, sig, valid, strict=True):
        if not ok:  # a centre the lens model cannot undistort tells nothing
            continue
        obs = frames[i].signs[si]
        T = np.repeat(r.world_T_cam[i][None], len(codes), axis=0)
        d = np.linalg.norm(project(camera, T, C) - uv, axis=1)
        own = d[codes.index(obs.code)]
        d_other = d.copy()
        d_other[codes.index(obs.code)] = np.inf
        best = int(np.argmin(d_other))
        if d_other[best] * settings.misdecode_ratio < own and d_other[best] < 3 * k * sigma:
            mis.append(
                Misdecode(int(frames[i].frame), obs.code, codes[best], float(own), float(d[best]))
            )
    return outliers, tuple(mis)


def gate_measurements(
    meas: Measurements,
    world_T_cam: Sequence[np.ndarray | None],
    camera: CameraModel,
    gate_px: float,
) -> tuple[Measurements, np.ndarray]:
    """Drop keypoints far from where their frame's per-frame pose projects them.

    Args:
        meas: all measurements.
        world_T_cam: per frame, a (4, 4) pose (e.g. RANSAC PnP) or None (kept).
        camera: the camera.
        gate_px: the gate [px]; 0 keeps everything.

    Returns:
        (the kept measurements, (M,) True for each gated measurement of ``meas``).
    """
    gated = np.zeros(len(meas.frame), bool)
    if gate_px <= 0 or len(meas.frame) == 0:
        return meas, gated
    have = np.array([T is not None for T in world_T_cam], bool)
    poses = np.array([T if T is not None else np.eye(4) for T in world_T_cam])
    sel = have[meas.frame]
    pred = project(camera, poses[meas.frame[sel]], meas.landmark_world[meas.landmark[sel]])
    gated[np.nonzero(sel)[0]] = np.linalg.norm(pred - meas.px[sel], axis=1) > gate_px
    kept = meas.subset(~gated)
    return kept, gated


@dataclass(frozen=True)
class _SmoothedRun:
    """The smoother's share of an EstimateResult."""

    methods: dict[str, MethodEstimate]
    downweighted: tuple[Outlier, ...]
    misdecoded: tuple[Misdecode, ...]
    rejected: tuple[Rejection, ...]
    motion: MotionChoice | None
    timing_s: dict[str, float]
    fusion: FusionResult | None = None  # with telemetry: "fused" is in methods
    pose_scale: float = 1.0  # see EstimateResult.pose_noise_scale
    pixel_scale: float = 1.0  # the smoother's residual noise scale, on top of PnP's
    intrinsics: IntrinsicsCheck | None = None  # the video's intrinsics against the file's


def _rejections(
    meas: Measurements,
    frames: Sequence[FrameObservations],
    ids: np.ndarray,
    test: RejectionTest,
    statistic: np.ndarray,
    threshold: float,
) -> list[Rejection]:
    """One Rejection per sign observation among measurements ``ids`` (statistic per id)."""
    out = []
    hit = np.zeros(len(meas.frame), bool)
    hit[ids] = True
    value = np.zeros(len(meas.frame))
    value[ids] = statistic
    for group in sign_groups(meas):
        g = group[hit[group]]
        if len(g):
            i = int(meas.frame[g[0]])
            out.append(
                Rejection(
                    frame=int(frames[i].frame),
                    code=meas.landmark_code[meas.landmark[g[0]]],
                    keypoints=len(g),
                    test=test,
                    statistic=float(value[g].max()),
                    threshold=float(threshold),
                )
            )
    return out


@dataclass(frozen=True)
class _Problem:
    """One flight's smoothing problem, shared by the rounds of the robust solve."""

    frames: Sequence[FrameObservations]
    meas: Measurements
    stamps: np.ndarray
    camera: CameraModel
    default: np.ndarray
    s: EstimatorSettings


def _innovation_rounds(
    p: _Problem, r: SmootherResult, active: np.ndarray
) -> tuple[SmootherResult, list[Rejection]]:
    """Drop each frame's worst observation failing the innovation test and solve again."""
    smoother = replace(p.s.smoother, kernel=HUBER)
    rejected: list[Rejection] = []
    for _ in range(p.s.outliers.rounds):
        pred, pred_cov = predict_from_neighbours(r.world_T_cam, r.cov6, p.stamps, smoother)
        failing = worst_innovations(p.meas, active, pred, pred_cov, p.camera, p.s.outliers.alpha)
        if not failing:
            break
        for ids, chi2, threshold in failing:
            active[ids] = False
            rejected += _rejections(
                p.meas, p.frames, ids, RejectionTest.INNOVATION, np.full(len(ids), chi2), threshold
            )
        init = list(r.world_T_cam)
        r = smooth_batch(p.meas.subset(active), p.stamps, init, p.camera, smoother, p.default)
    return r, rejected


def _final_solve(
    p: _Problem, r: SmootherResult, active: np.ndarray
) -> tuple[SmootherResult, list[Rejection]]:
    """The final solve with the kernel that removes outliers outright (GNC or Tukey).

    Clears ``active`` for the measurements it removes.
    """
    kernel = p.s.final_kernel
    if kernel == HUBER:
        return r, []
    smoother = replace(p.s.smoother, kernel=kernel)
    kept = p.meas.subset(active)
    init, landmarks = list(r.world_T_cam), r.landmarks_world  # Tukey needs both (see smooth_batch)
    r = smooth_batch(kept, p.stamps, init, p.camera, smoother, p.default, landmarks)
    ids = np.nonzero(active)[0]
    chi2 = whitened_chi2(kept, r, p.camera)
    if kernel == GNC:
        out, test, threshold = r.weights < 0.5, RejectionTest.GNC, smoother.gnc_chi2
    else:
        out, test, threshold = chi2 > smoother.tukey_k**2, RejectionTest.TUKEY, smoother.tukey_k**2
    active[ids[out]] = False
    return r, _rejections(p.meas, p.frames, ids[out], test, chi2[out], threshold)


def _smoothed(
    frames: Sequence[FrameObservations],
    sign_map: SignMap,
    camera: CameraModel,
    s: EstimatorSettings,
    per_frame: dict[str, list[FramePose]],
    progress: bool,
    telemetry: Telemetry | None = None,
    fusion: FusionSettings | None = None,
) -> _SmoothedRun:
    """The smoother over the flight, started from per-frame PnP (baseline where PnP has none).

    Huber solve; rounds of the innovation test (see ``estimator.robust``);
    the final solve with ``final_kernel``.
    """
    if s.final_kernel not in (HUBER, TUKEY, GNC):
        raise ValueError(f"unknown final kernel {s.final_kernel!r}")
    stamps = np.array([f.stamp_ns for f in frames], dtype=np.float64) * 1e-9
    meas = collect_measurements(frames, sign_map, camera)
    causal_init = [p.world_T_cam for p in per_frame["pnp"]]
    init = causal_init
    if "baseline" in per_frame:
        init = [
            a if a is not None else b.world_T_cam
            for a, b in zip(causal_init, per_frame["baseline"], strict=True)
        ]
    p = _Problem(frames, meas, stamps, camera, default_pose(sign_map), s)
    t0 = time.perf_counter()
    kept, gated = gate_measurements(meas, causal_init, camera, s.gate_px)
    ids = np.nonzero(gated)[0]
    rejected = _rejections(meas, frames, ids, RejectionTest.PNP_GATE, 0 * ids, s.gate_px)
    huber = replace(s.smoother, kernel=HUBER)
    if s.solver == "batch":
        r = smooth_batch(kept, stamps, init, camera, huber, p.default)
    else:
        r = smooth_isam2(kept, stamps, causal_init, camera, huber, p.default, progress)
    causal = r
    p, kept, r, pixel_scale = _residual_scaled(p, kept, r)
    meas = p.meas
    active = ~gated
    r, by_innovation = _innovation_rounds(p, r, active)
    motion = None
    if s.tune_motion:
        kept = meas.subset(active)
        motion = tune_motion_prior(
            kept, stamps, r.world_T_cam, camera, s.smoother, p.default, s.tuning
        )
        p = replace(p, s=replace(s, smoother=motion.settings))
        if s.final_kernel == HUBER:  # no final solve to carry the chosen prior
            r = smooth_batch(kept, stamps, list(r.world_T_cam), camera, motion.settings, p.default)
    r, by_kernel = _final_solve(p, r, active)
    r, pose_scale = _pose_scaled(r, [scaled_pose(q, pixel_scale) for q in per_frame["pnp"]], s)
    stated = (s.focal_sigma_rel, s.principal_sigma_px)
    intrinsics = check_intrinsics(meas.subset(active), r.world_T_cam, camera, pose_scale, stated)
    timing = {"smoothed": time.perf_counter() - t0, "sigmas": r.sigma_seconds}
    status = _smoothed_status(meas.subset(active), r, camera, s.status)
    methods = {"smoothed": _from_smoother("smoothed", stamps, r, status=status)}
    if causal.causal_world_T_cam is not None:
        scale = pixel_scale * pose_scale
        methods["causal"] = _causal_method(stamps, causal, r, meas.subset(active), camera, s, scale)
    down, mis = _outliers(meas, r, frames, sign_map, camera, s, gated)
    fused = None
    if telemetry is not None:  # the smoothed graph with the drone's sensors, from its solution
        on_run = on_smoother(fusion, p.s.smoother)  # the run's landmarks, tuned motion prior
        fused = fuse_trajectory(frames, sign_map, camera, stamps, telemetry, on_run, r)
        if not fused.refused:  # refused: clock offset not determined (fused.notes says why)
            methods["fused"] = _from_smoother("fused", stamps, fused, status=fused.status)
        timing["fused"] = fused.seconds
    return _SmoothedRun(
        methods=methods,
        downweighted=down,
        misdecoded=mis,
        rejected=tuple(rejected + by_innovation + by_kernel),
        motion=motion,
        timing_s=timing,
        fusion=fused,
        pose_scale=pose_scale,
        pixel_scale=pixel_scale,
        intrinsics=intrinsics,
    )


def _causal_method(
    stamps: np.ndarray,
    causal: SmootherResult,
    final: SmootherResult,
    kept: Measurements,
    camera: CameraModel,
    s: EstimatorSettings,
    scale: float,
) -> MethodEstimate:
    """iSAM2's filter estimate of each frame as the method "causal".

    Its sigmas are the filter's marginals times ``scale`` (the residual and
    pose noise scales the smoothed sigmas got); its statuses the smoothed poses' tests on the
    measurements the final solve kept, at the filter's poses and the final
    landmarks: a frame the filter let an outlier pull (it runs before the
    innovation test and the final kernel) is ``suspect``, not ``ok``.
    """
    sigma = None if causal.causal_sigma_xyz is None else causal.causal_sigma_xyz * scale
    as_filter = replace(
        causal,
        world_T_cam=causal.causal_world_T_cam,
        sigma_xyz=np.full_like(causal.sigma_xyz, np.nan) if sigma is None else sigma,
        landmarks_world=final.landmarks_world,
    )
    status = _smoothed_status(kept, as_filter, camera, s.status)
    return _from_smoother("causal", stamps, replace(causal, causal_sigma_xyz=sigma), True, status)


def _scaled_measurements(meas: Measurements, scale: float) -> Measurements:
    cov = None if meas.cov_uv_px is None else meas.cov_uv_px * scale**2
    return replace(
        meas,
        sigma_px=meas.sigma_px * scale,
        sigma_uv_px=meas.axis_sigmas() * scale,
        cov_uv_px=cov,
    )


def _residual_scaled(
    p: _Problem, kept: Measurements, r: SmootherResult
) -> tuple[_Problem, Measurements, SmootherResult, float]:
    """After the first solve: every sigma scaled by the smoother's own residual noise scale.

    ``noise_scale.residual_noise_scale`` on the first (Huber) solve's
    residuals; the problem's and the kept measurements' sigmas, and the
    solve's covariances (for the innovation test), scaled by it.
    """
    if not p.s.scale_pixel_noise:
        return p, kept, r, 1.0
    scale = residual_noise_scale(whitened_chi2(kept, r, p.camera), kept.frame, kept.n_frames)
    if scale == 1.0:
        return p, kept, r, scale
    cov6 = None if r.cov6 is None else r.cov6 * scale**2
    r = replace(r, cov6=cov6, sigma_xyz=r.sigma_xyz * scale)
    meas = _scaled_measurements(p.meas, scale)
    return replace(p, meas=meas), _scaled_measurements(kept, scale), r, scale


def _pose_scaled(
    r: SmootherResult, pnp: list[FramePose], s: EstimatorSettings
) -> tuple[SmootherResult, float]:
    """``r`` with its covariances scaled by the pose noise scale squared, and the scale.

    Only with the map taken as exact (``noise_scale.pose_noise_scale``).
    """
    if not s.scale_pixel_noise or s.smoother.landmarks != FIXED:
        return r, 1.0
    scale = pose_noise_scale(pnp, r.world_T_cam, r.cov6)
    if scale == 1.0:
        return r, scale
    cov6 = None if r.cov6 is None else r.cov6 * scale**2
    return replace(r, cov6=cov6, sigma_xyz=r.sigma_xyz * scale), scale


def per_frame_methods(s: EstimatorSettings) -> tuple[str, ...]:
    """The per-frame methods the settings need (PnP also initialises the smoother)."""
    wanted = set(s.methods)
    return tuple(
        name
        for name in PER_FRAME_METHODS
        if name in wanted or (name == "pnp" and "smoothed" in wanted)
    )


def _per_frame_methods(
    frames: Sequence[FrameObservations],
    sign_map: SignMap,
    camera: CameraModel,
    s: EstimatorSettings,
    progress: bool,
    solved_pnp: Sequence[SolvedPnP],
    timing: dict[str, float],
    done: PerFrameRun | None = None,
) -> dict[str, list[FramePose]]:
    """The baseline and PnP poses the settings need (PnP also initialises the smoother):
    ``done``'s when given (checked to be these frames'), else solved here."""
    if done is not None:
        return _per_frame_done(frames, sign_map, camera, s, done, timing)
    per_frame: dict[str, list[FramePose]] = {}
    for name in per_frame_methods(s):
        t0 = time.perf_counter()
        solved = solved_pnp if name == "pnp" else ()
        per_frame[name] = run_per_frame(
            frames, sign_map, camera, name, s.per_frame, progress, solved
        )
        timing[name] = time.perf_counter() - t0
    return per_frame


def _per_frame_done(
    frames: Sequence[FrameObservations],
    sign_map: SignMap,
    camera: CameraModel,
    s: EstimatorSettings,
    done: PerFrameRun,
    timing: dict[str, float],
) -> dict[str, list[FramePose]]:
    """The per-frame poses a PerFrameRun made on exactly these frames with these settings.

    Raises:
        ValueError: it was fed other frames, another map, camera or settings, or
            runs other methods (its poses would not be this flight's).
    """
    if done.methods != per_frame_methods(s) or not done.fed(frames, sign_map, camera, s.per_frame):
        raise ValueError(
            "the per-frame poses given were made on other frames, inputs or methods "
            f"({len(done.frames)} frames, methods {done.methods}) than this estimate's "
            f"({len(frames)} frames, methods {per_frame_methods(s)})"
        )
    timing.update(done.seconds)
    return {name: list(done.poses[name]) for name in done.methods}


def distrusted(
    methods: dict[str, MethodEstimate], scale: float
) -> tuple[dict[str, MethodEstimate], tuple[str, ...]]:
    """``methods`` with no pose ``ok`` or ``weak`` when ``scale`` is too large
    to be noise (``MAX_PIXEL_NOISE_SCALE``), and the warning; with no pose
    ``ok`` (they become ``weak``) when it is above ``WEAK_PIXEL_NOISE_SCALE``,
    and a warning; else as given.

    Keypoints that miss their predictions by several times their sigmas in
    the median frame say the camera model or the map does not fit the video
    (a lens distortion left out of the calibration bends every ray the same
    way from frame to frame): scaled sigmas cannot describe such an error,
    so every pose is marked ``suspect`` (bridged poses stay bridged) rather
    than reported as one to bet on.
    """
    if scale > WEAK_PIXEL_NOISE_SCALE and not scale > MAX_PIXEL_NOISE_SCALE:
        return _relabelled(methods, (PoseStatus.OK,), PoseStatus.WEAK), (
            f"the keypoints miss their predicted places by {scale:.1f}x their sigmas "
            f"(pixel_noise_scale; correct set-ups stay below {WEAK_PIXEL_NOISE_SCALE:g}): the "
            "sigmas were scaled by it, but an error that every frame shares (the map's sigma_m "
            "smaller than the survey's real error, a slightly wrong camera file) is not covered "
            "by that; no pose is marked ok",
        )
    if not scale > MAX_PIXEL_NOISE_SCALE:
        return methods, ()
    trusted = (PoseStatus.OK, PoseStatus.WEAK)
    return _relabelled(methods, trusted, PoseStatus.SUSPECT), (
        f"the keypoints miss their predicted places by {scale:.1f}x their sigmas "
        f"(pixel_noise_scale, at most {MAX_PIXEL_NOISE_SCALE:g} is noise): the camera file "
        "(focal length, lens distortion, image size) or the map (sign positions, 'up' and "
        "'normal') does not fit this video; every pose is marked suspect",
    )


def _relabelled(
    methods: dict[str, MethodEstimate], states: tuple[PoseStatus, ...], to: PoseStatus
) -> dict[str, MethodEstimate]:
    """``methods`` with every pose status in ``states`` replaced by ``to``."""
    return {
        name: replace(m, status=tuple(to if st in states else st for st in m.status))
        for name, m in methods.items()
    }


def _checked(
    frames: Sequence[FrameObservations],
    sign_map: SignMap,
    camera: CameraModel,
    methods: dict[str, MethodEstimate],
    scale: float,
    s: EstimatorSettings,
    run: _SmoothedRun | None = None,
) -> tuple[dict[str, MethodEstimate], tuple[str, ...]]:
    """The signs' orientations checked (``check_orientations``), then ``distrusted``,
    then the focal length's and the principal point's stated shares added to the
    sigmas (``intrinsics_share``), then the video's own check of them acted on
    (``_intrinsics_checked``, with the smoother's ``run``).

    With keypoints that miss by more than noise (``scale`` above
    ``MAX_PIXEL_NOISE_SCALE``) a sign whose centre misses too is not blamed
    on the map's ``up`` and ``normal``: a lens left out of the camera file
    bends the outer keypoints more than the centre; ``distrusted``'s warning
    names both the camera file and the map. A sign turned in the map (its
    centre fits, the rest does not) is still refused by name.
    """
    if "smoothed" in methods:
        bent = scale > MAX_PIXEL_NOISE_SCALE
        check_orientations(frames, sign_map, camera, methods["smoothed"], bent)
    methods, warnings = distrusted(methods, scale)
    weak = s.status.weak_sigma_m
    methods = {
        k: with_intrinsics_shares(
            m, frames, sign_map, camera, s.focal_sigma_rel, s.principal_sigma_px, weak
        )
        for k, m in methods.items()
    }
    return _intrinsics_checked(methods, warnings, run, (frames, sign_map, camera, scale), s)


def _intrinsics_checked(
    methods: dict[str, MethodEstimate],
    warnings: tuple[str, ...],
    run: _SmoothedRun | None,
    fit: tuple[Sequence[FrameObservations], SignMap, CameraModel, float],
    s: EstimatorSettings,
) -> tuple[dict[str, MethodEstimate], tuple[str, ...]]:
    """``methods`` and the warnings after the video's check of the camera file's
    intrinsics (``estimator.intrinsics_check``); ``fit``: the flight's frames, map,
    camera and pixel noise scale.

    With keypoints that miss by more than noise (the scale above
    ``WEAK_PIXEL_NOISE_SCALE``) the check is not acted on: the camera file and
    the map do not fit for another reason (``distrusted`` said so), and the
    check would blame the intrinsics for it.

    A focal length a few per cent off moves every pose by as much of its
    range, which no sigma here covers: no pose stays ``ok`` or ``weak``. A
    principal point off mostly turns the poses; what it moves, its share
    with the change the video sees (``intrinsics_share``) covers: the sigmas
    take it, as ``--principal-sigma`` would add it (a check that fires on a
    bias of the keypoints then costs precision, not the poses).
    """
    check = None if run is None else run.intrinsics
    frames, sign_map, camera, scale = fit
    if check is None or not check.disagrees or scale > WEAK_PIXEL_NOISE_SCALE:
        return methods, warnings
    if check.focal_off:
        methods = _relabelled(methods, (PoseStatus.OK, PoseStatus.WEAK), PoseStatus.SUSPECT)
    else:
        px = check.principal_change_px
        methods = {
            k: with_principal_share(m, frames, sign_map, camera, px, s.status.weak_sigma_m)
            for k, m in methods.items()
        }
    return methods, (*warnings, disagreement(check, camera))


def _noise_scaled(
    frames: Sequence[FrameObservations],
    per_frame: dict[str, list[FramePose]],
    s: EstimatorSettings,
) -> tuple[dict[str, list[FramePose]], float, Sequence[FrameObservations]]:
    """The per-frame poses and the frames with the flight's pixel noise scale
    (``estimator.noise_scale``) applied, and the scale.

    With the map taken as exact (landmarks ``fixed``) the poses' covariances
    and chi-squares lose their survey share first.
    """
    if s.smoother.landmarks == FIXED:
        per_frame = {k: [exact_map_pose(p) for p in v] for k, v in per_frame.items()}
    if not s.scale_pixel_noise or "pnp" not in per_frame:
        return per_frame, 1.0, frames
    scale = pixel_noise_scale(per_frame["pnp"])
    poses = {k: [scaled_pose(p, scale) for p in v] for k, v in per_frame.items()}
    return poses, scale, scaled_frames(frames, scale)


def estimate_trajectories(
    frames: Sequence[FrameObservations],
    sign_map: SignMap,
    camera: CameraModel,
    settings: EstimatorSettings | None = None,
    progress: bool = True,
    telemetry: Telemetry | None = None,
    fusion: FusionSettings | None = None,
    solved_pnp: Sequence[SolvedPnP] = (),
    per_frame_done: PerFrameRun | None = None,
) -> EstimateResult:
    """Every requested method's trajectory for one flight.

    Args:
        frames: the flight's observations in time order (raw pixels).
        sign_map: the surveyed signs.
        camera: the camera (its image size must match the observations).
        settings: methods, solver and their settings; progress: show tqdm bars over frames.
        telemetry, fusion: the drone's GNSS/IMU/gimbal (None: nothing changes), its fusion.
        solved_pnp: PnP calls the tracker made on these frames; the "pnp"
            method reuses those whose inputs are exactly its own (see
            ``perframe.run_per_frame``): the result is the same.
        per_frame_done: the per-frame methods run on exactly these frames as observed
            (``perframe.PerFrameRun``; else ValueError): taken, not solved again.

    Returns:
        The EstimateResult. Methods: "baseline", "pnp", "smoothed" as asked;
        with the iSAM2 solver also "causal" (each frame's estimate right after
        it was added); with telemetry also "fused" (``EstimateResult.fusion``).
    """
    s = settings or EstimatorSettings()
    if s.solver not in SOLVERS:
        raise ValueError(f"unknown solver {s.solver!r}; use one of {SOLVERS}")
    stamps = np.array([f.stamp_ns for f in frames], dtype=np.float64) * 1e-9
    timing: dict[str, float] = {}
    methods: dict[str, MethodEstimate] = {}
    map_codes = set(sign_map.codes)
    signs_seen = np.array([sum(o.code in map_codes for o in f.signs) for f in frames], np.int64)
    unknown = tuple((f.frame, o.code) for f in frames for o in f.signs if o.code not in map_codes)
    wanted = set(s.methods)
    per_frame = _per_frame_methods(
        frames, sign_map, camera, s, progress, solved_pnp, timing, per_frame_done
    )
    per_frame, scale, scaled = _noise_scaled(frames, per_frame, s)
    run = None  # the smoother, with the sigmas the PnP residuals support
    if "smoothed" in wanted:
        run = _smoothed(scaled, sign_map, camera, s, per_frame, progress, telemetry, fusion)
    pose_scale, more = (1.0, 1.0) if run is None else (run.pose_scale, run.pixel_scale)
    for name, poses in per_frame.items():
        if name in wanted:
            poses = [scaled_pose(p, more) for p in poses]
            poses = [inflated_pose(p, pose_scale) for p in poses] if name == "pnp" else poses
            methods[name] = _from_frame_poses(name, stamps, poses, s.status)
    if run is not None:
        methods.update(run.methods)
        timing.update(run.timing_s)
    methods, warnings = _checked(frames, sign_map, camera, methods, scale * more, s, run)
    base = per_frame.get("baseline", ())
    rejected = tuple((p.frame, p.reason) for p in base if p.world_T_cam is None)
    return EstimateResult(
        methods=methods,
        frames=np.array([f.frame for f in frames], dtype=np.int64),
        signs_seen=signs_seen,
        settings=s,
        outliers=OutlierReport(
            downweighted=() if run is None else run.downweighted,
            misdecoded=() if run is None else run.misdecoded,
            baseline_rejected=rejected,
            unknown_codes=unknown,
            rejected=() if run is None else run.rejected,
        ),
        timing_s=timing,
        motion=None if run is None else run.motion,
        fusion=None if run is None else run.fusion,
        pixel_noise_scale=scale * more,
        pose_noise_scale=pose_scale,
        warnings=warnings,
        intrinsics=None if run is None else run.intrinsics,
    )
