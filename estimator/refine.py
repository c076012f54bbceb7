"""A refined map from several flights of one site (the way TagSLAM and MarkerMapper build maps).

Each flight is first estimated on its own (outliers removed as in
``estimate_trajectories``); the keypoints that fit its smoothed trajectory
then go into one graph: one trajectory per flight, the signs shared as rigid
bodies with the survey priors (``smoother.solve_map``). Each sign's
estimated centre comes with its posterior sigma, the number of frames that
saw it and how far it moved against its survey sigma: a sign moved by more
than ``moved_sigmas`` may have been re-hung. Orientations are the map's (not
estimated).

World frame: the map's; centres [m].
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from signpose.estimator.camera import CameraModel
from signpose.estimator.estimate import EstimateResult, EstimatorSettings, estimate_trajectories
from signpose.estimator.noise_scale import scaled_frames
from signpose.estimator.projection import pixels_and_jacobians
from signpose.estimator.smoother import (
    Measurements,
    collect_measurements,
    solve_map,
)
from signpose.estimator.status import PoseStatus
from signpose.frontend.observations import FrameObservations
from signpose.maps.loader import SignMap

from signpose.core.errors import InputError

# A sign whose centre moved by more than this many survey sigmas is named.
MOVED_SIGMAS = 3.0
# A sign the flight moves further than this is not where the map says, or the camera
# file does not fit the video there: chi with 3 degrees of freedom at a 1 % family-wise
# rate over a 10-sign map (0.001 per sign: sqrt(16.27)); the poses of the frames that
# see it rest on it and are marked ``suspect`` (``survey_checked``). Correct set-ups:
# at most 2.5 sigmas over 7 flights (scripts/eval_flight.py's 5, eval_setup_faults.py's 2).
SUSPECT_MOVED_SIGMAS = 4.03
# A sign's shift is fitted from at least this many keypoint observations, in
# this many Gauss-Newton steps (the problem is nearly linear in the shift).
SHIFT_MIN_MEASUREMENTS = 6
SHIFT_ITERATIONS = 6

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RefinedSign:
    """One sign of the refined map.

    Attributes:
        code: the sign's code.
        center_m: (3,) refined centre, world frame [m].
        survey_center_m: (3,) the survey's centre [m].
        sigma_m: worst-axis posterior sigma of the centre [m].
        frames_seen: frames (over all flights) whose inliers include the sign.
        moved_m: distance from the survey [m]; moved_sigmas: in survey sigmas.
    """

    code: str
    center_m: np.ndarray
    survey_center_m: np.ndarray
    sigma_m: float
    frames_seen: int
    moved_m: float
    moved_sigmas: float

    def to_dict(self) -> dict:
        return {
            "code": self.code,
            "center_m": [float(x) for x in self.center_m],
            "survey_center_m": [float(x) for x in self.survey_center_m],
            "sigma_m": self.sigma_m,
            "frames_seen": self.frames_seen,
            "moved_m": self.moved_m,
            "moved_sigmas": self.moved_sigmas,
        }


@dataclass(frozen=True)
class RefinedMap:
    """The refined map and what changed.

    Attributes:
        sign_map: the map with refined centres and posterior sigma_m (signs
            never seen keep their survey).
        signs: per sign, as listed in the map.
        moved: codes of the signs that moved by more than ``MOVED_SIGMAS``.
    """

    sign_map: SignMap
    signs: tuple[RefinedSign, ...]
    moved: tuple[str, ...]


def _sign_shifts(
    meas: Measurements, world_T_cam: np.ndarray, camera: CameraModel, k: float
) -> tuple[np.ndarray, np.ndarray]:
    """Each sign moved rigidly to fit its observations from the fixed trajectory.

    Gauss-Newton on the sign's translation with Tukey-style inlier selection
    (a re-hung sign's observations are all outliers against the survey, so
    they are tested against the sign where the flight sees it).

    Returns:
        ((K, 3) shift of each sign, codes sorted [m], (M,) inlier mask).
    """
    codes = sorted(set(meas.landmark_code))
    lm_sign = np.array([codes.index(c) for c in meas.landmark_code])[meas.landmark]
    shifts = np.zeros((len(codes), 3))
    inlier = np.zeros(len(meas.frame), bool)
    for s in range(len(codes)):
        ids = np.nonzero(lm_sign == s)[0]
        if len(ids) < SHIFT_MIN_MEASUREMENTS:
            continue
        shift, ok = _fit_shift(meas, ids, world_T_cam, camera, k)
        shifts[s], inlier[ids] = shift, ok
    return shifts, inlier


def _fit_shift(
    meas: Measurements, ids: np.ndarray, world_T_cam: np.ndarray, camera: CameraModel, k: float
) -> tuple[np.ndarray, np.ndarray]:
    """(3,) translation of one sign and (len(ids),) inliers; the median residual gates first."""
    shift = np.zeros(3)
    ok = np.ones(len(ids), bool)
    T = world_T_cam[meas.frame[ids]]
    sig = meas.sigma_px[ids, None]
    norm = np.zeros(len(ids))
    for _ in range(SHIFT_ITERATIONS):
        world = meas.landmark_world[meas.landmark[ids]] + shift
        uv, _, d_point = pixels_and_jacobians(camera, T, world)
        J = d_point / sig[:, :, None]  # d(uv)/d(world point), whitened
        r = (meas.px[ids] - uv) / sig
        norm = np.linalg.norm(r, axis=1)
        ok = norm < max(k, 3.0 * float(np.median(norm)))
        if ok.sum() < SHIFT_MIN_MEASUREMENTS:
            break
        step = np.linalg.lstsq(J[ok].reshape(-1, 3), r[ok].reshape(-1), rcond=None)[0]
        shift = shift + step
    return shift, ok & (norm < k)


def _joined(parts: list[Measurements]) -> tuple[Measurements, list[int]]:
    """The flights' measurements one after another (frames renumbered) and each start."""
    starts, offset = [], 0
    for m in parts:
        starts.append(offset)
        offset += m.n_frames
    cat = np.concatenate
    joined = replace(
        parts[0],
        frame=cat([m.frame + a for m, a in zip(parts, starts, strict=True)]),
        landmark=cat([m.landmark for m in parts]),
        px=cat([m.px for m in parts]).reshape(-1, 2),
        sigma_px=cat([m.sigma_px for m in parts]),
        sign_index=cat([m.sign_index for m in parts]),
        sigma_uv_px=cat([m.axis_sigmas() for m in parts]).reshape(-1, 2),
        cov_uv_px=(
            None
            if all(m.cov_uv_px is None for m in parts)
            else cat([m.pixel_cov() for m in parts]).reshape(-1, 2, 2)
        ),
        n_frames=offset,
    )
    return joined, starts


