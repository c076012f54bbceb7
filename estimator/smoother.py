"""The gtsam smoother: every frame's pose from every sign observation of the flight.

Factor graph:
    * one ``Pose3`` per frame, ``world_T_cam`` (key ``x<i>``, i = position in
      the frame list), camera axes OpenCV's (x right, y down, z forward);
    * one ``Point3`` per map keypoint (key ``l<j>``), world frame [m]; the
      survey (``landmarks``): rigid signs (default: a ``Point3`` per sign
      centre, key ``s<k>``, with a ``PriorFactorPoint3`` of the map's
      ``sigma_m``, its keypoints tied to it at the map's offsets), every
      keypoint with its own prior, or the survey as exact;
    * a ``GenericProjectionFactorCal3_S2`` per observed keypoint on undistorted
      pixels, noise ``Robust(kernel, Diagonal(sigma_u, sigma_v))`` (the
      decoder's per-keypoint, per-axis sigmas, else the sign's) or, through a
      lens, ``Robust(kernel, Gaussian.Covariance(J diag(su^2, sv^2) J^T))``
      (the decoder's sigmas are in raw pixels; J, the undistortion's Jacobian
      at the keypoint, stretches and correlates them: ``Measurements.cov_uv_px``)
      with a Huber
      (default), Tukey or no kernel (GNC weighs plain Gaussian factors);
    * a motion prior between consecutive frames scaled by their time step dt:
      ``random-walk``: ``BetweenFactorPose3`` to the identity with sigmas
      ``q * sqrt(dt)``; ``constant-velocity``: a world-frame velocity
      ``Vector3`` per frame (key ``v<i>``) and gtsam's ``ImuFactor`` fed a zero
      specific force and zero rate over dt with gravity off, i.e. white-noise
      acceleration (sigma ``cv_sigma_acc``) and a rotation random walk
      (``cv_sigma_rot``), all in C++ (a Python CustomFactor would cost seconds
      per 10,000 frames);
    * a very weak prior on the first pose (and velocity), so that every
      iSAM2 step is well posed even before the first sign is seen.

Solvers: batch Gauss-Newton (its last Bayes net gives the marginals;
Levenberg-Marquardt takes over from a step that does not decrease the error;
``gtsam.GncLMOptimizer`` for GNC) and iSAM2
(whose estimate of the newest frame after each update is the causal,
filter-like result). Also: the Laplace-approximated evidence of a motion
prior (``log_evidence``), the graph's covariances at given poses (the
Cramér-Rao bound at the truth, ``covariances_at``) and the joint solve of
several flights for the sign centres (``solve_map``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace

import gtsam
import numpy as np
from signpose.estimator.camera import (
    CameraModel,
    undistort_px_jacobian,
    undistorted_cov,
)
from signpose.estimator.marginals import Conditional, selected_covariances_and_shares
from signpose.estimator.perframe import keypoint_sigmas
from signpose.estimator.projection import pixel_from_normalised, whitened
from signpose.frontend.observations import FrameObservations
from signpose.maps.loader import SignMap
from tqdm import tqdm

log = logging.getLogger(__name__)

RANDOM_WALK = "random-walk"
CONSTANT_VELOCITY = "constant-velocity"
MOTION_MODELS = (RANDOM_WALK, CONSTANT_VELOCITY)

# Kernels on the projection factors: Huber bounds an outlier's pull; Tukey
# (redescending) and graduated non-convexity with truncated least squares
# (gtsam.GncLMOptimizer) remove it. scripts/eval_estimator.py compares them.
# Landmark models: every keypoint its own point with the survey prior; a sign
# as one rigid body (its centre a point with the survey prior, its keypoints
# tied to it at the map's offsets); or the survey taken as exact.
KEYPOINTS = "keypoints"
RIGID = "rigid"
FIXED = "fixed"
LANDMARK_MODELS = (KEYPOINTS, RIGID, FIXED)

HUBER = "huber"
TUKEY = "tukey"
GNC = "gnc"
KERNELS = (HUBER, TUKEY, GNC)
# chi-square with 2 degrees of freedom at 1 - 1e-3: a keypoint whose whitened
# squared residual exceeds this is an outlier at the 0.1 % level.
CHI2_2DOF_999 = 13.816


def X(i: int) -> int:
    return gtsam.symbol("x", i)


def V(i: int) -> int:
    return gtsam.symbol("v", i)


def L(j: int) -> int:
    return gtsam.symbol("l", j)


def S(j: int) -> int:
    """A sign's centre (rigid landmark model)."""
    return gtsam.symbol("s", j)


BIAS_KEY = gtsam.symbol("b", 0)


@dataclass(frozen=True)
class SmootherSettings:
    """Settings of the factor graph and its solvers.

    Attributes:
        huber_k: Huber threshold on the whitened 2-D residual norm; 2.45 keeps
            95 % of Gaussian inliers at full weight (chi with 2 dof).
        landmarks: ``"rigid"`` (the default: one point per sign centre with
            the survey prior ``sigma_m``, its keypoints tied to it at the map's
            offsets by ``rigid_tie_sigma_m``: the sign moves as one body, its
            orientation and size the map's up to that tolerance; batch only,
            iSAM2's causal pass keeps keypoints), ``"keypoints"`` (each
            keypoint a point with its own survey prior ``sigma_m``) or
            ``"fixed"`` (the survey as exact: priors of ``fixed_sigma_m``).
            Rigid, because a surveyed centre's error moves the whole sign:
            keypoint landmarks treat it as independent per keypoint and claim
            too little (smoothed 2-sigma share 17-19 % on an axis of two of
            three paper-like flights with a survey error of N(0, sigma_m) per
            sign, rigid 97-100 %).
        rigid_tie_sigma_m: how far a keypoint may sit from its place in the
            sign's frame [m]: the tolerance of printing and hanging (3 mm is
            about 0.5 degrees of tilt at the slots' 0.3 m). Not exact: with the
            sign's size held to 1e-5 m, a 0.01-0.02 px size bias of the decoded
            keypoints moved upper and lower signs along their normals in
            opposite ways and tilted the demo's trajectory by 4 cm at 2.8 sigma
            (smoothed RMSE 0.041 m, aligned 0.005 m); at 3 mm it is 0.008 m
            (keypoint landmarks 0.007 m, PnP 0.022 m).
        fixed_sigma_m: prior sigma of the fixed map [m].
            Measured and dropped: a per-sign shift shared by all frames (the
            rigid landmarks with a 0.5 mm centre prior and 0.3 mm ties in place
            of exact keypoints, for the decoder's persistent error): ``ok``
            poses beyond 3 sigma 15 -> 12 of 349 / 358 on two rendered orbits
            (clean and hard, seed 5), but RMSE x 7.5 -> 10.9 mm; the tails are
            bursts of keypoint errors shared by 10-20 frames (PnP is 40 mm off
            there too), not a bias constant over the flight.
        kernel: ``"huber"``, ``"tukey"`` (redescending: zero weight beyond
            ``tukey_k``) or ``"gnc"`` (graduated non-convexity, truncated least
            squares at ``gnc_chi2``, batch only).
        tukey_k: Tukey threshold on the whitened residual norm (4.685: 95 %
            efficiency on Gaussian data).
        gnc_chi2: a keypoint whose whitened squared residual exceeds this is an
            outlier for GNC (default: chi-square, 2 dof, 0.1 %).
        motion: ``"random-walk"`` or ``"constant-velocity"`` (the default: it
            had the lower error on simulated flights, see scripts/eval_estimator.py).
        rw_sigma_rot: random-walk rotation density [rad/sqrt(s)].
        rw_sigma_pos: random-walk position density [m/sqrt(s)].
        cv_sigma_acc: constant-velocity acceleration noise density [m/s^2/sqrt(Hz)].
        cv_sigma_rot: constant-velocity rotation random walk [rad/s/sqrt(Hz)].
        first_sigma_m: the weak prior on the first position [m].
        first_sigma_rad: the weak prior on the first rotation [rad].
        first_sigma_mps: the weak prior on the first velocity [m/s].
        min_dt_s: time steps are clamped to at least this [s].
        lm_max_iterations: Gauss-Newton (and Levenberg-Marquardt) iteration cap.
        lm_rel_tol: relative error decrease tolerance of the batch solve
            (1e-5: 3 iterations from per-frame PnP, 0.03 mm from the solution
            converged to 1e-9; 1e-7 took a 4th iteration for 0.004 mm).
            Gauss-Newton stops when a step's predicted decrease is below it
            (the same steps as gtsam's LM, poses within 2e-9 m of its).
        segment_frames: segment length of the batch elimination ordering
            (see ``segmented_ordering``; 10,000 frames, constant velocity, one
            sequential elimination: 0.116 ms/frame CPU at 300, 0.096 at 30).
        isam_relinearize_threshold: iSAM2 relinearisation threshold (rad and
            m of a pose's tangent, m of a landmark, the bias's units).
        isam_relinearize_velocity_mps: the same for a velocity [m/s]. Larger
            is faster and a worse causal estimate (10,000 bench frames, window
            300, recent 0: 0.1 -> 4.84 ms CPU per update, causal error 70.31
            mm; 0.2 -> 4.19, 73.78; 0.3 -> 2.61, 75.83; 0.5 -> 2.22, 77.34; the
            final estimate the same, 0.113 mm from batch).
        isam_relinearize_recent_frames: only the velocities of the newest this
            many frames may be relinearised (older ones are iSAM2's
            ``noRelinKeys``; 0: all). Relinearising an old frame re-eliminates
            the tree from it to the root, most of the window: at 0, every 10th
            update relinearised 100-350 variables (10-55 ms). 10,000 bench
            frames: 30 -> 4.13 ms CPU per update, causal 70.31 mm (as at 0);
            10 -> 2.30, 72.44 (before this and the previous-frame ordering:
            7.64 ms, 70.00 mm).
        isam_final_updates: cap on the converging updates after the last frame.
        isam_init_gate_m: a per-frame initial pose further than this from the
            motion model's prediction is ignored [m].
        isam_segment_frames: iSAM2 gives the landmarks (and the IMU bias)
            a new variable every this many frames, tied to the previous one
            by a ``BetweenFactor`` of sigma ``isam_copy_sigma`` (an equality
            to 1e-5 m: the solution is the batch one). Every new frame's
            factors touch the landmarks, so iSAM2 re-eliminates them at each
            update and scans every factor attached to them: with one variable
            per landmark that scan grows with the flight (40 ms per frame
            after 1,000 frames); with copies it is bounded by the segment.
            0 disables (one variable per landmark, as in the batch graph).
        isam_copy_sigma: sigma of the ties between copies (metres for
            landmarks, bias units for the bias); 1e-6 made iSAM2's Cholesky
            report an indeterminate system, 1e-4 let the final estimate drift
            0.5 mm from the batch one.
        isam_window_frames: every this many frames the frames before the
            newest leave iSAM2 (memory and time per frame are then bounded by
            the window, not the flight): their factors, linearised at the
            running estimate, are eliminated into (a) linear factors on the
            newest frame, the landmarks and the bias, which start a fresh
            iSAM2 (the causal estimate goes on from all the information) and
            (b) their conditionals on those variables, kept aside (~10 KB per
            frame). After the last frame a back-substitution through them
            gives the whole flight's estimate, centimetres from the batch
            one (linearised where the running estimate was); Gauss-Newton
            sweeps over the whole graph, each eliminated block by block
            (window-sized blocks, one linear factor carried from each to the
            next), take it to the batch solution (within 0.1 mm in
            tests/test_isam2_memory.py), and the last sweep's conditionals
            give the covariances by one selected inversion. Landmark copies
            (``isam_segment_frames``) still bound each update within the
            window. 0: one iSAM2 over the whole flight (1.2 MB per frame).
        compute_sigmas: compute per-pose marginal position sigmas.
        max_sigma_frames: skip the sigmas (NaN, with a warning) for longer
            flights. With one Bayes-tree marginal per pose (3-5 ms each:
            every pose's clique carries all landmarks) this was 3,000; the
            one backward pass (``batch_covariances``) costs less than the
            solve itself.
    """

    huber_k: float = 2.45
    landmarks: str = RIGID
    rigid_tie_sigma_m: float = 3e-3
    fixed_sigma_m: float = 1e-6
    kernel: str = HUBER
    tukey_k: float = 4.685
    gnc_chi2: float = CHI2_2DOF_999
    motion: str = CONSTANT_VELOCITY
    rw_sigma_rot: float = 0.2
    rw_sigma_pos: float = 0.2
    cv_sigma_acc: float = 2.0
    cv_sigma_rot: float = 0.2
    first_sigma_m: float = 100.0
    first_sigma_rad: float = 3.0
    first_sigma_mps: float = 30.0
    min_dt_s: float = 1e-4
    lm_max_iterations: int = 50
    lm_rel_tol: float = 1e-5
    segment_frames: int = 30
    isam_relinearize_threshold: float = 0.1
    isam_relinearize_velocity_mps: float = 0.1
    isam_relinearize_recent_frames: int = 30
    isam_final_updates: int = 20
    isam_relinearize_skip: int = 10
    isam_wildfire: float = 0.01
    isam_landmarks_last: bool = True
    isam_init_gate_m: float = 1.0
    isam_segment_frames: int = 50
    isam_copy_sigma: float = 1e-5
    isam_window_frames: int = 300
    compute_sigmas: bool = True
    max_sigma_frames: int = 20000


