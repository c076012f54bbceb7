"""The motion prior's strength chosen from the flight.

By default the candidate with the highest marginal likelihood (Laplace
approximation, ``smoother.log_evidence``) wins. The alternative, held-out
residuals: every ``holdout_every``-th observed frame loses its observations; the flight
is smoothed with each candidate prior and the held-out keypoints are
projected from the poses the prior interpolates there. The candidate with
the lowest mean whitened squared residual (each capped at ``cap_chi2`` so a
missed outlier cannot decide) wins. The acceleration (or random-walk
position) density is chosen first, then (with a rotation grid) the rotation
density with it.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np
from signpose.estimator.camera import CameraModel
from signpose.estimator.smoother import (
    CONSTANT_VELOCITY,
    HUBER,
    EvidenceGraph,
    Measurements,
    SmootherSettings,
    project,
    smooth_batch,
)

EVIDENCE = "evidence"
HOLDOUT = "holdout"


@dataclass(frozen=True)
class TuningSettings:
    """The grid and the held-out frames.

    Attributes:
        position_grid: candidates for ``cv_sigma_acc`` [m/s^2/sqrt(Hz)]
            (``rw_sigma_pos`` [m/sqrt(s)] with the random-walk prior). Up to
            512: a fast manoeuvre within a few frames (a 12-frame
            climb-hover-depart) needs 64; at 8 the prior outweighed the
            Huber-bounded pixels and the final Tukey solve then dropped every
            observation (smoothed 4.8 m off, PnP exact).
        rotation_grid: candidates for the rotation density [rad/s/sqrt(Hz)];
            empty (the default) keeps the settings' value. Measured on the
            fault scenario (seeds 0, 1) and the three paper-like flights at
            0.3 px: both criteria then chose 0.0125 (a stiffer rotation
            predicts the held-out pixels better) and the position RMSE grew
            on 3 of 5 flights (orbit 0.026 -> 0.082 m), because rotation and
            lateral position trade off in a narrow view.
        criterion: ``"evidence"`` (the Laplace approximation of the marginal
            likelihood, ``smoother.log_evidence``) or ``"holdout"``. Evidence:
            on the same five flights it was never worse than the fixed default
            (position RMSE 0.054 -> 0.046 m climb-hover-depart, 0.076 ->
            0.052 m lawnmower, equal elsewhere); held-out residuals gained
            on four but lost on orbit (0.026 -> 0.042 m).
        holdout_every: every this many observed frames one is held out.
        cap_chi2: whitened squared residuals are capped at this.
        min_frames: with the held-out criterion, flights with fewer observed
            frames keep the default (the evidence needs no held-out frames and
            is used on any flight of at least 3 observed frames).
        max_frames: longer flights are tuned on their middle this many frames
            (each candidate is one batch solve).
    """

    position_grid: tuple[float, ...] = tuple(0.125 * 2.0**k for k in range(13))  # 0.125 .. 512
    rotation_grid: tuple[float, ...] = ()
    criterion: str = EVIDENCE
    holdout_every: int = 5
    cap_chi2: float = 25.0
    min_frames: int = 20
    max_frames: int = 600


@dataclass(frozen=True)
class MotionChoice:
    """What the tuning chose and why.

    Attributes:
        settings: the smoother settings with the chosen prior.
        position: the chosen position density; rotation: the chosen rotation density.
        default_position / default_rotation: the fixed defaults.
        scores: (parameter, value, mean capped held-out chi2) per candidate tried.
        held_out_frames: how many frames were held out.
    """

    settings: SmootherSettings
    position: float
    rotation: float
    default_position: float
    default_rotation: float
    scores: tuple[tuple[str, float, float], ...]
    held_out_frames: int

    def to_dict(self) -> dict:
        d = asdict(self)
        d.pop("settings")
        d["scores"] = [{"parameter": p, "value": v, "score": s} for p, v, s in self.scores]
        # The densities' units are composite (no _m / _s suffix fits): named beside them.
        d["parameters"] = dict(zip(("position", "rotation"), _names(self.settings), strict=True))
        d["units"] = {k: DENSITY_UNITS[name] for k, name in d["parameters"].items()} | {
            "default_position": DENSITY_UNITS[d["parameters"]["position"]]
        }
        d["units"]["default_rotation"] = d["units"]["rotation"]
        return d


# Units of the motion prior's densities (estimator.smoother.SmootherSettings).
DENSITY_UNITS = {
    "rw_sigma_pos": "m/sqrt(s)",
    "rw_sigma_rot": "rad/sqrt(s)",
    "cv_sigma_acc": "m/s^2/sqrt(Hz)",
    "cv_sigma_rot": "rad/s/sqrt(Hz)",
}


def _names(s: SmootherSettings) -> tuple[str, str]:
    if s.motion == CONSTANT_VELOCITY:
        return "cv_sigma_acc", "cv_sigma_rot"
    return "rw_sigma_pos", "rw_sigma_rot"


def _held_out_score(
    meas: Measurements,
    held: np.ndarray,
    stamps_s: np.ndarray,
    init: list[np.ndarray],
    camera: CameraModel,
    s: SmootherSettings,
    default: np.ndarray,
    cap: float,
) -> float:
    """Mean capped squared residual of the held-out measurements, whitened as the
    projection factors whiten them (``Measurements.whitened``)."""
    train = meas.subset(~held)
    r = smooth_batch(train, stamps_s, init, camera, s, default)
    pred = project(camera, r.world_T_cam[meas.frame[held]], r.landmarks_world[meas.landmark[held]])
    chi2 = np.sum(meas.whitened(pred - meas.px[held], held) ** 2, axis=1)
    return float(np.mean(np.minimum(chi2, cap)))


def _window(
    meas: Measurements, stamps_s: np.ndarray, init: np.ndarray, max_frames: int
) -> tuple[Measurements, np.ndarray, np.ndarray]:
    """The middle ``max_frames`` frames of a longer flight (frames renumbered from 0)."""
    n = meas.n_frames
    if n <= max_frames:
        return meas, stamps_s, init
    a = (n - max_frames) // 2
    keep = (meas.frame >= a) & (meas.frame < a + max_frames)
    window = replace(meas.subset(keep), frame=meas.frame[keep] - a, n_frames=max_frames)
    return window, stamps_s[a : a + max_frames], init[a : a + max_frames]


def _evidence_score(graph, trial: SmootherSettings, start):
    """(-log evidence of ``trial``, the solution to start the next candidate from).

    A solve from the previous candidate's solution whose system comes out
    indeterminate (gtsam raises) is done again from the initial poses; a
    candidate indeterminate from there too scores +inf (never chosen).
    """
    for begin in (start, None) if start is not None else (None,):
        try:
            evidence, solution = graph.evidence(trial, begin)
            return -evidence, solution
        except RuntimeError:
            continue
    return math.inf, start


def tune_motion_prior(
    meas: Measurements,
    stamps_s: np.ndarray,
    init_world_T_cam: np.ndarray,
    camera: CameraModel,
    settings: SmootherSettings,
    default_world_T_cam: np.ndarray,
    tuning: TuningSettings,
) -> MotionChoice:
    """The motion prior that best predicts held-out frames (see the module docstring).

    Args:
        meas: the measurements (outliers already removed).
        stamps_s: (N,) frame times [s].
        init_world_T_cam: (N, 4, 4) a good initial trajectory (e.g. a first solve).
        camera: the camera.
        settings: the smoother settings; only the motion densities change.
        default_world_T_cam: pose for frames without any initial pose.
        tuning: grid and hold-out.
    """
    meas, stamps_s, init_world_T_cam = _window(meas, stamps_s, init_world_T_cam, tuning.max_frames)
    pos_name, rot_name = _names(settings)
    default_pos, default_rot = getattr(settings, pos_name), getattr(settings, rot_name)
    observed = np.unique(meas.frame)
    base = replace(settings, kernel=HUBER, compute_sigmas=False)
    too_short = tuning.min_frames if tuning.criterion == HOLDOUT else 3
    if len(observed) < too_short:
        return MotionChoice(settings, default_pos, default_rot, default_pos, default_rot, (), 0)
    held_frames = observed[tuning.holdout_every // 2 :: tuning.holdout_every]
    held = np.isin(meas.frame, held_frames)
    init = list(init_world_T_cam)
    scores: list[tuple[str, float, float]] = []
    if tuning.criterion == EVIDENCE:  # the factors but the motion prior's, built once
        graph = EvidenceGraph(meas, stamps_s, init_world_T_cam, camera, base)

    def best_of(name: str, grid: tuple[float, ...], s: SmootherSettings) -> float:
        tried = []
        start = None  # each candidate's solve starts from the previous one's solution
        for value in grid:
            trial = replace(s, **{name: float(value)})
            if tuning.criterion == EVIDENCE:
                score, start = _evidence_score(graph, trial, start)
            else:
                score = _held_out_score(
                    meas, held, stamps_s, init, camera, trial, default_world_T_cam, tuning.cap_chi2
                )
            tried.append((score, float(value)))
            scores.append((name, float(value), score))
        best = min(tried)
        return best[1] if math.isfinite(best[0]) else float(getattr(s, name))

    pos = best_of(pos_name, tuning.position_grid, base)
    rot = default_rot
    if tuning.rotation_grid:
        rot = best_of(rot_name, tuning.rotation_grid, replace(base, **{pos_name: pos}))
    chosen = replace(settings, **{pos_name: pos, rot_name: rot})
    return MotionChoice(
        settings=chosen,
        position=pos,
        rotation=rot,
        default_position=default_pos,
        default_rotation=default_rot,
        scores=tuple(scores),
        held_out_frames=len(held_frames),
    )