def check_flights_share_signs(flights: Sequence[Sequence[FrameObservations]], names) -> None:
    """InputError when two flights share no code (flights of different sites)."""
    seen = [{o.code for f in frames for o in f.signs} for frames in flights]
    for k in range(1, len(seen)):
        if not seen[k] & seen[0]:
            raise InputError(
                f"{names[k]}: shares no code with {names[0]}; refine-map needs flights of one site"
            )


def refine_map(
    flights: Sequence[Sequence[FrameObservations]],
    sign_map: SignMap,
    camera: CameraModel,
    settings: EstimatorSettings | None = None,
) -> RefinedMap:
    """Solve the flights jointly for the sign centres (see the module docstring)."""
    s = settings or EstimatorSettings()
    s = replace(s, methods=("smoothed",), smoother=replace(s.smoother, compute_sigmas=False))
    poses = [
        estimate_trajectories(frames, sign_map, camera, s, progress=False)
        .methods["smoothed"]
        .world_T_cam
        for frames in flights
    ]
    try:
        return _solve_flights(flights, poses, sign_map, camera, s)
    except RuntimeError as e:
        if "ndetermina" not in str(e):  # gtsam's IndeterminantLinearSystemException
            raise
        raise InputError(
            f"{sign_map.source or 'the map'}: the {len(flights)} flight(s) do not constrain "
            "the sign positions (the joint solve is indeterminate): too few of their "
            "observations agree with the map; check the survey (a sign far from where the "
            "map puts it, two codes swapped) and the camera file"
        ) from None


def refine_flight(
    frames: Sequence[FrameObservations],
    sign_map: SignMap,
    camera: CameraModel,
    result: EstimateResult,
) -> RefinedMap | None:
    """The refined map from one estimated flight (``map_refined.yaml`` beside its trajectories).

    Starts from the flight's smoothed trajectory (no second robust solve) and
    solves it with the signs as in ``refine_map``. None without a smoothed
    trajectory, or when the flight cannot move the signs (too few views: the
    linear system is indeterminate; a warning says so).

    Args:
        frames: the observations ``result`` was estimated from.
        sign_map: the survey; camera: the camera.
        result: ``estimate_trajectories``'s result for ``frames``.
    """
    smoothed = result.methods.get("smoothed")
    if smoothed is None or not np.any(smoothed.valid):
        return None
    s = result.settings
    if result.motion is not None:  # the motion prior chosen from the flight
        s = replace(s, smoother=result.motion.settings)
    frames = scaled_frames(frames, result.pixel_noise_scale)  # the sigmas the smoother had
    try:
        return _solve_flights([frames], [smoothed.world_T_cam], sign_map, camera, s)
    except RuntimeError as e:
        # gtsam's IndeterminantLinearSystemException: too few views to move the signs
        # (a short flight, one sign per frame). The trajectory stands; the map stays.
        if "ndetermina" not in str(e):
            raise
        log.warning(
            "map_refined.yaml not written: the flight's %d frames do not constrain the "
            "sign positions (the linear system is indeterminate)",
            len(frames),
        )
        return None