@dataclass(frozen=True)
class Measurements:
    """Every usable keypoint observation of a flight, flattened.

    Attributes:
        landmark_code: (L,) code of each landmark.
        landmark_name: (L,) keypoint name of each landmark.
        landmark_world: (L, 3) surveyed landmark positions [m].
        landmark_sigma_m: (L,) survey sigma [m].
        frame: (M,) frame position (0..N-1) of each measurement.
        landmark: (M,) landmark index of each measurement.
        px: (M, 2) undistorted pixels.
        sigma_px: (M,) undistorted-pixel sigma, one per keypoint (the
            geometric mean of its two axes' ``sigma_uv_px``, as the decoder's
            ``sigma_px`` is of a sign's).
        sign_index: (M,) index of the observation in its frame's ``signs``.
        n_frames: N.
        sigma_uv_px: (M, 2) pixel sigma per image axis (u, v): the decoder's
            ``keypoint_sigma_px``, else its ``sigma_px`` on both (raw pixels),
            carried into the undistorted image by the lens's Jacobian there
            (the marginals ``sqrt(diag(cov_uv_px))``); None: ``sigma_px`` on
            both axes.
        cov_uv_px: (M, 2, 2) pixel covariance [px^2] in the undistorted image,
            ``J diag(su^2, sv^2) J^T`` (the lens correlates the axes), or None
            (no distortion: the axes' sigmas are the whole of it).
    """

    landmark_code: tuple[str, ...]
    landmark_name: tuple[str, ...]
    landmark_world: np.ndarray
    landmark_sigma_m: np.ndarray
    frame: np.ndarray
    landmark: np.ndarray
    px: np.ndarray
    sigma_px: np.ndarray
    sign_index: np.ndarray
    n_frames: int
    sigma_uv_px: np.ndarray | None = None
    cov_uv_px: np.ndarray | None = None

    def subset(self, keep: np.ndarray) -> Measurements:
        """The measurements where ``keep`` (M,) is True (or at indices ``keep``)."""
        return replace(
            self,
            frame=self.frame[keep],
            landmark=self.landmark[keep],
            px=self.px[keep],
            sigma_px=self.sigma_px[keep],
            sign_index=self.sign_index[keep],
            sigma_uv_px=None if self.sigma_uv_px is None else self.sigma_uv_px[keep],
            cov_uv_px=None if self.cov_uv_px is None else self.cov_uv_px[keep],
        )

    def axis_sigmas(self) -> np.ndarray:
        """(M, 2) pixel sigma of every measurement per image axis (u, v)."""
        if self.sigma_uv_px is not None:
            return self.sigma_uv_px
        return np.repeat(self.sigma_px.reshape(-1, 1), 2, axis=1)

    def pixel_noise(self) -> np.ndarray:
        """What the factors whiten by: (M, 2, 2) covariances where the lens
        correlates the axes (``cov_uv_px``), else the (M, 2) axes' sigmas
        (``projection.whitened`` and the pose functions take either)."""
        return self.axis_sigmas() if self.cov_uv_px is None else self.cov_uv_px

    def pixel_cov(self) -> np.ndarray:
        """(M, 2, 2) pixel covariance of every measurement [px^2]."""
        if self.cov_uv_px is not None:
            return self.cov_uv_px
        return self.axis_sigmas()[:, :, None] ** 2 * np.eye(2)

    def whitened(self, residual_px: np.ndarray, ids: np.ndarray | None = None) -> np.ndarray:
        """(K, 2) residuals of measurements ``ids`` (all: None) whitened as the factors do."""
        noise = self.pixel_noise()
        return whitened(residual_px, noise if ids is None else noise[ids])


def collect_measurements(
    frames: Sequence[FrameObservations], sign_map: SignMap, camera: CameraModel
) -> Measurements:
    """Match observed keypoints to map landmarks; undistort all pixels in one call."""
    codes, names, world, sig = [], [], [], []
    index: dict[tuple[str, str], int] = {}
    for sign in sign_map.signs:
        for name, p in sign.keypoints_world().items():
            index[(sign.code, name)] = len(codes)
            codes.append(sign.code)
            names.append(name)
            world.append(p)
            sig.append(sign.sigma_m)
    fr, lm, raw, sp, si = [], [], [], [], []
    for i, f in enumerate(frames):
        for k, obs in enumerate(f.signs):
            for name, uv in obs.keypoints_px.items():
                j = index.get((obs.code, name))
                if j is None:  # code absent from the map, or a keypoint it does not have
                    continue
                fr.append(i)
                lm.append(j)
                raw.append(uv)
                sp.append(keypoint_sigmas(obs, name))
                si.append(k)
    # The decoder's sigmas are raw pixels': carried through the lens's Jacobian;
    # a keypoint where the lens model holds no inverse is dropped (not guessed).
    px, jac, valid = undistort_px_jacobian(camera, np.asarray(raw, dtype=float).reshape(-1, 2))
    sigma_uv = np.asarray(sp, dtype=float).reshape(-1, 2)
    cov = None
    if jac is not None:
        cov = undistorted_cov(jac, sigma_uv)
        sigma_uv = np.sqrt(np.stack([cov[:, 0, 0], cov[:, 1, 1]], axis=1))
    fr_a, lm_a, si_a = (np.asarray(a, dtype=np.int64) for a in (fr, lm, si))
    if valid is not None and not np.all(valid):
        log.warning(
            "%d of %d keypoints lie where the camera file's lens model has no inverse "
            "(a ray at 90 deg or more, or beyond the radius its polynomial was fitted to): "
            "not used; check the calibration covers the whole image",
            int(np.sum(~valid)),
            len(valid),
        )
        px, sigma_uv, cov, fr_a, lm_a, si_a = (
            a[valid] for a in (px, sigma_uv, cov, fr_a, lm_a, si_a)
        )
    return Measurements(
        tuple(codes),
        tuple(names),
        np.asarray(world, dtype=float).reshape(-1, 3),
        np.asarray(sig, dtype=float),
        fr_a,
        lm_a,
        px,
        np.sqrt(sigma_uv[:, 0] * sigma_uv[:, 1]),
        si_a,
        len(frames),
        sigma_uv,
        cov,
    )


@dataclass(frozen=True)
class SmootherResult:
    """A smoothed trajectory.

    Attributes:
        world_T_cam: (N, 4, 4) pose of every frame.
        sigma_xyz: (N, 3) marginal position standard deviations, world axes
            [m] (NaN when not computed).
        observed: (N,) True where the frame had at least one projection factor.
        signs_used: (N,) distinct map signs with factors in each frame.
        landmarks_world: (L, 3) estimated landmark positions [m].
        causal_world_T_cam: (N, 4, 4) iSAM2's estimate of each frame right
            after it was added (the filter result), or None for batch.
        causal_sigma_xyz: (N, 3) that estimate's marginal position sigmas,
            world axes [m] (the filter's, from the same update), or None
            (batch, or sigmas not computed).
        seconds: solve time [s] (graph building and optimisation).
        build_seconds: of which building the graph [s] (batch; 0 for iSAM2).
        sigma_seconds: time spent on marginals [s].
        per_frame_ms: (N,) iSAM2 update time per frame [ms], or None.
        per_frame_cpu_ms: (N,) iSAM2 CPU time per frame [ms], or None.
        iterations: LM iterations (batch) or 0.
        final_error: graph error at the solution.
        cov6: (N, 6, 6) marginal covariance of each pose, gtsam's order
            [rotation, translation] in the camera frame, or None.
        weights: (M,) GNC weight of each measurement (1 inlier, 0 outlier),
            or None when GNC did not run.
        survey_sigma_xyz: (N, 3) the survey's share of ``sigma_xyz``, world axes
            [m]: the sd that the landmark priors' means drawn as their sigmas say
            (the map's N(0, sigma_m) per centre) give each position through the
            smoother, ``sqrt(diag(Sigma_xP Lambda_P Sigma_Px))``. Every frame
            that sees the same signs shares this part of its error: a flight's
            positions move together by it (tests/test_survey_share.py: the
            positions' finite-difference response to the centres gives the same).
            None when not computed (no sigmas, or marginals from the Bayes tree:
            Levenberg-Marquardt, GNC, iSAM2).
    """

    world_T_cam: np.ndarray
    sigma_xyz: np.ndarray
    observed: np.ndarray
    signs_used: np.ndarray
    landmarks_world: np.ndarray
    causal_world_T_cam: np.ndarray | None = None
    causal_sigma_xyz: np.ndarray | None = None
    seconds: float = 0.0
    build_seconds: float = 0.0
    sigma_seconds: float = 0.0
    per_frame_ms: np.ndarray | None = None
    per_frame_cpu_ms: np.ndarray | None = None
    iterations: int = 0
    final_error: float = float("nan")
    cov6: np.ndarray | None = None
    weights: np.ndarray | None = None
    survey_sigma_xyz: np.ndarray | None = None