def _solve_flights(
    flights: Sequence[Sequence[FrameObservations]],
    poses: Sequence[np.ndarray],
    sign_map: SignMap,
    camera: CameraModel,
    s: EstimatorSettings,
) -> RefinedMap:
    """The joint solve of flights whose (N, 4, 4) smoothed trajectories are ``poses``."""
    parts, stamps = [], []
    for frames, world_T_cam in zip(flights, poses, strict=True):
        meas = collect_measurements(frames, sign_map, camera)
        _, keep = _sign_shifts(meas, world_T_cam, camera, s.smoother.tukey_k)
        parts.append(meas.subset(keep))
        stamps.append(np.array([f.stamp_ns for f in frames], dtype=np.float64) * 1e-9)
    joined, starts = _joined(parts)
    all_poses = np.concatenate(poses)
    shifts, _ = _sign_shifts(joined, all_poses, camera, s.smoother.tukey_k)
    sol = solve_map(joined, np.concatenate(stamps), all_poses, camera, s.smoother, starts, shifts)
    return _refined(sign_map, joined, sol.codes, sol.centres_world, sol.cov_world)


def _refined(
    sign_map: SignMap, meas: Measurements, codes, centres: np.ndarray, cov: np.ndarray
) -> RefinedMap:
    lm_code = np.array(meas.landmark_code)[meas.landmark]
    out, signs, moved = [], [], []
    for sign in sign_map.signs:
        k = codes.index(sign.code)
        frames_seen = len(np.unique(meas.frame[lm_code == sign.code]))
        centre = centres[k] if frames_seen else sign.center_m
        sigma = float(np.sqrt(np.max(np.diag(cov[k])))) if frames_seen else sign.sigma_m
        dist = float(np.linalg.norm(centre - sign.center_m))
        info = RefinedSign(
            code=sign.code,
            center_m=np.asarray(centre, float),
            survey_center_m=sign.center_m,
            sigma_m=sigma,
            frames_seen=frames_seen,
            moved_m=dist,
            moved_sigmas=dist / sign.sigma_m,
        )
        signs.append(info)
        if info.moved_sigmas > MOVED_SIGMAS:
            moved.append(sign.code)
        out.append(replace(sign, center_m=info.center_m, sigma_m=sigma))
    return RefinedMap(
        sign_map=replace(sign_map, signs=tuple(out)), signs=tuple(signs), moved=tuple(moved)
    )


def survey_checked(
    result: EstimateResult, refined: RefinedMap | None, frames: Sequence[FrameObservations]
) -> EstimateResult:
    """``result`` with every ``ok`` / ``weak`` pose of a frame that sees a sign the flight
    moved by more than ``SUSPECT_MOVED_SIGMAS`` survey sigmas marked ``suspect`` (every
    method), and a warning naming the signs; else ``result`` itself.

    A sign the flight puts decimetres from its survey (a survey slip, two records
    mixed up, a wrong camera file) pulls the poses that see it by as much while
    their sigmas stay those of a 1 cm survey: a sign 0.2 m off left every smoothed
    pose ``ok`` and beyond 3 sigma (scripts/eval_setup_faults.py ``sign_0.2m``).

    Args:
        result: ``estimate_trajectories``'s result for ``frames``.
        refined: ``refine_flight``'s map from the same flight, or None (no check).
        frames: the observations, in ``result``'s frame order.
    """
    if refined is None:
        return result
    far = sorted(
        (s for s in refined.signs if s.moved_sigmas > SUSPECT_MOVED_SIGMAS),
        key=lambda s: -s.moved_sigmas,
    )
    if not far:
        return result
    codes = {s.code for s in far}
    sees = [any(o.code in codes for o in f.signs) for f in frames]
    trusted = (PoseStatus.OK, PoseStatus.WEAK)
    methods = {
        name: replace(
            m,
            status=tuple(
                PoseStatus.SUSPECT if st in trusted and seen else st
                for st, seen in zip(m.status, sees, strict=True)
            ),
        )
        for name, m in result.methods.items()
    }
    named = ", ".join(f"{s.code} by {s.moved_m:.2f} m ({s.moved_sigmas:.0f} sigmas)" for s in far)
    warning = (
        f"the flight puts sign(s) {named} from the map (more than {SUSPECT_MOVED_SIGMAS:g} "
        "survey sigmas): the map or the camera file does not fit this video there; the poses "
        f"of the {sum(sees)} frames that see them are marked suspect (map_refined.json)"
    )
    return replace(result, methods=methods, warnings=(*result.warnings, warning))