def _calibration(camera: CameraModel) -> gtsam.Cal3_S2:
    K = camera.K
    return gtsam.Cal3_S2(
        float(K[0, 0]), float(K[1, 1]), float(K[0, 1]), float(K[0, 2]), float(K[1, 2])
    )


class _GraphBuilder:
    """Makes the factors of one frame (shared by the batch and incremental solvers)."""

    def __init__(
        self, meas: Measurements, stamps_s: np.ndarray, camera: CameraModel, s: SmootherSettings
    ):
        if s.motion not in MOTION_MODELS:
            raise ValueError(f"unknown motion model {s.motion!r}; use one of {MOTION_MODELS}")
        if s.kernel not in KERNELS:
            raise ValueError(f"unknown kernel {s.kernel!r}; use one of {KERNELS}")
        if s.landmarks not in LANDMARK_MODELS:
            raise ValueError(
                f"unknown landmark model {s.landmarks!r}; use one of {LANDMARK_MODELS}"
            )
        self.m = meas
        self.s = s
        self.stamps = np.asarray(stamps_s, dtype=float)
        self.K = _calibration(camera)
        self._noise: dict[tuple[float, float], object] = {}
        order = np.argsort(meas.frame, kind="stable")
        self._order = order
        self._starts = np.searchsorted(meas.frame[order], np.arange(meas.n_frames + 1))
        self._pim_cache: dict[float, object] = {}
        if s.motion == CONSTANT_VELOCITY:
            p = gtsam.PreintegrationParams.MakeSharedU(0.0)
            p.setAccelerometerCovariance(np.eye(3) * s.cv_sigma_acc**2)
            p.setGyroscopeCovariance(np.eye(3) * s.cv_sigma_rot**2)
            p.setIntegrationCovariance(np.eye(3) * 1e-8)
            self._imu_params = p

    def measurement_ids(self, i: int) -> np.ndarray:
        """Indices into the measurements of frame i's keypoints."""
        return self._order[self._starts[i] : self._starts[i + 1]]

    def _pixel_noise(self, sigma_u: float, sigma_v: float):
        key = (round(float(sigma_u), 6), round(float(sigma_v), 6))
        if key not in self._noise:
            if key[0] == key[1]:
                base = gtsam.noiseModel.Isotropic.Sigma(2, key[0])
            else:
                base = gtsam.noiseModel.Diagonal.Sigmas(np.array(key))
            self._noise[key] = self._robust(base)
        return self._noise[key]

    @staticmethod
    def _gaussian(cov: np.ndarray):
        """A full 2 x 2 pixel covariance's noise model (its Cholesky whitening)."""
        return gtsam.noiseModel.Gaussian.Covariance(np.ascontiguousarray(cov, dtype=float))

    def _robust(self, base):
        """``base`` under the settings' kernel (GNC weighs plain Gaussian factors itself)."""
        if self.s.kernel == GNC:
            return base
        if not hasattr(self, "_kernel"):  # one (stateless) kernel for every factor
            est = gtsam.noiseModel.mEstimator
            self._kernel = (
                est.Tukey.Create(self.s.tukey_k)
                if self.s.kernel == TUKEY
                else est.Huber.Create(self.s.huber_k)
            )
        return gtsam.noiseModel.Robust.Create(self._kernel, base)

    def landmark_sigma(self, j: int) -> float:
        """Prior sigma of keypoint landmark j [m] (keypoints and fixed models)."""
        if self.s.landmarks == FIXED:
            return self.s.fixed_sigma_m
        return float(self.m.landmark_sigma_m[j])

    def landmark_prior(self, j: int) -> gtsam.NonlinearFactor:
        noise = gtsam.noiseModel.Isotropic.Sigma(3, self.landmark_sigma(j))
        return gtsam.PriorFactorPoint3(L(j), self.m.landmark_world[j], noise)

    def signs(self) -> tuple[np.ndarray, np.ndarray]:
        """((L,) sign index of each landmark, (n_signs, 3) survey centres) of the map."""
        m = self.m
        codes = sorted(set(m.landmark_code))
        sign = np.array([codes.index(c) for c in m.landmark_code], np.int64)
        centre = np.zeros((len(codes), 3))
        for j, name in enumerate(m.landmark_name):
            if name == "center":
                centre[sign[j]] = m.landmark_world[j]
        return sign, centre

    def landmark_factors(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        start_world: np.ndarray | None = None,
    ) -> None:
        """The survey's factors and the landmarks' initial values (batch graph).

        ``start_world``: (L, 3) initial keypoint landmarks [m] (an earlier
        solve's), else the survey's; a rigid sign's centre starts where its
        keypoints put it (their mean less the map's offsets).
        """
        m = self.m
        start = m.landmark_world if start_world is None else np.asarray(start_world, float)
        for j in range(len(m.landmark_code)):
            values.insert(L(j), start[j])
        if self.s.landmarks != RIGID:
            for j in range(len(m.landmark_code)):
                graph.add(self.landmark_prior(j))
            return
        sign, centre = self.signs()
        tie = gtsam.noiseModel.Isotropic.Sigma(3, self.s.rigid_tie_sigma_m)
        sigma = np.zeros(len(centre))
        sigma[sign] = m.landmark_sigma_m
        moved = np.zeros_like(centre)
        np.add.at(moved, sign, start - m.landmark_world)
        moved /= np.maximum(np.bincount(sign, minlength=len(centre)), 1)[:, None]
        for k, c in enumerate(centre):
            values.insert(S(k), c + moved[k])
            noise = gtsam.noiseModel.Isotropic.Sigma(3, float(sigma[k]))
            graph.add(gtsam.PriorFactorPoint3(S(k), c, noise))
        for j in range(len(m.landmark_code)):
            offset = m.landmark_world[j] - centre[sign[j]]
            graph.add(gtsam.BetweenFactorPoint3(S(int(sign[j])), L(j), offset, tie))

    def survey_priors(self) -> dict[int, np.ndarray]:
        """Key -> (3, 3) information of each landmark prior (``landmark_factors``'s):
        a rigid sign's centre, else every keypoint."""
        if self.s.landmarks == RIGID:
            sign, centre = self.signs()
            sigma = np.zeros(len(centre))
            sigma[sign] = self.m.landmark_sigma_m
            return {S(k): np.eye(3) / float(sg) ** 2 for k, sg in enumerate(sigma)}
        return {
            L(j): np.eye(3) / self.landmark_sigma(j) ** 2 for j in range(len(self.m.landmark_code))
        }

    def ordered(self, order: gtsam.Ordering) -> gtsam.Ordering:
        """``order`` with the rigid model's sign keys appended (eliminated last)."""
        if self.s.landmarks == RIGID:
            for k in range(len(set(self.m.landmark_code))):
                order.push_back(S(k))
        return order

    def _prepare_projection(self) -> None:
        """Per-measurement pixels, noise models and landmark keys as Python lists.

        Building 370,000 factors is a Python loop; indexing numpy arrays and
        rounding sigmas inside it cost more than the gtsam constructors.
        """
        m = self.m
        if m.cov_uv_px is not None:  # through a lens: one full 2 x 2 model per keypoint
            self._meas_noise = [self._robust(self._gaussian(c)) for c in m.cov_uv_px]
        else:
            sig = np.round(m.axis_sigmas().astype(float), 6)
            # one complex key per (sigma_u, sigma_v): 4.7 ms for 74,000 measurements,
            # np.unique(axis=0) 40 ms; a real key when every keypoint is isotropic (1.3 ms)
            iso = bool(np.all(sig[:, 0] == sig[:, 1]))
            key = sig[:, 0] if iso else sig[:, 0] + 1j * sig[:, 1]
            uniq, inv = np.unique(key, return_inverse=True)
            models = [self._pixel_noise(u.real, u.real if iso else u.imag) for u in uniq]
            self._meas_noise = [models[k] for k in inv.reshape(-1).tolist()]
        self._meas_px = list(np.ascontiguousarray(m.px, dtype=float))
        self._meas_lm = m.landmark.tolist()
        self._lm_keys = [L(j) for j in range(len(m.landmark_code))]

    def projection_factors(
        self, i: int, graph: gtsam.NonlinearFactorGraph, lm_keys: list[int] | None = None
    ) -> set[int]:
        """Add frame i's projection factors; return the landmarks they touch.

        ``lm_keys`` maps landmark index to variable key (default ``L(j)``).
        """
        if not hasattr(self, "_meas_px"):
            self._prepare_projection()
        xi = X(i)
        cal = self.K
        px, noise, lm = self._meas_px, self._meas_noise, self._meas_lm
        keys = self._lm_keys if lm_keys is None else lm_keys
        make = gtsam.GenericProjectionFactorCal3_S2
        ids = self.measurement_ids(i).tolist()
        add = graph.add
        for k in ids:
            add(make(px[k], noise[k], xi, keys[lm[k]], cal))
        return {lm[k] for k in ids}

    def dt(self, i: int) -> float:
        return max(float(self.stamps[i] - self.stamps[i - 1]), self.s.min_dt_s)

    def motion_factor(
        self, i: int, graph: gtsam.NonlinearFactorGraph, bias_key: int = BIAS_KEY
    ) -> None:
        """The motion prior between frames i-1 and i."""
        s, dt = self.s, self.dt(i)
        if s.motion == RANDOM_WALK:
            r, p = s.rw_sigma_rot * np.sqrt(dt), s.rw_sigma_pos * np.sqrt(dt)
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([r, r, r, p, p, p]))
            graph.add(gtsam.BetweenFactorPose3(X(i - 1), X(i), gtsam.Pose3(), noise))
        else:
            key = round(dt, 9)
            if key not in self._pim_cache:
                pim = gtsam.PreintegratedImuMeasurements(
                    self._imu_params, gtsam.imuBias.ConstantBias()
                )
                # Several sub-steps: one step makes the position and velocity noise
                # fully correlated (a singular covariance); four approach the
                # continuous white-noise-acceleration covariance.
                for _ in range(4):
                    pim.integrateMeasurement(np.zeros(3), np.zeros(3), dt / 4)
                self._pim_cache[key] = pim
            graph.add(
                gtsam.ImuFactor(X(i - 1), V(i - 1), X(i), V(i), bias_key, self._pim_cache[key])
            )

    def first_priors(
        self, pose0: gtsam.Pose3, graph: gtsam.NonlinearFactorGraph, i: int = 0
    ) -> None:
        """The weak priors on a flight's first frame i (and, for frame 0, the IMU bias)."""
        s = self.s
        sig = np.array([s.first_sigma_rad] * 3 + [s.first_sigma_m] * 3)
        graph.add(gtsam.PriorFactorPose3(X(i), pose0, gtsam.noiseModel.Diagonal.Sigmas(sig)))
        if s.motion == CONSTANT_VELOCITY:
            graph.add(
                gtsam.PriorFactorVector(
                    V(i), np.zeros(3), gtsam.noiseModel.Isotropic.Sigma(3, s.first_sigma_mps)
                )
            )
        if s.motion == CONSTANT_VELOCITY and i == 0:
            graph.add(
                gtsam.PriorFactorConstantBias(
                    BIAS_KEY,
                    gtsam.imuBias.ConstantBias(),
                    gtsam.noiseModel.Isotropic.Sigma(6, 1e-4),
                )
            )


def _fill_initial(init: list[np.ndarray | None], default: np.ndarray) -> np.ndarray:
    """Initial poses: given ones kept, gaps held from the nearest earlier (else later) pose."""
    n = len(init)
    out = np.empty((n, 4, 4))
    have = [i for i, p in enumerate(init) if p is not None]
    if not have:
        out[:] = default
        return out
    last = init[have[0]]
    for i in range(n):
        if init[i] is not None:
            last = init[i]
        out[i] = last
    return out


def _velocities(poses: np.ndarray, stamps: np.ndarray) -> np.ndarray:
    p = poses[:, :3, 3]
    v = np.zeros_like(p)
    if len(p) > 1:
        dt = np.maximum(np.diff(stamps), 1e-4)
        v[1:] = np.diff(p, axis=0) / dt[:, None]
        v[0] = v[1]
    return v


def default_pose(sign_map: SignMap, distance_m: float = 27.0) -> np.ndarray:
    """A pose looking at the map's centre from ``distance_m`` along the signs' mean normal."""
    c = sign_map.centers_m().mean(axis=0)
    normals = [s.normal for s in sign_map.signs if s.normal is not None]
    n = np.mean(normals, axis=0) if normals else np.array([0.0, 1.0, 0.0])
    n = n / max(np.linalg.norm(n), 1e-9)
    pos = c + distance_m * n
    z = -n
    up = np.array([0.0, 0.0, 1.0])
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], axis=1)
    T[:3, 3] = pos
    return T


def _position_sigmas(cov6: np.ndarray, world_R_cam: np.ndarray) -> np.ndarray:
    """Pose3 covariance is [rot, trans] in the body frame; rotate the trans block to world."""
    c = world_R_cam @ cov6[3:, 3:] @ world_R_cam.T
    return np.sqrt(np.maximum(np.diag(c), 0.0))


def _observed_and_signs(meas: Measurements) -> tuple[np.ndarray, np.ndarray]:
    observed = np.zeros(meas.n_frames, bool)
    observed[meas.frame] = True
    signs = np.zeros(meas.n_frames, np.int64)
    if len(meas.frame):
        _, code_of_landmark = np.unique(np.array(meas.landmark_code), return_inverse=True)
        code = code_of_landmark.reshape(-1)[meas.landmark]
        pairs = np.unique(meas.frame * (int(code.max()) + 1) + code)  # distinct (frame, code)
        np.add.at(signs, pairs // (int(code.max()) + 1), 1)
    return observed, signs


@dataclass(frozen=True)
class _BatchGraph:
    graph: gtsam.NonlinearFactorGraph
    values: gtsam.Values
    projection_factor: np.ndarray  # (M,) factor index of each measurement (-1: none)


def _batch_graph(
    b: _GraphBuilder,
    init: np.ndarray,
    stamps_s: np.ndarray,
    starts: Sequence[int] = (0,),
    motion: bool = True,
    landmarks_start: np.ndarray | None = None,
) -> _BatchGraph:
    """Every factor of the flight (or of flights starting at frames ``starts``), initial values.

    ``motion=False`` leaves out the motion prior's factors (``_add_motion`` adds them).
    ``landmarks_start``: (L, 3) initial keypoint landmarks [m], else the survey's.
    """
    meas, s = b.m, b.s
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    b.landmark_factors(graph, values, landmarks_start)
    for i in starts:
        b.first_priors(gtsam.Pose3(init[i]), graph, i)
    vel = _velocities(init, stamps_s) if s.motion == CONSTANT_VELOCITY else None
    if s.motion == CONSTANT_VELOCITY:
        values.insert(BIAS_KEY, gtsam.imuBias.ConstantBias())
    factor = np.full(len(meas.frame), -1, np.int64)
    for i in range(meas.n_frames):
        values.insert(X(i), gtsam.Pose3(init[i]))
        if vel is not None:
            values.insert(V(i), vel[i])
        first = graph.size()
        b.projection_factors(i, graph)
        factor[b.measurement_ids(i)] = np.arange(first, graph.size())
        if motion and i > 0 and i not in starts:
            b.motion_factor(i, graph)
    return _BatchGraph(graph, values, factor)


def _add_motion(b: _GraphBuilder, graph: gtsam.NonlinearFactorGraph) -> None:
    """The motion prior's factors of one flight (frames 1..N-1) appended to ``graph``."""
    for i in range(1, b.m.n_frames):
        b.motion_factor(i, graph)


def _optimize(
    g: _BatchGraph, params: gtsam.LevenbergMarquardtParams, s: SmootherSettings
) -> tuple[gtsam.Values, int, np.ndarray | None]:
    """(solution, LM iterations, (M,) GNC weights or None)."""
    if s.kernel != GNC:
        opt = gtsam.LevenbergMarquardtOptimizer(g.graph, g.values, params)
        return opt.optimize(), int(opt.iterations()), None
    gnc = gtsam.GncLMParams(params)
    gnc.setLossType(gtsam.GncLossType.TLS)
    projection = set(g.projection_factor.tolist())
    gnc.setKnownInliers([k for k in range(g.graph.size()) if k not in projection])
    opt = gtsam.GncLMOptimizer(g.graph, g.values, gnc)
    # GNC compares the factor error 0.5 * chi2 with its threshold.
    opt.setInlierCostThresholds(0.5 * s.gnc_chi2)
    result = opt.optimize()
    weights = np.asarray(opt.getWeights())[g.projection_factor]
    return result, 0, weights


def _lm_params(b: _GraphBuilder) -> gtsam.LevenbergMarquardtParams:
    """Levenberg-Marquardt settings of a batch solve: segmented order, the settings' limits."""
    s, n = b.s, b.m.n_frames
    params = gtsam.LevenbergMarquardtParams()
    params.setOrdering(
        b.ordered(segmented_ordering(n, len(b.m.landmark_code), s.motion, s.segment_frames))
    )
    params.setMaxIterations(s.lm_max_iterations)
    params.setRelativeErrorTol(s.lm_rel_tol)
    return params


@dataclass(frozen=True)
class _Solved:
    """A batch solve: the solution and the Bayes net that gives its marginals.

    ``net`` is the graph linearised at ``linearised_at`` (the estimate one
    Gauss-Newton step before ``values``: that step's predicted decrease was
    below the tolerance) and eliminated in ``order``; None when the solve
    fell back to Levenberg-Marquardt (the marginals then linearise again).
    """

    values: gtsam.Values
    iterations: int
    net: gtsam.GaussianBayesNet | None
    order: gtsam.Ordering


def _gauss_newton(g: _BatchGraph, b: _GraphBuilder, abs_tol: float = 0.0) -> _Solved:
    """Gauss-Newton steps from ``g.values``, each one sequential elimination in the segmented order.

    Stops when a step's decrease, predicted by its Bayes net (``0.5 sum |d|^2``)
    or achieved, is below ``lm_rel_tol`` of the error (Levenberg-Marquardt's
    relative test, one step earlier: the net of the last linearisation is kept
    for the marginals instead of linearising and eliminating once more at the
    solution). A step that does not decrease the error, or an elimination that
    fails, hands over to gtsam's Levenberg-Marquardt from the last estimate.
    """
    s, n = b.s, b.m.n_frames
    order = b.ordered(segmented_ordering(n, len(b.m.landmark_code), s.motion, s.segment_frames))
    values = g.values
    error = g.graph.error(values)
    for it in range(s.lm_max_iterations):
        try:
            net = g.graph.linearize(values).eliminateSequential(order)
        except RuntimeError:
            net = None
        if net is None:
            break
        delta = net.optimize()
        zero = gtsam.VectorValues(delta)
        zero.setZero()
        predicted = net.error(zero)
        new = values.retract(delta)
        new_error = g.graph.error(new)
        if not new_error <= error:  # also NaN: damping from here
            break
        small = max(predicted, error - new_error) <= s.lm_rel_tol * error
        values, error = new, new_error
        if small or error <= abs_tol:
            return _Solved(values, it + 1, net, order)
    else:
        return _Solved(values, s.lm_max_iterations, None, order)
    params = _lm_params(b)
    params.setAbsoluteErrorTol(abs_tol)
    opt = gtsam.LevenbergMarquardtOptimizer(g.graph, values, params)
    result = opt.optimize()
    return _Solved(result, it + int(opt.iterations()), None, order)


def smooth_batch(
    meas: Measurements,
    stamps_s: np.ndarray,
    init_world_T_cam: list[np.ndarray | None],
    camera: CameraModel,
    settings: SmootherSettings,
    default_world_T_cam: np.ndarray,
    init_landmarks_world: np.ndarray | None = None,
) -> SmootherResult:
    """Batch Gauss-Newton / Levenberg-Marquardt (or GNC on top of it) over the whole flight.

    ``init_landmarks_world``: (L, 3) initial keypoint landmarks [m] (else the
    survey's). Tukey gives no pull to a residual beyond its threshold, so it
    cannot move a sign off its survey where the survey is the reason for the
    residual: when the pixel sigmas are small against ``sigma_m``, a sign
    surveyed 2.5 sigma_m off lies 30+ sigmas off in every frame and the whole
    sign was dropped (40 of 40 observations of the moved sign on
    ``estimator_scene`` with 0.05 px). Without given landmarks, a Tukey solve
    therefore starts from a Huber solve of the same graph (poses and landmarks).
    """
    s = settings
    if s.kernel == TUKEY and init_landmarks_world is None:
        huber = replace(s, kernel=HUBER, compute_sigmas=False)
        start = smooth_batch(meas, stamps_s, init_world_T_cam, camera, huber, default_world_T_cam)
        init_world_T_cam, init_landmarks_world = list(start.world_T_cam), start.landmarks_world
    t0 = time.perf_counter()
    n = meas.n_frames
    b = _GraphBuilder(meas, stamps_s, camera, s)
    init = _fill_initial(init_world_T_cam, default_world_T_cam)
    g = _batch_graph(b, init, stamps_s, landmarks_start=init_landmarks_world)
    t_build = time.perf_counter() - t0
    solved, weights = None, None
    if s.kernel == GNC:
        params = _lm_params(b)
        params.setAbsoluteErrorTol(1e-9)
        result, iterations, weights = _optimize(g, params, s)
    else:
        solved = _gauss_newton(g, b, abs_tol=1e-9)
        result, iterations = solved.values, solved.iterations
    seconds = time.perf_counter() - t0
    poses = np.array([result.atPose3(X(i)).matrix() for i in range(n)])
    lms = np.array([result.atPoint3(L(j)) for j in range(len(meas.landmark_code))]).reshape(-1, 3)
    cov6, share6 = None, None
    sigma_seconds = 0.0
    if _want_sigmas(s, n):
        t1 = time.perf_counter()
        cov6, share6 = _net_covariances(solved, n, b.survey_priors())
        if cov6 is None:
            graph = g.graph
            if weights is not None:  # the marginals of the graph GNC converged to
                graph = _without(graph, g.projection_factor[weights < 0.5])
            order = b.ordered(
                segmented_ordering(n, len(meas.landmark_code), s.motion, s.segment_frames)
            )
            cov6 = batch_covariances(graph, result, n, order)
        sigma_seconds = time.perf_counter() - t1
    observed, signs = _observed_and_signs(meas)
    return SmootherResult(
        world_T_cam=poses,
        sigma_xyz=_sigmas_from(cov6, poses),
        observed=observed,
        signs_used=signs,
        landmarks_world=lms,
        seconds=seconds,
        build_seconds=t_build,
        sigma_seconds=sigma_seconds,
        iterations=iterations,
        final_error=float(g.graph.error(result)),
        cov6=cov6,
        weights=weights,
        survey_sigma_xyz=None if share6 is None else _sigmas_from(share6, poses),
    )


def _net_covariances(
    solved: _Solved | None, n: int, priors: dict[int, np.ndarray] | None = None
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """((N, 6, 6) pose covariances from the solve's last Bayes net, or None without one;
    (N, 6, 6) the ``priors``' share of them, or None)."""
    if solved is None or solved.net is None:
        return None, None
    conds = _net_conditionals(solved.net)
    if conds is None:
        return None, None
    return _pose_covariances_and_shares(conds, n, priors or {})


def _without(graph: gtsam.NonlinearFactorGraph, drop: np.ndarray) -> gtsam.NonlinearFactorGraph:
    """A copy of ``graph`` without the factors at indices ``drop``."""
    skip = set(drop.tolist())
    out = gtsam.NonlinearFactorGraph()
    for k in range(graph.size()):
        if k not in skip:
            out.add(graph.at(k))
    return out


def _sigmas_from(cov6: np.ndarray | None, poses: np.ndarray) -> np.ndarray:
    """(N, 3) world-axis position sigmas [m] from pose covariances (NaN without)."""
    if cov6 is None:
        return np.full((len(poses), 3), np.nan)
    return np.array([_position_sigmas(c, T[:3, :3]) for c, T in zip(cov6, poses, strict=True)])


def chain_ordering(n_frames: int, n_landmarks: int, motion: str) -> gtsam.Ordering:
    """Frames in time order, then the landmarks.

    Every frame sees most landmarks, so whatever the ordering each frame's
    clique carries the landmarks in its separator; eliminating the frames in
    time order keeps the rest of the separator to the next frame (a chain),
    which COLAMD does not find on long flights (measured: 10,000 frames took
    98 s with COLAMD).
    """
    return _frames_then_landmarks(range(n_frames), n_landmarks, motion)


def segmented_ordering(
    n_frames: int, n_landmarks: int, motion: str, segment: int = 300
) -> gtsam.Ordering:
    """Time order split into segments (one level of nested dissection), landmarks last.

    Each segment's frames but its last are eliminated in time order, then the
    segments' last frames (recursively segmented the same way), then the
    landmarks. Same fill as ``chain_ordering`` (every clique carries the
    landmarks, plus at most two boundary frames) and an identical solution,
    but a shallow Bayes tree: gtsam's multifrontal elimination costs more per
    clique the deeper the tree (measured, 10,000 frames, constant velocity:
    12.6 s CPU in one chain, 2.3 s with 300-frame segments).
    """
    frames = _dissect(list(range(n_frames)), max(int(segment), 2))
    return _frames_then_landmarks(frames, n_landmarks, motion)


def _frames_then_landmarks(frames: Sequence[int], n_landmarks: int, motion: str) -> gtsam.Ordering:
    """Each frame's keys in the order of ``frames``, the velocity bias, then the landmarks."""
    order = gtsam.Ordering()
    for i in frames:
        order.push_back(X(i))
        if motion == CONSTANT_VELOCITY:
            order.push_back(V(i))
    if motion == CONSTANT_VELOCITY:
        order.push_back(BIAS_KEY)
    for j in range(n_landmarks):
        order.push_back(L(j))
    return order


def _dissect(frames: list[int], segment: int) -> list[int]:
    if len(frames) <= segment:
        return frames
    inner: list[int] = []
    bounds: list[int] = []
    for a in range(0, len(frames), segment):
        part = frames[a : a + segment]
        inner += part[:-1]
        bounds.append(part[-1])
    return inner + _dissect(bounds, segment)


def _want_sigmas(s: SmootherSettings, n: int) -> bool:
    if s.compute_sigmas and n > s.max_sigma_frames:
        log.warning(
            "%d frames: skipping marginal sigmas (max_sigma_frames=%d)", n, s.max_sigma_frames
        )
        return False
    return s.compute_sigmas


def batch_covariances(
    graph: gtsam.NonlinearFactorGraph,
    values: gtsam.Values,
    n_frames: int,
    ordering: gtsam.Ordering | None = None,
    per_pose: bool = False,
) -> np.ndarray:
    """(N, 6, 6) marginal covariance of every pose ([rotation, translation], camera frame).

    Eliminates the graph linearised at the solution once, sequentially in
    ``ordering`` (the chain ordering: frames in time order, then the
    landmarks), and gets every pose's marginal in one backward pass over
    that Bayes net (``estimator.marginals``: the variables after the last
    frame are inverted as one dense block). Identical to gtsam.Marginals to
    1e-9 (tests/test_marginals_fast.py); one Bayes-tree ``marginalCovariance``
    per pose cost 3.2 ms per pose at 1,000 frames. Without an ordering, or
    when the tail is not small (or ``per_pose``: scripts/bench_estimator.py
    compares the two), the Bayes tree is asked pose by pose, newest first. NaN
    when the elimination fails (a warning is logged).
    """
    cov = np.full((n_frames, 6, 6), np.nan)
    try:
        linear = graph.linearize(values)
        if ordering is not None and not per_pose:
            fast = _chain_covariances(linear, ordering, n_frames)
            if fast is not None:
                return fast
        tree = (
            linear.eliminateMultifrontal(ordering) if ordering else linear.eliminateMultifrontal()
        )
        for i in reversed(range(n_frames)):
            cov[i] = tree.marginalCovariance(X(i))
    except RuntimeError as exc:
        log.warning("marginals failed: %s", exc)
    return cov


# Above this many dimensions after the last frame the dense tail of the
# one-pass marginals would cost more than the Bayes tree's per-pose marginals.
MAX_TAIL_DIM = 1500


def _chain_covariances(
    linear: gtsam.GaussianFactorGraph, ordering: gtsam.Ordering, n_frames: int
) -> np.ndarray | None:
    """(N, 6, 6) pose covariances by one backward pass, or None when the net does not suit it."""
    conds = _net_conditionals(linear.eliminateSequential(ordering))
    return None if conds is None else _pose_covariances(conds, n_frames)


def _net_conditionals(net: gtsam.GaussianBayesNet) -> list[Conditional] | None:
    """A sequential Bayes net's conditionals, or None when one is not unit-noise."""
    conds = []
    for k in range(net.size()):
        c = net.at(k)
        if c.get_model() is not None:  # a constrained or weighted conditional
            return None
        keys = c.keys()
        conds.append(Conditional(keys[0], np.array(c.R()), tuple(keys[1:]), np.array(c.S())))
    return conds


def _pose_covariances(conds: list[Conditional], n_frames: int) -> np.ndarray | None:
    """(N, 6, 6) from conditionals frames first (the variables after the last frame: the tail)."""
    return _pose_covariances_and_shares(conds, n_frames, {})[0]


def _pose_covariances_and_shares(
    conds: list[Conditional], n_frames: int, priors: dict[int, np.ndarray]
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``_pose_covariances`` and the share of the ``priors`` (tail key -> information) in
    them (None without priors, or when one is not in the tail)."""
    frame_keys = {X(i) for i in range(n_frames)} | {V(i) for i in range(n_frames)}
    last = max((k for k, c in enumerate(conds) if c.key in frame_keys), default=-1)
    if sum(c.R.shape[0] for c in conds[last + 1 :]) > MAX_TAIL_DIM:
        return None, None
    tail = {c.key for c in conds[last + 1 :]}
    priors = priors if priors and all(k in tail for k in priors) else {}
    wanted = [X(i) for i in range(n_frames)]
    got, shares = selected_covariances_and_shares(conds, last + 1, wanted, priors)
    cov = np.array([got[X(i)] for i in range(n_frames)]).reshape(n_frames, 6, 6)
    if not shares:
        return cov, None
    return cov, np.array([shares[X(i)] for i in range(n_frames)]).reshape(n_frames, 6, 6)


def _isam2_params(s: SmootherSettings) -> gtsam.ISAM2Params:
    """The running iSAM2's parameters."""
    p = gtsam.ISAM2Params()
    thresholds = gtsam.ISAM2ThresholdMap()
    # Every kind of variable the run holds (gtsam reads the map unchecked):
    # poses, velocities, landmarks and their copies, the bias and its copies.
    for kind, dim in (("x", 6), ("v", 3), ("l", 3), ("m", 3), ("s", 3), ("b", 6), ("c", 6)):
        value = s.isam_relinearize_velocity_mps if kind == "v" else s.isam_relinearize_threshold
        thresholds.insert((kind, np.full(dim, float(value))))
    p.setRelinearizeThreshold(thresholds)
    p.relinearizeSkip = s.isam_relinearize_skip
    # Every frame sees the same landmarks, so each update nudges all poses a
    # little; the partial check and a coarser wildfire threshold keep the
    # relinearisation check and back-substitution near the top of the tree
    # instead of walking the whole flight every frame.
    p.enablePartialRelinearizationCheck = True
    gn = gtsam.ISAM2GaussNewtonParams()
    gn.setWildfireThreshold(s.isam_wildfire)
    p.setOptimizationParams(gn)
    return p


def _tangent(values: gtsam.Values, theta: gtsam.Values, key: int) -> np.ndarray:
    """``values[key]`` minus ``theta[key]`` in theta's tangent space (gtsam's local coordinates)."""
    c = chr(gtsam.Symbol(key).chr())
    if c == "x":
        return theta.atPose3(key).localCoordinates(values.atPose3(key))
    if c == "v":
        return np.asarray(values.atVector(key)) - np.asarray(theta.atVector(key))
    if c in "bc":
        return values.atConstantBias(key).vector() - theta.atConstantBias(key).vector()
    return np.asarray(values.atPoint3(key)) - np.asarray(theta.atPoint3(key))


def _insert_retracted(values: gtsam.Values, theta: gtsam.Values, key: int, dx: np.ndarray) -> None:
    """``values[key] = theta[key] + dx`` (gtsam's retraction)."""
    c = chr(gtsam.Symbol(key).chr())
    if c == "x":
        values.insert(key, theta.atPose3(key).retract(dx))
    elif c == "v":
        values.insert(key, np.asarray(theta.atVector(key)) + dx)
    elif c in "bc":
        v = theta.atConstantBias(key).vector() + dx
        values.insert(key, gtsam.imuBias.ConstantBias(v[:3], v[3:]))
    else:
        values.insert(key, np.asarray(theta.atPoint3(key)) + dx)


@dataclass(frozen=True)
class _WrittenOut:
    """Eliminated frames (out of iSAM2, or a sweep's block): ``R dx_key + S dx_parents = d``.

    ``dx`` are tangent vectors at ``theta`` (the running estimate when they
    left); the parents are later frames of the same block, or the variables
    that stayed (the newest frame, the landmarks, the bias).
    """

    conditionals: tuple[Conditional, ...]
    d: tuple[np.ndarray, ...]
    theta: gtsam.Values
    end: int  # the first frame that stayed

    @staticmethod
    def of(net: gtsam.GaussianBayesNet, theta: gtsam.Values, end: int) -> _WrittenOut:
        conds = _net_conditionals(net)
        if conds is None:
            raise RuntimeError("iSAM2 window: a conditional with a noise model")
        ds = tuple(np.array(net.at(k).d(), float).reshape(-1) for k in range(net.size()))
        return _WrittenOut(tuple(conds), ds, theta, end)

    def back_substitute(self, final: gtsam.Values) -> None:
        """Insert the final estimate of each frame variable into ``final`` (its parents there)."""
        delta: dict[int, np.ndarray] = {}
        for c, d in zip(reversed(self.conditionals), reversed(self.d), strict=True):
            parts = []
            for p in c.parents:
                if p not in delta:
                    delta[p] = _tangent(final, self.theta, p)
                parts.append(delta[p])
            rhs = d - c.S @ np.concatenate(parts) if parts else d
            dx = np.linalg.solve(c.R, rhs)
            delta[c.key] = dx
            _insert_retracted(final, self.theta, c.key, dx)


class _Isam2Run:
    """The state of one incremental solve: iSAM2, the current landmark copies, the last estimate."""

    def __init__(self, b: _GraphBuilder, default_world_T_cam: np.ndarray):
        s = b.s
        self.b = b
        self.s = s
        self.want_sigmas = False
        self.causal_cov6: list[np.ndarray] = []  # the newest pose's marginal after each update
        self.isam = gtsam.ISAM2(_isam2_params(s))
        self.n_lm = len(b.m.landmark_code)
        self.cv = s.motion == CONSTANT_VELOCITY
        self.lm_keys = [L(j) for j in range(self.n_lm)]  # the current copy of each landmark
        self.added_lm: set[int] = set()
        self.bias_key = BIAS_KEY
        self.segment = 0
        self.tie_point = gtsam.noiseModel.Isotropic.Sigma(3, s.isam_copy_sigma)
        self.tie_bias = gtsam.noiseModel.Isotropic.Sigma(6, s.isam_copy_sigma)
        self.default = gtsam.Pose3(default_world_T_cam)
        self.prev_pose: gtsam.Pose3 | None = None
        self.prev_vel = np.zeros(3)
        self.start = 0  # the first frame in the current iSAM2
        self.written: list[_WrittenOut] = []
        self.last_update: gtsam.ISAM2Result | None = None  # the newest frame's update

    def _new_segment(self, i: int, graph: gtsam.NonlinearFactorGraph, values: gtsam.Values):
        """Fresh copies of the landmarks seen so far (and of the bias), tied to the old ones."""
        seg_len = int(self.s.isam_segment_frames)
        if seg_len <= 0 or i == 0 or i // seg_len == self.segment:
            return
        self.segment = i // seg_len
        for j in sorted(self.added_lm):
            new_key = gtsam.symbol("m", self.segment * self.n_lm + j)
            values.insert(new_key, self.isam.calculateEstimatePoint3(self.lm_keys[j]))
            graph.add(
                gtsam.BetweenFactorPoint3(self.lm_keys[j], new_key, np.zeros(3), self.tie_point)
            )
            self.lm_keys[j] = new_key
        if self.cv:
            new_bias = gtsam.symbol("c", self.segment)
            values.insert(new_bias, self.isam.calculateEstimateConstantBias(self.bias_key))
            graph.add(
                gtsam.BetweenFactorConstantBias(
                    self.bias_key, new_bias, gtsam.imuBias.ConstantBias(), self.tie_bias
                )
            )
            self.bias_key = new_bias

    def _copy_segment(self, key: int) -> int:
        """The segment whose frames use a landmark or bias copy (``_new_segment``'s keys)."""
        sym = gtsam.Symbol(key)
        c, index = chr(sym.chr()), int(sym.index())
        if c in "lb":
            return 0
        return index if c == "c" else index // self.n_lm

    def _initial_guess(self, i: int, init_world_T_cam: np.ndarray | None) -> gtsam.Pose3:
        """The per-frame pose unless it is far from the motion model's prediction."""
        predicted = self.prev_pose
        if predicted is not None and self.cv:
            predicted = gtsam.Pose3(
                predicted.rotation(), predicted.translation() + self.prev_vel * self.b.dt(i)
            )
        guess = predicted if predicted is not None else self.default
        if init_world_T_cam is not None:
            candidate = gtsam.Pose3(init_world_T_cam)
            # A per-frame pose far from the prediction is a bad start (mis-decoded
            # signs); the prediction is the better linearisation point then.
            jump = np.linalg.norm(candidate.translation() - guess.translation())
            if predicted is None or jump < self.s.isam_init_gate_m:
                guess = candidate
        return guess

    def _new_landmarks(self, touched: set[int], graph: gtsam.NonlinearFactorGraph, values):
        m = self.b.m
        for j in sorted(touched - self.added_lm):
            key = L(j) if self.segment == 0 else gtsam.symbol("m", self.segment * self.n_lm + j)
            self.lm_keys[j] = key
            noise = gtsam.noiseModel.Isotropic.Sigma(3, self.b.landmark_sigma(j))
            graph.add(gtsam.PriorFactorPoint3(key, m.landmark_world[j], noise))
            values.insert(key, m.landmark_world[j])
            self.added_lm.add(j)

    def _update_params(self, i: int) -> gtsam.ISAM2UpdateParams:
        """Landmarks (and bias) eliminated last, the new frame just before them, the previous
        frame before it.

        Without the previous frame's place, a batch reordering (iSAM2 reorders
        everything when an update touches most of the tree) left it anywhere
        in the tree: the next frame's motion factor then touched the path from
        it to the root, most of the tree again, and every update of a window's
        first segment was a batch reordering (whole tree, 1 -> 9 ms per frame
        over 50 frames). Velocities older than ``isam_relinearize_recent_frames``
        stay where they were linearised.
        """
        upd = gtsam.ISAM2UpdateParams()
        groups = gtsam.KeyGroupMap()
        for j in self.added_lm:
            groups.insert2(self.lm_keys[j], 3)
        if self.cv:
            groups.insert2(self.bias_key, 3)
        groups.insert2(X(i), 2)
        if self.cv:
            groups.insert2(V(i), 2)
        if i > self.start:
            groups.insert2(X(i - 1), 1)
            if self.cv:
                groups.insert2(V(i - 1), 1)
        upd.constrainedKeys = groups
        recent = int(self.s.isam_relinearize_recent_frames)
        if self.cv and recent > 0 and i - recent > self.start:
            old = gtsam.KeyList()
            for k in range(self.start, i - recent):
                old.push_back(V(k))
            upd.noRelinKeys = old
        return upd

    def add_frame(self, i: int, init_world_T_cam: np.ndarray | None) -> np.ndarray:
        """Frame i's variables and factors in one update; returns its (4, 4) causal estimate."""
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        self._new_segment(i, graph, values)
        guess = self._initial_guess(i, init_world_T_cam)
        values.insert(X(i), guess)
        if i == 0:
            self.b.first_priors(guess, graph)
            if self.cv:
                values.insert(BIAS_KEY, gtsam.imuBias.ConstantBias())
        if self.cv:
            values.insert(V(i), self.prev_vel)
        touched = self.b.projection_factors(i, graph, self.lm_keys)
        self._new_landmarks(touched, graph, values)
        if i > 0:
            self.b.motion_factor(i, graph, self.bias_key)
        if self.s.isam_landmarks_last:
            self.last_update = self.isam.update(graph, values, self._update_params(i))
        else:
            self.last_update = self.isam.update(graph, values)
        self.prev_pose = self.isam.calculateEstimatePose3(X(i))
        if self.want_sigmas:  # the filter's covariance: the newest pose sits at the root
            self.causal_cov6.append(np.asarray(self.isam.marginalCovariance(X(i))))
        if self.cv:
            self.prev_vel = np.asarray(self.isam.calculateEstimateVector(V(i))).reshape(3)
        window = int(self.s.isam_window_frames)
        if window > 0 and i - self.start >= window:
            self._write_out(i)
        return self.prev_pose.matrix()

    def _write_out(self, i: int) -> None:
        """Frames start..i-1 leave iSAM2 (see ``isam_window_frames``); a fresh one holds the rest.

        They leave linearised at the running estimate (two Gauss-Newton steps
        with every variable relinearised first moved the final estimate by
        less than 0.01 mm: not worth their time).
        """
        values = self.isam.calculateEstimate()
        old = {X(k) for k in range(self.start, i)}
        if self.cv:
            old |= {V(k) for k in range(self.start, i)}
        current = {self.lm_keys[j] for j in self.added_lm} | {self.bias_key}
        held = values.keys()
        copies = [k for k in held if chr(gtsam.Symbol(k).chr()) in "lmbc"]
        copies = [k for k in copies if k not in current]  # landmark and bias copies replaced
        old |= set(copies)
        factors = self.isam.getFactorsUnsafe()
        keep, leave = gtsam.NonlinearFactorGraph(), gtsam.NonlinearFactorGraph()
        for k in range(factors.size()):
            f = factors.at(k)
            if f is not None:
                involved = f.keys()
                (leave if any(key in old for key in involved) else keep).add(f)
        order = gtsam.Ordering()
        # Each segment's frames, then its replaced copies: a frame's conditional
        # then holds one generation of copies (frames first, all copies last:
        # every generation in the window, 38 KB per frame).
        by_segment: dict[int, list[int]] = {}
        for k in copies:
            by_segment.setdefault(self._copy_segment(k), []).append(k)
        seg_len = max(int(self.s.isam_segment_frames), 1)
        for k in range(self.start, i):
            order.push_back(X(k))
            if self.cv:
                order.push_back(V(k))
            if k == i - 1 or (k + 1) // seg_len != k // seg_len:
                for c in by_segment.pop(k // seg_len, []):
                    order.push_back(c)
        for rest in by_segment.values():
            for c in rest:
                order.push_back(c)
        net, marginal = leave.linearize(values).eliminatePartialSequential(order)
        self.written.append(_WrittenOut.of(net, values, i))
        for k in range(marginal.size()):
            keep.add(gtsam.LinearContainerFactor(marginal.at(k), values))
        kept = gtsam.Values()
        kept.insert(X(i), values.atPose3(X(i)))
        if self.cv:
            kept.insert(V(i), values.atVector(V(i)))
            kept.insert(self.bias_key, values.atConstantBias(self.bias_key))
        for j in self.added_lm:
            kept.insert(self.lm_keys[j], values.atPoint3(self.lm_keys[j]))
        self.isam = gtsam.ISAM2(_isam2_params(self.s))
        self.isam.update(keep, kept)
        self.start = i

    def converge(self) -> gtsam.ISAM2:
        """Converge to the batch solution.

        The running iSAM2 only relinearises variables whose delta exceeds its
        threshold, which leaves the final estimate centimetres from the optimum;
        so the final estimate is one more iSAM2 started from the running
        estimate with every variable relinearised at every step (a few
        Gauss-Newton steps on the same graph).
        """
        final_params = gtsam.ISAM2Params()
        final_params.setRelinearizeThreshold(0.0)
        final_params.relinearizeSkip = 1
        gn0 = gtsam.ISAM2GaussNewtonParams()
        gn0.setWildfireThreshold(0.0)
        final_params.setOptimizationParams(gn0)
        final = gtsam.ISAM2(final_params)
        final.update(self.isam.getFactorsUnsafe(), self.isam.calculateBestEstimate())
        last = gtsam.utilities.extractPose3(final.calculateBestEstimate())
        for _ in range(self.s.isam_final_updates):
            final.update()
            now = gtsam.utilities.extractPose3(final.calculateBestEstimate())
            change = float(np.abs(now - last).max()) if now.size else 0.0
            last = now
            if change < 1e-6:
                break
        return final

    def landmarks(self, result: gtsam.Values) -> np.ndarray:
        """(L, 3) the latest copy of every landmark; the survey for landmarks never seen."""
        m = self.b.m
        return np.array(
            [
                result.atPoint3(self.lm_keys[j]) if j in self.added_lm else m.landmark_world[j]
                for j in range(self.n_lm)
            ]
        ).reshape(-1, 3)


# Gauss-Newton sweeps over the whole flight after a windowed iSAM2 (each one
# exact, block by block), and when they stop: the largest position step [m].
SWEEPS = 4
SWEEP_TOL_M = 1e-5


def _sweep_values(run: _Isam2Run, result: gtsam.Values, n: int) -> gtsam.Values:
    """The flight's variables as the batch graph names them (one key per landmark, one bias)."""
    cur = gtsam.Values()
    for i in range(n):
        cur.insert(X(i), result.atPose3(X(i)))
        if run.cv:
            cur.insert(V(i), result.atVector(V(i)))
    for j in sorted(run.added_lm):
        cur.insert(L(j), result.atPoint3(run.lm_keys[j]))
    if run.cv:
        cur.insert(BIAS_KEY, result.atConstantBias(run.bias_key))
    return cur


def _block_graph(run: _Isam2Run, a: int, e: int, n: int) -> gtsam.NonlinearFactorGraph:
    """Frames a..e-1's factors, the motion factor on to frame e, the priors in the first block."""
    b = run.b
    graph = gtsam.NonlinearFactorGraph()
    if a == 0:
        for j in sorted(run.added_lm):
            graph.add(b.landmark_prior(j))
    for i in range(a, e):
        b.projection_factors(i, graph)
    for i in range(a + 1, min(e + 1, n)):
        b.motion_factor(i, graph)
    return graph


def _sweep(run: _Isam2Run, cur: gtsam.Values, n: int, block: int, first_pose) -> list:
    """One Gauss-Newton step of the whole flight's graph, eliminated block by block in time
    order (what stays after a block: one linear factor on the next frame, the landmarks and
    the bias), as the blocks' conditionals (_WrittenOut, last block last)."""
    carry = gtsam.GaussianFactorGraph()
    blocks = []
    for a in range(0, n, block):
        e = min(a + block, n)
        graph = _block_graph(run, a, e, n)
        if a == 0:
            run.b.first_priors(first_pose, graph)
        linear = graph.linearize(cur)
        for k in range(carry.size()):
            linear.push_back(carry.at(k))
        order = gtsam.Ordering()
        for i in range(a, e):
            order.push_back(X(i))
            if run.cv:
                order.push_back(V(i))
        if e == n:
            if run.cv:
                order.push_back(BIAS_KEY)
            for j in sorted(run.added_lm):
                order.push_back(L(j))
            blocks.append(_WrittenOut.of(linear.eliminateSequential(order), cur, e))
        else:
            net, carry = linear.eliminatePartialSequential(order)
            blocks.append(_WrittenOut.of(net, cur, e))
    return blocks


def _converge_in_blocks(run: _Isam2Run, result: gtsam.Values, n: int) -> tuple:
    """(Values of the batch optimum, the last sweep's blocks) from the windowed run's estimate.

    The windowed iSAM2 leaves the flight linearised where its running estimate
    was (centimetres from the end result); Gauss-Newton sweeps over the whole
    graph, each one eliminated block by block (memory: one block's factors and
    the conditionals), converge from the back-substituted estimate to the
    batch solution.
    """
    for block in reversed(run.written):
        block.back_substitute(result)
    run.written.clear()  # memory: the sweeps hold their own conditionals
    cur = _sweep_values(run, result, n)
    first_pose = gtsam.Pose3(result.atPose3(X(0)))
    size = max(int(run.s.isam_window_frames), 1)
    blocks: list = []
    for _ in range(SWEEPS):
        blocks = []  # the previous sweep's conditionals go before the next are made
        blocks = _sweep(run, cur, n, size, first_pose)
        nxt = gtsam.Values()
        for blk in reversed(blocks):
            blk.back_substitute(nxt)
        step = max(
            float(np.linalg.norm(nxt.atPose3(X(i)).translation() - cur.atPose3(X(i)).translation()))
            for i in range(n)
        )
        cur = nxt
        if step < SWEEP_TOL_M:
            break
    return cur, blocks


def smooth_isam2(
    meas: Measurements,
    stamps_s: np.ndarray,
    init_world_T_cam: list[np.ndarray | None],
    camera: CameraModel,
    settings: SmootherSettings,
    default_world_T_cam: np.ndarray,
    progress: bool = False,
) -> SmootherResult:
    """iSAM2, one frame per update; records the causal estimate of each new frame.

    ``init_world_T_cam`` must be causal (e.g. per-frame PnP) for the causal
    result to be causal; a frame without one starts at the motion model's
    prediction from the previous estimate.
    """
    s = settings
    t0 = time.perf_counter()
    n = meas.n_frames
    run = _Isam2Run(_GraphBuilder(meas, stamps_s, camera, s), default_world_T_cam)
    run.want_sigmas = _want_sigmas(s, n)
    causal = np.empty((n, 4, 4))
    per_ms = np.empty(n)
    per_cpu_ms = np.empty(n)
    for i in tqdm(range(n), desc="iSAM2", unit="frame", disable=not progress, leave=False):
        t_frame, c_frame = time.perf_counter(), time.process_time()
        causal[i] = run.add_frame(i, init_world_T_cam[i])
        per_ms[i] = (time.perf_counter() - t_frame) * 1e3
        per_cpu_ms[i] = (time.process_time() - c_frame) * 1e3
    isam = run.converge()
    result = isam.calculateBestEstimate()
    final_error = float(isam.getFactorsUnsafe().error(result))  # of the last window's graph
    landmarks = run.landmarks(result)
    blocks: list = []
    if run.written:
        result, blocks = _converge_in_blocks(run, result, n)
        landmarks = np.array(
            [
                result.atPoint3(L(j)) if j in run.added_lm else meas.landmark_world[j]
                for j in range(run.n_lm)
            ]
        ).reshape(-1, 3)
    seconds = time.perf_counter() - t0
    poses = np.array([result.atPose3(X(i)).matrix() for i in range(n)]).reshape(n, 4, 4)
    cov6 = None
    sigma_seconds = 0.0
    if run.want_sigmas:
        t1 = time.perf_counter()
        if blocks:  # the last sweep's conditionals, linearised at the optimum
            cov = _pose_covariances([c for blk in blocks for c in blk.conditionals], n)
            cov6 = np.full((n, 6, 6), np.nan) if cov is None else cov
        else:
            cov6 = np.array([isam.marginalCovariance(X(i)) for i in range(n)])
        sigma_seconds = time.perf_counter() - t1
    observed, signs = _observed_and_signs(meas)
    return SmootherResult(
        world_T_cam=poses,
        sigma_xyz=_sigmas_from(cov6, poses),
        observed=observed,
        signs_used=signs,
        landmarks_world=landmarks,
        causal_world_T_cam=causal,
        causal_sigma_xyz=_sigmas_from(np.array(run.causal_cov6), causal)
        if run.causal_cov6
        else None,
        seconds=seconds,
        sigma_seconds=sigma_seconds,
        per_frame_ms=per_ms,
        per_frame_cpu_ms=per_cpu_ms,
        final_error=final_error,
        cov6=cov6,
    )


# --------------------------------------------------------------------------- outliers


def project(camera: CameraModel, world_T_cam: np.ndarray, world_points: np.ndarray) -> np.ndarray:
    """(M, 2) undistorted pixels of (M, 3) points seen from (M, 4, 4) poses (full K, skew too)."""
    R = world_T_cam[:, :3, :3]
    t = world_T_cam[:, :3, 3]
    pc = np.einsum("mji,mj->mi", R, world_points - t)
    z = np.where(np.abs(pc[:, 2]) < 1e-9, 1e-9, pc[:, 2])
    return pixel_from_normalised(camera, pc[:, :2] / z[:, None])


def residuals_px(meas: Measurements, res: SmootherResult, camera: CameraModel) -> np.ndarray:
    """(M,) reprojection residual norm of every measurement at the solution [px]."""
    if len(meas.frame) == 0:
        return np.zeros(0)
    pred = project(camera, res.world_T_cam[meas.frame], res.landmarks_world[meas.landmark])
    return np.linalg.norm(pred - meas.px, axis=1)


def whitened_chi2(meas: Measurements, res: SmootherResult, camera: CameraModel) -> np.ndarray:
    """(M,) squared residual of every measurement whitened as the factors whiten it
    (per axis, or by its 2 x 2 covariance through a lens): what the kernels see."""
    if len(meas.frame) == 0:
        return np.zeros(0)
    pred = project(camera, res.world_T_cam[meas.frame], res.landmarks_world[meas.landmark])
    return np.sum(meas.whitened(pred - meas.px) ** 2, axis=1)


def covariances_at(
    meas: Measurements,
    stamps_s: np.ndarray,
    world_T_cam: np.ndarray,
    camera: CameraModel,
    settings: SmootherSettings,
) -> np.ndarray:
    """(N, 6, 6) pose covariances of the Gaussian graph linearised at ``world_T_cam``.

    No robust kernel, landmarks at the survey. At the true poses, with the true
    pixel noise in ``meas.sigma_px``, this is the Cramér-Rao bound of the
    smoother's model (motion prior and survey priors included).
    """
    s = replace(settings, kernel=GNC)  # GNC's noise models are the plain Gaussian ones
    b = _GraphBuilder(meas, stamps_s, camera, s)
    g = _batch_graph(b, np.asarray(world_T_cam, float), stamps_s)
    order = b.ordered(chain_ordering(meas.n_frames, len(meas.landmark_code), s.motion))
    return batch_covariances(g.graph, g.values, meas.n_frames, order)


def log_evidence(
    meas: Measurements,
    stamps_s: np.ndarray,
    init_world_T_cam: list[np.ndarray | None],
    camera: CameraModel,
    settings: SmootherSettings,
    default_world_T_cam: np.ndarray,
) -> float:
    """Laplace approximation of log p(measurements | motion prior), up to a constant.

    ``-E(x*) - 0.5 sum_f log det Sigma_f - 0.5 log det H``: the graph error
    at the solution, the motion factors' normalisers (the only ones that
    depend on the prior's densities) and the Gauss-Newton information of the
    whole graph (the eliminated net gives log det R = 0.5 log det H).
    """
    init = _fill_initial(init_world_T_cam, default_world_T_cam)
    return EvidenceGraph(meas, stamps_s, init, camera, settings).evidence(settings)[0]


class EvidenceGraph:
    """One flight's factors but the motion prior, built once to weigh many motion priors.

    Only the motion factors depend on the prior's densities: each
    ``evidence`` call adds them to a copy of the rest (the factors are
    shared, not rebuilt).
    """

    def __init__(
        self,
        meas: Measurements,
        stamps_s: np.ndarray,
        init_world_T_cam: np.ndarray,
        camera: CameraModel,
        settings: SmootherSettings,
    ):
        """``init_world_T_cam``: (N, 4, 4) initial poses of every frame; ``settings``: all but
        the motion densities as every ``evidence`` call will have them."""
        self.meas, self.stamps, self.camera = meas, stamps_s, camera
        s = replace(settings, compute_sigmas=False)
        b = _GraphBuilder(meas, stamps_s, camera, s)
        self.base = _batch_graph(b, np.asarray(init_world_T_cam, float), stamps_s, motion=False)

    def evidence(
        self, settings: SmootherSettings, start: gtsam.Values | None = None
    ) -> tuple[float, gtsam.Values]:
        """(``log_evidence`` under ``settings``' motion prior, the solution it was evaluated at).

        ``start``: the solution under another prior (same variables), a closer
        start than the initial poses. The log-determinant is the Gauss-Newton
        solve's last net (linearised one step, below the tolerance, before the
        solution; Levenberg-Marquardt's solution eliminated again when that
        took over).
        """
        s = replace(settings, compute_sigmas=False)
        meas, n = self.meas, self.meas.n_frames
        b = _GraphBuilder(meas, self.stamps, self.camera, s)
        graph = gtsam.NonlinearFactorGraph(self.base.graph)
        _add_motion(b, graph)
        g = replace(self.base, graph=graph, values=self.base.values if start is None else start)
        if s.kernel == GNC:
            result, _, _ = _optimize(g, _lm_params(b), s)
            net = None
        else:
            solved = _gauss_newton(g, b, abs_tol=1e-5)  # gtsam LM's default absolute tolerance
            result, net = solved.values, solved.net
        if net is None:
            order = b.ordered(
                segmented_ordering(n, len(meas.landmark_code), s.motion, s.segment_frames)
            )
            net = graph.linearize(result).eliminateSequential(order)
        log_det: dict[float, float] = {}  # one per distinct time step
        log_det_motion = 0.0
        for i in range(1, n):
            key = round(b.dt(i), 9)
            if key not in log_det:
                log_det[key] = _motion_log_det(b, i)
            log_det_motion += log_det[key]
        evidence = -graph.error(result) - 0.5 * log_det_motion - net.logDeterminant()
        return float(evidence), result


def _motion_log_det(b: _GraphBuilder, i: int) -> float:
    """log det of the covariance of the motion factor between frames i-1 and i."""
    s, dt = b.s, b.dt(i)
    if s.motion == RANDOM_WALK:
        return 3 * np.log(s.rw_sigma_rot**2 * dt) + 3 * np.log(s.rw_sigma_pos**2 * dt)
    graph = gtsam.NonlinearFactorGraph()
    b.motion_factor(i, graph)
    cov = b._pim_cache[round(dt, 9)].preintMeasCov()
    return float(np.linalg.slogdet(cov)[1])


@dataclass(frozen=True)
class MapSolution:
    """Sign centres solved jointly from several flights (rigid landmark model).

    Attributes:
        codes: (K,) the map's codes, sorted.
        centres_world: (K, 3) estimated sign centres [m].
        cov_world: (K, 3, 3) their posterior covariances [m^2].
        world_T_cam: (N, 4, 4) every frame of every flight, flights one after another.
    """

    codes: tuple[str, ...]
    centres_world: np.ndarray
    cov_world: np.ndarray
    world_T_cam: np.ndarray


def solve_map(
    meas: Measurements,
    stamps_s: np.ndarray,
    init_world_T_cam: np.ndarray,
    camera: CameraModel,
    settings: SmootherSettings,
    flight_starts: Sequence[int],
    sign_shift_m: np.ndarray | None = None,
) -> MapSolution:
    """One graph over several flights sharing the signs: one trajectory per flight.

    ``meas`` holds the flights' frames one after another; a flight starts at
    each index of ``flight_starts`` (no motion factor across; its own weak
    first-frame priors). Landmarks are rigid signs with the survey priors;
    ``sign_shift_m`` (K, 3) starts each sign (codes sorted) that far from the
    survey (e.g. triangulated from the flights), the priors stay at the survey.
    """
    s = replace(settings, landmarks=RIGID, kernel=HUBER, compute_sigmas=False)
    b = _GraphBuilder(meas, stamps_s, camera, s)
    g = _batch_graph(b, np.asarray(init_world_T_cam, float), stamps_s, tuple(flight_starts))
    if sign_shift_m is not None:
        sign, centre = b.signs()
        for k, c in enumerate(centre):
            g.values.update(S(k), c + sign_shift_m[k])
        for j, k in enumerate(sign):
            g.values.update(L(j), meas.landmark_world[j] + sign_shift_m[k])
    n = meas.n_frames
    result, _, _ = _optimize(g, _lm_params(b), s)
    codes = tuple(sorted(set(meas.landmark_code)))
    tree = g.graph.linearize(result).eliminateMultifrontal(
        b.ordered(chain_ordering(n, len(meas.landmark_code), s.motion))
    )
    centres = np.array([result.atPoint3(S(k)) for k in range(len(codes))]).reshape(-1, 3)
    cov = np.array([tree.marginalCovariance(S(k)) for k in range(len(codes))]).reshape(-1, 3, 3)
    poses = np.array([result.atPose3(X(i)).matrix() for i in range(n)])
    return MapSolution(codes=codes, centres_world=centres, cov_world=cov, world_T_cam=poses)
