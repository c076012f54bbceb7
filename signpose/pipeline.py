"""The flight pipeline: frames -> observations -> trajectories -> files.

``observe`` runs the frontend over a frame source and streams every frame's
observations to ``observations.jsonl`` (one flushed line per frame; on
Ctrl-C the complete lines are moved into place before the interrupt goes on).
In tracking mode each frame's signs are searched where an earlier frame's
pose (``estimator.perframe.solve_frame_pnp``) projects the map; a frame whose
prediction finds too little falls back to full-frame detection. Frame i is
predicted from frame i - ``track_lag_frames`` (constant velocity), whatever
the number of workers, so the same input gives the same observations.jsonl
byte for byte on any machine. Readings that contradict the frame (a code seen
twice) or the track (another code at a tracked sign's place) are refused and
listed in report.json, as are the readings of codes the map does not have
(``code_not_in_map``): a code read in ``UNKNOWN_CODE_FRAMES`` frames or more
is a warning (a sign missing from the map, or the map of another site).

The flight is cut into chunks of
``chunk_frames`` source positions (``io.sources.read_range``: a seek to the
chunk's start), each observed with its own tracking (a full-frame search at
its start) inline or in one of ``workers`` processes, and the frames are
written in flight order as chunks finish; the chunks do not depend on the
number of workers. Once no chunk is left to start, an idle worker is lent to a
chunk still observed: its worker has every other frame detected there (the
tracker allows ``track_lag_frames`` frames in flight; the main process passes
the image and the plan on), so the last chunks do not leave a core idle, and
the tracker gets the same results in the same order. A process that dies
loses its chunk only: the run goes on and names the frames in ``problems``
(report.json: ``missing_frames``).

``run`` = ``observe`` + ``estimator.estimate.estimate_trajectories`` + the
estimator's files + plots + ``result.mcap`` (+ ``compare`` against a ground
truth), with the time split by stage (the paper's Table 5) in ``report.json``.
The stages overlap where the data allow (``RunSettings.overlap``): the
per-frame methods run on each frame as it is merged in flight order (taking
the tracker's PnP call where its inputs are the chain's), while later chunks
are still observed; the plots are drawn in ``PLOT_PROCESSES`` processes while
the main one writes the other files (unless observing is inline: ``workers``
1 starts no process). The files are the same bytes either way.
A run's folder is one unit through ``run.json``: over an earlier run it is
``running`` from before the first output (a killed or failed run leaves it so:
the folder then mixes two runs), and ``complete`` with the names of this run's
files after the last one, once the files an earlier run wrote and this one did
not are removed; its ``run_id`` is also report.json's ``pipeline.run_id``. A
folder without a ``complete`` run.json holds no finished run.
"""

from __future__ import annotations

import contextlib
import cProfile
import enum
import itertools
import json
import logging
import math
import multiprocessing
import multiprocessing.connection as mp_connection
import os
import resource
import shutil
import signal
import time
import uuid
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import IO, Protocol

import numpy as np
from tqdm import tqdm

from signpose.core.errors import InputError, OutputError
from signpose.core.fileio import atomic_write, ensure_dir
from signpose.estimator.camera import CameraModel, check_image_size, pixel_from_world_point
from signpose.estimator.estimate import (
    EstimateResult,
    EstimatorSettings,
    estimate_trajectories,
    per_frame_methods,
)
from signpose.estimator.fusion import FusionSettings
from signpose.estimator.perframe import FramePose, PerFrameRun, SolvedPnP, solve_frame_pnp
from signpose.estimator.refine import RefinedMap, refine_flight, survey_checked
from signpose.estimator.telemetry import Telemetry
from signpose.estimator.trajectory import Trajectory
from signpose.frontend.detector import (
    HOMOGRAPHY_POINTS,
    DetectionResult,
    Detector,
    PredictedSign,
    SignDetector,
    homography_from_points,
    to_frame_observations,
)
from signpose.frontend.observations import FrameObservations, SignObservation
from signpose.frontend.sign import ALL_CODES
from signpose.io import mcap as mcap_io
from signpose.io.geo_out import (
    RunGeo,
    check_anchor,
    check_geo_request,
    fused_clock_and_outliers,
    fusion_summary,
    run_geo,
    write_run_geo,
)
from signpose.io.groundtruth import check_time_overlap, read_ground_truth
from signpose.io.observations import append_observation
from signpose.io.results import (
    compare_dir,
    metrics_table,
    read_report,
    status_shares,
    write_json,
    write_outputs,
)
from signpose.io.rosbag_write import ResultBag, write_result_bag
from signpose.io.sources import (
    Frame,
    FrameSource,
    PrefetchedFrame,
    RangeRead,
    SourceSpec,
    open_source,
    prefetch,
    read_range,
)
from signpose.io.telemetry import TelemetryRequest, check_overlap, describe, read_requested
from signpose.maps.loader import MapSign, SignMap, bundled_map_path, load_map
from signpose.plots import PLOTS, PlotData, plot_gnss_track, pose_errors
from signpose.report_html import write_run_report
from signpose.sim.flight import SimSettings, simulate

log = logging.getLogger(__name__)

OBSERVATIONS_NAME = "observations.jsonl"
REPORT_NAME = "report.json"
RESULT_MCAP_NAME = "result.mcap"
RESULT_BAG_NAME = "result_bag"
# The stages of the paper's Table 5, plus the ones signpose adds ("per_frame": the
# per-frame methods run as frames are merged, overlapping observing; "estimate" then
# holds the rest of the estimation).
STAGES = ("decode_video", "detect", "decode", "track", "per_frame", "estimate", "outputs")
# Signs nearer the camera than this [m] are not predicted (behind it or at the lens).
MIN_PREDICTED_DEPTH_M = 0.5
# A reading within this many predicted diameters of a tracked sign's predicted
# centre is at that sign's place (signs on a pylon are several diameters apart).
CODE_CHANGED_RADIUS = 0.5
# The prediction (from a pose a frame or two old) is first moved by its median
# offset to the readings of the predicted codes within this many diameters
# [1]; it is trusted when the readings then lie within PREDICTION_AGREES
# diameters of it (median) [1].
MAX_PREDICTION_SHIFT = 8.0
PREDICTION_AGREES = 0.25
# A reading of a code seen twice agrees with the frame when the frame's PnP
# with it reprojects within this [px] RMS (as ``max_track_rms_px``).
DUPLICATE_MAX_RMS_PX = 4.0
# Frames per chunk: tracking starts again with a full-frame search at every chunk's
# start. scripts/bench_observe.py --chunks measured coverage and time for 50 / 100 / 200.
CHUNK_FRAMES = 100
# How worker processes start: "forkserver" (copies of a server process that has
# imported the pipeline and run nothing), not "fork" (a copy of a process that has
# run OpenCV's, OpenBLAS's or gtsam's threads can hang in their locks). Measured on 8
# 960x540 frames, 3 chunks, 3 workers, load 6: spawn 8.4 s (every worker imports
# matplotlib, gtsam, OpenCV: 2.4 s at that load), forkserver 2.1 s after its first start.
WORKER_START = "forkserver"
# Seconds a stopping worker process is given before it is killed.
WORKER_JOIN_S = 2.0
# A worker's exit code after a MemoryError (its chunk is reported lost, out of memory).
WORKER_OUT_OF_MEMORY = 75
# PROFILE_ENV's job number of a lent worker's frame: chunk * this + position.
LENT_JOB_STRIDE = 1_000_000
# Set to a folder, every chunk and plot process writes into it, per job, what it cost
# (``<kind>-<pid>-<job>.json``: CPU before the job, i.e. the process's own start, and
# during it, wall stamps of the job) and, with PROFILE_STATS_ENV also set, the job's
# cProfile statistics (``.prof``, thread CPU as the clock). scripts/bench_pipeline.py sets
# it to count those processes' CPU (the forkserver's children: no rusage of the run counts
# them); nothing is written without it.
PROFILE_ENV = "SIGNPOSE_PROFILE_DIR"
PROFILE_STATS_ENV = "SIGNPOSE_PROFILE_STATS"


# --------------------------------------------------------------------------- settings / results


@dataclass(frozen=True)
class ObserveSettings:
    """How the frontend runs over a flight.

    Attributes:
        codes: codes to look for; None = the map's codes (all codes without a map).
        tracking: search where the running estimate predicts the signs.
        detector_mode: full-frame detection mode of ``SignDetector.detect``
            ("fast" or "paper").
        max_track_rms_px: a pose whose reprojection RMS is above this [px] does
            not feed the tracker.
        prediction_margin: predicted signs whose centre lies this many diameters
            beyond the image border are still searched for; negative keeps only
            signs well inside (a sign cut by the border does not decode, and a
            predicted sign that is not found makes the detector search the
            full frame).
        cascade_path: detector cascade XML; "" = the bundled one.
        prefetch: read and decode the input in a background thread (per chunk).
        workers: processes observing chunks at once (0 = 2 on a multi-core
            machine; 1 = inline). The output does not depend on it.
        track_lag_frames: tracking predicts frame i from the pose of frame
            i - this (and the one before it).
        chunk_frames: source positions per chunk; each chunk starts its
            tracking with a full-frame search. The output depends on it.
        track_refresh_frames: every this many frames after a full-frame
            search, a tracked frame that misses any predicted sign searches
            the full frame again.
    """

    codes: tuple[str, ...] | None = None
    tracking: bool = True
    detector_mode: str = "fast"
    max_track_rms_px: float = 4.0
    prediction_margin: float = -0.6
    cascade_path: str = ""
    prefetch: bool = True
    workers: int = 0
    track_lag_frames: int = 2
    track_refresh_frames: int = 10
    chunk_frames: int = CHUNK_FRAMES


@dataclass(frozen=True)
class ObserveResult:
    """What ``observe`` produced.

    Attributes:
        frames: every processed frame's observations, in order.
        timing_s: stage -> seconds: decode_video (reader thread's time, which
            overlaps the rest), wait_video (time the frame loop waited for it),
            detect, decode, track.
        problems: one line per reading problem (where a truncated input stopped).
        tracked_frames: frames searched only around predictions.
        full_frames: frames searched over the whole image.
        refused: decoded readings left out of ``frames``, in frame order.
        lost: chunks whose process died (their frames are missing).
        solved_pnp: the tracker's PnP call on each frame it posed (with the
            frame of ``frames`` it was made on, this run's map and camera), for
            the estimator to reuse (``estimator.perframe.SolvedPnP``).
        lent_frames: frames detected by an idle worker lent to another one's
            chunk (once no chunk was left to start).
    """

    frames: tuple[FrameObservations, ...]
    timing_s: dict[str, float]
    problems: tuple[str, ...]
    tracked_frames: int
    full_frames: int
    refused: tuple[RefusedObservation, ...] = ()
    lost: tuple[LostChunk, ...] = ()
    solved_pnp: tuple[SolvedPnP, ...] = ()
    lent_frames: int = 0


@dataclass(frozen=True)
class RunSettings:
    """What ``run`` does beyond observing.

    Attributes:
        observe: frontend settings.
        estimator: the estimator's settings.
        with_images: put the images (JPEG) into ``result.mcap``.
        plots: write the PNG plots.
        mcap: write ``result.mcap``.
        ros2_bag: write ``result_bag/``, a rosbag2 folder for ROS 2 tools.
        start_ns: first frame's time of a video or ``fps`` folder [ns since 1970];
            None: the video's own creation_time, else 0.
        gt_offset_s: added to the ground truth's stamps [s] (``--gt-offset``).
        telemetry: the drone's GNSS/IMU to fuse (``--telemetry``), or None.
        geo: the user asked for the WGS84 outputs (``--geo``): a map without
            origin is refused; otherwise they are written when the map has one.
        fusion: the fusion's geometry (``--antenna-offset``, ``--imu-to-camera``)
            and weights; None: the defaults. Its clock is the telemetry's.
        overlap: run the per-frame methods as the frames arrive (while later
            chunks are observed) and, unless observing is inline (``workers``
            1), draw the plots in ``PLOT_PROCESSES`` processes while the main
            one writes the other files; False: one stage after the other. The
            files are the same bytes either way.
    """

    observe: ObserveSettings = field(default_factory=ObserveSettings)
    estimator: EstimatorSettings = field(default_factory=EstimatorSettings)
    with_images: bool = False
    plots: bool = True
    mcap: bool = True
    ros2_bag: bool = False
    start_ns: int | None = None
    gt_offset_s: float = 0.0
    telemetry: TelemetryRequest | None = None
    geo: bool = False
    fusion: FusionSettings | None = None
    overlap: bool = True


@dataclass(frozen=True)
class RunResult:
    """What ``run`` wrote and measured.

    Attributes:
        out_dir: the output folder.
        n_frames: frames processed.
        coverage: method -> fraction of frames with a pose.
        position_rmse_m: method -> RMS position error against the ground truth
            over the frames the method posed [m] (empty without ground truth).
        comparison: ``compare`` summary against the ground truth, or None.
        comparison_table: the printable comparison table, or "".
        timing_s: stage -> seconds, plus ``total``.
        fps: frames per second over the whole run.
        problems: reading problems (truncated input ...).
        files: every file written.
        refused: refusal reason -> decoded readings refused (listed in report.json).
        status: method -> share of each pose status token (ok, weak, bridged, ...).
        notes: what the user should know that is not a problem (telemetry read,
            geodetic outputs skipped).
    """

    out_dir: Path
    n_frames: int
    coverage: dict[str, float]
    position_rmse_m: dict[str, float]
    comparison: dict | None
    comparison_table: str
    timing_s: dict[str, float]
    fps: float
    problems: tuple[str, ...]
    files: tuple[Path, ...]
    refused: dict[str, int] = field(default_factory=dict)
    status: dict[str, dict[str, float]] = field(default_factory=dict)
    notes: tuple[str, ...] = ()


# --------------------------------------------------------------------------- observations stream


class ObservationStream:
    """observations.jsonl written line by line under a temporary name.

    ``finish()`` moves the complete file into place; ``finish_partial()`` does
    the same for what is complete so far (after Ctrl-C); ``abort()`` removes it.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._stack = contextlib.ExitStack()
        self._handle: IO[str] | None = self._stack.enter_context(
            atomic_write(self.path, "w", encoding="utf-8")
        )
        self.lines = 0

    def append(self, obs: FrameObservations) -> None:
        assert self._handle is not None
        append_observation(self._handle, obs)
        self._handle.flush()
        self.lines += 1

    def finish(self) -> Path:
        self._handle = None
        self._stack.close()
        return self.path

    def finish_partial(self) -> Path | None:
        """Keep the complete lines (if any) at ``path``."""
        if self.lines == 0:
            self.abort()
            return None
        return self.finish()

    def abort(self) -> None:
        if self._handle is not None:
            self._handle = None
            self._stack.__exit__(OutputError, OutputError("aborted"), None)


# --------------------------------------------------------------------------- tracking


def predict_signs(
    sign_map: SignMap,
    camera: CameraModel,
    world_T_cam: np.ndarray,
    codes: tuple[str, ...],
    margin: float = 0.5,
    sign_points: dict[str, np.ndarray] | None = None,
) -> list[PredictedSign]:
    """Where the map's signs should appear from ``world_T_cam``.

    Args:
        sign_map: the map.
        camera: the camera.
        world_T_cam: (4, 4) predicted camera pose.
        codes: the codes of interest.
        margin: keep signs up to ``margin`` diameters outside the image.
        sign_points: ``homography_points(sign_map)``, when the caller keeps it
            (a tracker predicts every frame from the same map); None: made here.

    Returns:
        The signs in front of the camera that fall in (or near) the image.
    """
    signs = [s for s in sign_map.signs if s.code in codes]
    if not signs:
        return []
    centers = np.array([s.center_m for s in signs])
    px, depth = pixel_from_world_point(camera, world_T_cam, centers)
    diameters = _image_diameters_px(camera, world_T_cam, centers, [s.diameter_m for s in signs])
    inside = []
    for s, (u, v), z, d_lens in zip(signs, px, depth, diameters, strict=True):
        if not (z > MIN_PREDICTED_DEPTH_M and np.isfinite(u) and np.isfinite(v)):
            continue
        d = float(d_lens) if np.isfinite(d_lens) else camera.fx * s.diameter_m / z
        m = margin * d
        if -m <= u <= camera.width - 1 + m and -m <= v <= camera.height - 1 + m:
            inside.append((s, float(u), float(v), float(d)))
    if sign_points is None:
        sign_points = homography_points([s for s, *_ in inside])
    homographies = _predicted_homographies(
        [s for s, *_ in inside], camera, world_T_cam, sign_points
    )
    return [
        PredictedSign(s.code, (u, v), d, h)
        for (s, u, v, d), h in zip(inside, homographies, strict=True)
    ]


def _image_diameters_px(
    camera: CameraModel, world_T_cam: np.ndarray, centers_m: np.ndarray, diameters_m
) -> np.ndarray:
    """(N,) image diameter [px] of each disc turned toward the camera, through the lens.

    The longer of the images of two diameters across the viewing ray, so a
    wide lens's edge (where fx * D / z overstates an equidistant image up to
    twice at 60 deg off the axis) is sized as the lens draws it. NaN where a
    rim point falls behind the camera or off the lens model.

    Args:
        centers_m: (N, 3) disc centres in the world frame [m].
        diameters_m: (N,) disc diameters [m].
    """
    centers_m = np.asarray(centers_m, dtype=float).reshape(-1, 3)
    ray = centers_m - world_T_cam[:3, 3]
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    x_cam = world_T_cam[:3, 0]
    across = x_cam - (ray @ x_cam)[:, None] * ray
    across /= np.linalg.norm(across, axis=1, keepdims=True)
    other = np.cross(ray, across)
    half = 0.5 * np.asarray(diameters_m, dtype=float)[:, None]
    ends = np.stack(
        [
            centers_m + half * across,
            centers_m - half * across,
            centers_m + half * other,
            centers_m - half * other,
        ],
        axis=1,
    )  # (N, 4, 3)
    px, _ = pixel_from_world_point(camera, world_T_cam, ends.reshape(-1, 3))
    px = px.reshape(-1, 4, 2)
    chords = np.stack(
        [np.linalg.norm(px[:, 0] - px[:, 1], axis=1), np.linalg.norm(px[:, 2] - px[:, 3], axis=1)],
        axis=1,
    )
    return chords.max(axis=1)


def homography_points(signs: Iterable[MapSign]) -> dict[str, np.ndarray]:
    """code -> (4, 3) world points [m] of each oriented sign's detector.HOMOGRAPHY_POINTS."""
    points = {}
    for sign in signs:
        if sign.oriented:
            plane = sign.world_R_sign()[:, :2] * sign.diameter_m
            points[sign.code] = sign.center_m + HOMOGRAPHY_POINTS @ plane.T
    return points


def _predicted_homographies(
    signs: list[MapSign],
    camera: CameraModel,
    world_T_cam: np.ndarray,
    sign_points: dict[str, np.ndarray],
) -> list[np.ndarray | None]:
    """Each sign's predicted image_H_sign (detector.HOMOGRAPHY_POINTS); None for a sign
    without orientation or with a point behind the camera.

    The points of all signs are projected in one call: the same bits as one call per
    sign (each point is projected on its own; checked on the 300 poses of both bench
    flights), and with the points made once per tracker 2.2 -> 0.6 ms per frame.
    """
    oriented = [s for s in signs if s.code in sign_points]
    if not oriented:
        return [None] * len(signs)
    points = np.concatenate([sign_points[s.code] for s in oriented])
    px, depth = pixel_from_world_point(camera, world_T_cam, points)
    n = len(HOMOGRAPHY_POINTS)
    by_code = {}
    for k, sign in enumerate(oriented):
        rows = slice(k * n, (k + 1) * n)
        ok = (depth[rows] > MIN_PREDICTED_DEPTH_M).all()
        by_code[sign.code] = homography_from_points(px[rows]) if ok else None
    return [by_code.get(s.code) for s in signs]


def _extrapolate(prev: np.ndarray, prev2: np.ndarray | None, steps: int = 1) -> np.ndarray:
    """Constant velocity from the last two poses, ``steps`` frames on.

    Translation and rotation: the camera's turn between the two poses is
    applied again ``steps`` times (a turning camera moves every sign across
    the image; with the translation only, the predictions on the simulated
    flights were off by 32 px median, with the rotation too by 1.8 px, from
    true poses two frames back: scripts/bench_frontend.py's tracking).
    """
    if prev2 is None:
        return prev
    out = prev.copy()
    out[:3, 3] = prev[:3, 3] + steps * (prev[:3, 3] - prev2[:3, 3])
    out[:3, :3] = prev[:3, :3] @ _rotation_power(prev2[:3, :3].T @ prev[:3, :3], steps)
    return out


def _rotation_power(rel: np.ndarray, steps: float) -> np.ndarray:
    """(3, 3) rotation ``rel`` applied ``steps`` times (axis-angle scaled, Rodrigues)."""
    cos = float(np.clip((np.trace(rel) - 1.0) / 2.0, -1.0, 1.0))
    angle = math.acos(cos)
    if angle < 1e-9 or angle > math.pi - 1e-6:
        return np.eye(3) if angle < 1e-9 else rel
    axis = np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
    axis /= 2.0 * math.sin(angle)
    a = angle * steps
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(a) * k + (1.0 - math.cos(a)) * (k @ k)


@dataclass(frozen=True)
class FramePlan:
    """How one frame is searched.

    Attributes:
        predictions: the signs expected in view; empty = search the full frame.
        refresh: a missing predicted sign is enough to search the full frame.
    """

    predictions: tuple[PredictedSign, ...] = ()
    refresh: bool = False


class FrameTracker:
    """The running pose that tells the detector where to look, fed frames in order.

    ``plan(i)`` uses only what ``finish`` has been given; the frame loop gives
    it every frame up to ``i - track_lag_frames`` and no more, so the plan of
    a frame (and with it every observation) is the same whatever the number
    of workers and whichever of them finishes first.
    """

    def __init__(
        self,
        sign_map: SignMap | None,
        camera: CameraModel | None,
        codes: tuple[str, ...],
        settings: ObserveSettings,
    ) -> None:
        self.sign_map = sign_map
        self.camera = camera
        self.codes = codes
        self.settings = settings
        self.tracking = settings.tracking and sign_map is not None and camera is not None
        self._sign_points = homography_points(sign_map.signs) if self.tracking else {}
        # (position, world_T_cam) of the last frame finished, when it was posed,
        # and the pose of the frame before it (for the velocity).
        self._last: tuple[int, np.ndarray] | None = None
        self._before_last: np.ndarray | None = None
        # Positions of the last full search finished and of the last refresh
        # planned (frames in flight may be refreshing already).
        self._last_full = self._last_refresh = -settings.track_refresh_frames

    def plan(self, position: int) -> FramePlan:
        """The search of the frame at ``position`` (0 = the first frame of the flight).

        Called once per frame, in order (it remembers the refreshes it plans).
        """
        if not self.tracking or self._last is None:
            return FramePlan()
        last_position, world_T_cam = self._last
        predicted_T = _extrapolate(world_T_cam, self._before_last, position - last_position)
        predictions = predict_signs(
            self.sign_map,
            self.camera,
            predicted_T,
            self.codes,
            self.settings.prediction_margin,
            self._sign_points,
        )
        since = position - max(self._last_full, self._last_refresh)
        refresh = since >= self.settings.track_refresh_frames
        if refresh:
            self._last_refresh = position
        return FramePlan(tuple(predictions), refresh)

    def finish(
        self, position: int, obs: FrameObservations, plan: FramePlan, searched_full: bool
    ) -> tuple[FrameObservations, list[RefusedObservation], TrackedPose | None]:
        """The frame's observations once checked for consistency, and the PnP call that
        moved the pose on (None without tracking)."""
        if searched_full:
            self._last_full = position
        obs, refused = refuse_changed_codes(obs, plan.predictions)
        prior = self._last[1] if self._last is not None and self._last[0] == position - 1 else None
        obs, more = settle_duplicate_codes(obs, self.sign_map, self.camera, prior)
        refused += more
        if not self.tracking:
            return obs, refused, None
        pose = solve_frame_pnp(obs, self.sign_map, self.camera, prior_world_T_cam=prior)
        ok = pose.world_T_cam is not None and (
            not math.isfinite(pose.rms_px) or pose.rms_px <= self.settings.max_track_rms_px
        )
        self._before_last = prior if ok else None
        self._last = (position, pose.world_T_cam) if ok else None
        return obs, refused, TrackedPose(prior, pose)


@dataclass(frozen=True)
class TrackedPose:
    """The tracker's ``solve_frame_pnp`` call on a frame (default settings).

    Attributes:
        prior_world_T_cam: (4, 4) the prior it was given, or None.
        pose: what it returned.
    """

    prior_world_T_cam: np.ndarray | None
    pose: FramePose


# --------------------------------------------------------------------------- consistency


class RefusalReason(enum.StrEnum):
    """Why a decoded reading is not in observations.jsonl; the value is the file token."""

    DUPLICATE_CODE = "duplicate_code"  # its code is seen twice in the frame; not this one
    CODE_CHANGED = "code_changed"  # read at a tracked sign's predicted place, another code
    CODE_NOT_IN_MAP = "code_not_in_map"  # the decoder read a code the map does not have


# Readings that contradict the frame or the track (the others: codes not in the map).
CONTRADICTIONS = (RefusalReason.DUPLICATE_CODE.value, RefusalReason.CODE_CHANGED.value)
# A code the map does not have, read in this many frames, is a warning: a sign
# missing from the map or another site's map. Fewer may be misreadings (the
# decoder's wrong-code rate is about 1 in 2,000 signs; a 1,000-frame flight
# with 5 signs in view may misread 2-3 into unknown codes, spread over codes).
UNKNOWN_CODE_FRAMES = 10


@dataclass(frozen=True)
class RefusedObservation:
    """An observation left out of ``observations.jsonl``, and why.

    Attributes:
        frame: frame index.
        reason: why.
        observation: the refused reading.
        other_px: (u, v) [px] of what it disagreed with: the reading of the
            same code that was kept (duplicate_code; None when none was), or
            the tracked sign's predicted centre (code_changed); None for
            code_not_in_map (whose observation has the centre of the region
            read as its only keypoint, and the region as its box).
        other_code: the tracked sign's code (code_changed), else the refused
            reading's own code.
    """

    frame: int
    reason: RefusalReason
    observation: SignObservation
    other_px: tuple[float, float] | None
    other_code: str

    def to_json(self) -> dict:
        """The report's record (pixels rounded to 0.01 px)."""
        u, v = self.observation.center_px
        return {
            "frame": self.frame,
            "reason": self.reason.value,
            "code": self.observation.code,
            "center_px": [round(u, 2), round(v, 2)],
            "other_code": self.other_code,
            "other_px": None if self.other_px is None else [round(c, 2) for c in self.other_px],
        }


def refusal_counts(refused: Iterable[RefusedObservation]) -> dict[str, int]:
    """Reason token -> number of readings refused for it (every reason, 0 included)."""
    counts = {reason.value: 0 for reason in RefusalReason}
    for r in refused:
        counts[r.reason.value] += 1
    return counts


def unknown_readings(frame: int, result: DetectionResult) -> list[RefusedObservation]:
    """The decoder's readings of codes the map does not have, as refusals."""
    out = []
    for code, (x, y, w, h) in result.unknown:
        centre = (x + w / 2, y + h / 2)
        sign = SignObservation(code, {"center": centre}, bbox_px=(x, y, w, h), score=0.0)
        out.append(RefusedObservation(frame, RefusalReason.CODE_NOT_IN_MAP, sign, None, code))
    return out


def unknown_code_warnings(
    refused: Iterable[RefusedObservation], map_name: str, min_frames: int = UNKNOWN_CODE_FRAMES
) -> list[str]:
    """One line per code the map does not have that was read in ``min_frames`` frames or more."""
    frames: dict[str, set[int]] = {}
    for r in refused:
        if r.reason is RefusalReason.CODE_NOT_IN_MAP:
            frames.setdefault(r.observation.code, set()).add(r.frame)
    return [
        f"code {code} was read in {len(seen)} frames (first frame {min(seen)}) but {map_name} "
        "has no sign of that code: a sign missing from the map (add it with its surveyed "
        "centre to use it) or the map of another site; its readings were left out"
        for code, seen in sorted(frames.items())
        if len(seen) >= min_frames
    ]


def _with_signs(obs: FrameObservations, signs: list[SignObservation]) -> FrameObservations:
    return FrameObservations(obs.frame, obs.stamp_ns, obs.image_size, tuple(signs))


def refuse_changed_codes(
    obs: FrameObservations, predictions: tuple[PredictedSign, ...]
) -> tuple[FrameObservations, list[RefusedObservation]]:
    """Refuse readings at a tracked sign's predicted place that give another code.

    The prediction comes from an earlier pose and may be shifted in the
    image: it is first moved by the median offset between the predicted and
    the read centres of the codes read where they were predicted, and used
    only when that leaves them within ``PREDICTION_AGREES`` diameters. Then a
    reading within ``CODE_CHANGED_RADIUS`` predicted diameters of a predicted
    sign, nearer to it than to any predicted sign of its own code, is that
    sign misread (an occluder took a slot): refused with ``code_changed``,
    never taken for another sign of the map.
    """
    predictions = _aligned(obs, predictions)
    kept, refused = [], []
    for sign in obs.signs:
        near = _nearest_prediction(sign, predictions)
        if near is not None and near.code != sign.code:
            refused.append(
                RefusedObservation(
                    obs.frame, RefusalReason.CODE_CHANGED, sign, near.center_px, near.code
                )
            )
        else:
            kept.append(sign)
    if not refused:
        return obs, []
    return _with_signs(obs, kept), refused


def _aligned(
    obs: FrameObservations, predictions: tuple[PredictedSign, ...]
) -> tuple[PredictedSign, ...]:
    """The predictions moved onto the frame's readings, or () when they do not fit it."""
    by_code = {p.code: p for p in predictions}
    pairs = [
        (np.subtract(s.center_px, by_code[s.code].center_px), by_code[s.code].diameter_px)
        for s in obs.signs
        if s.code in by_code
        and math.dist(s.center_px, by_code[s.code].center_px)
        <= MAX_PREDICTION_SHIFT * by_code[s.code].diameter_px
    ]
    if len(pairs) < 2:
        return ()
    offsets = np.array([d for d, _ in pairs])
    shift = np.median(offsets, axis=0)
    misfit = [np.hypot(*(d - shift)) / diam for d, diam in pairs]
    if float(np.median(misfit)) > PREDICTION_AGREES:
        return ()
    du, dv = float(shift[0]), float(shift[1])
    return tuple(
        PredictedSign(p.code, (p.center_px[0] + du, p.center_px[1] + dv), p.diameter_px)
        for p in predictions
    )


def _nearest_prediction(
    sign: SignObservation, predictions: tuple[PredictedSign, ...]
) -> PredictedSign | None:
    """The predicted sign whose place ``sign`` is at, or None."""
    best, best_d = None, math.inf
    for p in predictions:
        d = math.dist(sign.center_px, p.center_px)
        if d <= CODE_CHANGED_RADIUS * p.diameter_px and d < best_d:
            best, best_d = p, d
    if best is None:
        return None
    own = [math.dist(sign.center_px, p.center_px) for p in predictions if p.code == sign.code]
    return None if own and min(own) <= best_d else best


def settle_duplicate_codes(
    obs: FrameObservations,
    sign_map: SignMap | None,
    camera: CameraModel | None,
    prior_world_T_cam: np.ndarray | None = None,
) -> tuple[FrameObservations, list[RefusedObservation]]:
    """One reading per code: the one that agrees with the other signs' pose.

    A code seen at two places in one frame is one sign and a misreading. For
    each candidate, the frame is posed (``solve_frame_pnp``) with it and the
    frame's signs of other codes; the candidate whose pose reprojects within
    ``max_rms_px`` and best is kept. Without a map and camera, or when no
    candidate agrees, every reading of the code is refused (a wrong code puts
    a landmark metres from its sign; refusing costs one observation).
    """
    by_code: dict[str, list[SignObservation]] = {}
    for sign in obs.signs:
        by_code.setdefault(sign.code, []).append(sign)
    twice = {code: signs for code, signs in by_code.items() if len(signs) > 1}
    if not twice:
        return obs, []
    others = [s for s in obs.signs if s.code not in twice]
    kept, refused = list(others), []
    for code, candidates in twice.items():
        keep = _agreeing(obs, others, candidates, sign_map, camera, prior_world_T_cam)
        if keep is not None:
            kept.append(keep)
        for sign in candidates:
            if sign is not keep:
                other = None if keep is None else keep.center_px
                refused.append(
                    RefusedObservation(obs.frame, RefusalReason.DUPLICATE_CODE, sign, other, code)
                )
    kept.sort(key=lambda s: obs.signs.index(s))
    return _with_signs(obs, kept), refused


def _agreeing(
    obs: FrameObservations,
    others: list[SignObservation],
    candidates: list[SignObservation],
    sign_map: SignMap | None,
    camera: CameraModel | None,
    prior_world_T_cam: np.ndarray | None,
) -> SignObservation | None:
    """The candidate reading that agrees with the other signs' geometry, or None."""
    if sign_map is None or camera is None or not others:
        return None
    best, best_rms = None, DUPLICATE_MAX_RMS_PX
    for sign in candidates:
        trial = _with_signs(obs, [*others, sign])
        pose = solve_frame_pnp(trial, sign_map, camera, prior_world_T_cam=prior_world_T_cam)
        if pose.world_T_cam is None or sign.code not in pose.inlier_codes:
            continue
        if pose.rms_px < best_rms:
            best, best_rms = sign, pose.rms_px
    return best


# --------------------------------------------------------------------------- observe


def _codes_to_find(settings: ObserveSettings, sign_map: SignMap | None) -> tuple[str, ...]:
    if settings.codes is not None:
        return tuple(settings.codes)
    if sign_map is not None:
        return tuple(sign_map.codes)
    return tuple(ALL_CODES)


def _no_prefetch(frames: Iterable[Frame]) -> Iterator[PrefetchedFrame]:
    for frame in frames:
        t0 = time.perf_counter()
        gray = frame.gray()
        yield PrefetchedFrame(frame, gray, time.perf_counter() - t0)


def _close(it: Iterator) -> None:
    close = getattr(it, "close", None)
    if close is not None:
        close()


def make_detector(settings: ObserveSettings) -> Detector:
    """The frontend's detector (``frontend.detector.SignDetector``)."""
    return SignDetector(settings.cascade_path or None)


class DetectorFactory(Protocol):
    """What builds a chunk's detector; a module-level function, so a process can be given it."""

    def __call__(self, settings: ObserveSettings) -> Detector: ...


@dataclass(frozen=True)
class DetectedFrame:
    """One frame's detector result.

    Attributes:
        result: what the detector found.
        tracked: searched around predictions only (no full-frame fallback).
        spent_s: wall time of the detector call [s].
    """

    result: DetectionResult
    tracked: bool
    spent_s: float


def detect_frame(
    det: Detector, gray: np.ndarray, plan: FramePlan, codes: tuple[str, ...], mode: str
) -> DetectedFrame:
    """Run ``det`` on one frame as ``plan`` says."""
    t = time.perf_counter()
    if plan.predictions:
        # The detector searches the full frame itself when a prediction is lost.
        result = det.detect_tracked(gray, plan.predictions, codes, plan.refresh)
        tracked = not result.fell_back
    else:
        result = det.detect(gray, codes, mode)
        tracked = False
    return DetectedFrame(result, tracked, time.perf_counter() - t)


@dataclass
class _Collected:
    """What observing gathers while frames finish (frames in order).

    ``next_index``: the flight index of the next frame (chunk positions are
    renumbered: a frame's index counts the frames read before it).
    """

    stream: ObservationStream | None
    bar: tqdm | None
    timing: dict[str, float] = field(
        default_factory=lambda: dict.fromkeys(
            ("decode_video", "wait_video", "detect", "decode", "track"), 0.0
        )
    )
    frames: list[FrameObservations] = field(default_factory=list)
    refused: list[RefusedObservation] = field(default_factory=list)
    tracked_frames: int = 0
    full_frames: int = 0
    next_index: int = 0
    lost: list[LostChunk] = field(default_factory=list)
    lent_frames: int = 0  # see ObserveResult
    # Instead of all that: frames go here as they are (a worker process's chunk).
    sink: FrameSink | None = None
    # The map and camera the tracker's PnP calls had (copies of these in a worker).
    sign_map: SignMap | None = None
    camera: CameraModel | None = None
    solved: list[SolvedPnP] = field(default_factory=list)
    # Each frame of the flight as it is added, in order, with the tracker's PnP call.
    on_frame: Callable[[FrameObservations, SolvedPnP | None], None] | None = None

    def add(
        self,
        obs: FrameObservations,
        refused: list[RefusedObservation],
        pnp: TrackedPose | None = None,
    ) -> None:
        """The next frame of the flight (its index and its refusals' renumbered)."""
        if self.sink is not None:
            self.sink(obs, refused, pnp)
            return
        if obs.frame != self.next_index:
            obs = replace(obs, frame=self.next_index)
            refused = [replace(r, frame=self.next_index) for r in refused]
            if pnp is not None:  # the index is the only input that differs; it is pose.frame
                pnp = replace(pnp, pose=replace(pnp.pose, frame=self.next_index))
        self.next_index += 1
        if self.stream is not None:
            self.stream.append(obs)
        self.frames.append(obs)
        self.refused += refused
        solved = None
        if pnp is not None and self.sign_map is not None and self.camera is not None:
            solved = SolvedPnP(
                obs, pnp.prior_world_T_cam, None, pnp.pose, self.sign_map, self.camera
            )
            self.solved.append(solved)
        if self.on_frame is not None:
            self.on_frame(obs, solved)
        if self.bar is not None:
            self.bar.update(1)


class FrameSink(Protocol):
    """Where a worker process's frames go as they finish (its pipe to the main process)."""

    def __call__(
        self, obs: FrameObservations, refused: list[RefusedObservation], pnp: TrackedPose | None
    ) -> None: ...


@dataclass(frozen=True)
class _Pending:
    """A frame planned and detected (``detected`` None: another process is detecting it)."""

    position: int
    frame: Frame
    plan: FramePlan
    detected: DetectedFrame | None


def _finish_frame(
    item: _Pending, tracker: FrameTracker, out: _Collected, helper: _HelpedChunk | None = None
) -> None:
    detected = item.detected
    if detected is None:
        assert helper is not None
        detected = helper.answer(item.position, item.plan, tracker.codes)
    t_done = time.perf_counter()
    _add_detector_time(out.timing, detected.result, detected.spent_s)
    if detected.tracked:
        out.tracked_frames += 1
    else:
        out.full_frames += 1
    frame = item.frame
    obs = to_frame_observations(detected.result, frame.index, frame.stamp_ns, frame.image_size)
    obs, refused, pnp = tracker.finish(item.position, obs, item.plan, not detected.tracked)
    refused = refused + unknown_readings(frame.index, detected.result)
    out.timing["track"] += time.perf_counter() - t_done
    out.add(obs, refused, pnp)


def _frames_timed(frame_iter: Iterator[PrefetchedFrame], timing: dict[str, float]):
    """The frames, with the reader's time and the loop's wait for it added to ``timing``."""
    while True:
        t0 = time.perf_counter()
        try:
            item = next(frame_iter)
        except StopIteration:
            return
        # Reading runs ahead in its own thread: its cost is the reader's time,
        # the wall-clock wait for it is "wait_video".
        timing["decode_video"] += item.read_s
        timing["wait_video"] += time.perf_counter() - t0
        yield item


@dataclass(frozen=True)
class ChunkJob:
    """What observing one chunk needs (sent to a worker process).

    Attributes:
        number: the chunk's number (0 = the flight's start).
        spec: how to open the input.
        start: first source position (``io.sources.read_range``).
        stop: the position after the last; None: to the end of the input.
        size: (width, height) [px] of the flight's frames.
        sign_map: the map, or None.
        camera: the camera, or None.
        codes: codes to look for.
        settings: frontend settings.
        make: builds the detector.
    """

    number: int
    spec: SourceSpec
    start: int
    stop: int | None
    size: tuple[int, int]
    sign_map: SignMap | None
    camera: CameraModel | None
    codes: tuple[str, ...]
    settings: ObserveSettings
    make: DetectorFactory


@dataclass(frozen=True)
class ChunkResult:
    """One chunk observed (its frames went to ``out`` or ``send``): what reading met."""

    number: int
    read: RangeRead
    timing_s: dict[str, float]
    tracked_frames: int
    full_frames: int


@dataclass(frozen=True)
class LostChunk:
    """A chunk whose process died: its frames are not in the flight.

    Attributes:
        number: the chunk's number.
        start: its first source position.
        stop: the position after its last (None: to the end of the input).
        reason: what happened (exit code or signal).
    """

    number: int
    start: int
    stop: int | None
    reason: str

    def describe(self, source_name: str) -> str:
        end = "the end" if self.stop is None else str(self.stop - 1)
        return (
            f"{source_name}: frames {self.start} to {end} not observed: the process observing "
            f"them {self.reason}; the other frames were observed"
        )

    def to_json(self) -> dict:
        return {"start": self.start, "stop": self.stop, "reason": self.reason}


def _observe_chunk(
    frames: Iterable[Frame],
    tracker: FrameTracker,
    det: Detector,
    out: _Collected,
    prefetched: bool,
    helper: _HelpedChunk | None = None,
) -> None:
    """One chunk's frame loop: frame i is planned from frame i - ``track_lag_frames``.

    With ``helper`` (a worker process's chunk), a frame is detected in another
    process whenever one is offered and free; the tracker is fed the same plans
    and results in the same order either way (detection is a function of the
    image and the plan only), so the observations are the same bytes.
    On KeyboardInterrupt the frames already detected are finished first.
    """
    s = tracker.settings
    lag = max(1, s.track_lag_frames)
    frame_iter = prefetch(frames) if prefetched else _no_prefetch(frames)
    pending: deque[_Pending] = deque()
    try:
        for position, item in enumerate(_frames_timed(frame_iter, out.timing)):
            plan = tracker.plan(position)
            if helper is not None and helper.free():
                # Frame i waits for nothing but frame i - lag: it is detected elsewhere
                # while this process detects the next one.
                helper.ask(position, item.gray, plan)
                detected = None
            else:
                detected = detect_frame(det, item.gray, plan, tracker.codes, s.detector_mode)
            pending.append(_Pending(position, item.frame, plan, detected))
            while len(pending) >= lag:
                _finish_frame(pending.popleft(), tracker, out, helper)
    finally:
        # Also after Ctrl-C: what is detected is finished, in order.
        while pending:
            _finish_frame(pending.popleft(), tracker, out, helper)
        _close(frame_iter)


# Per worker process: the input and the detector, opened once for all its chunks.
_WORKER_CACHE: dict[tuple, object] = {}


def _cached(key: tuple, build: Callable[[], object]):
    if key not in _WORKER_CACHE:
        _WORKER_CACHE[key] = build()
    return _WORKER_CACHE[key]


def run_chunk(
    job: ChunkJob,
    det: Detector | None = None,
    out: _Collected | None = None,
    source: FrameSource | None = None,
    send: FrameSink | None = None,
    conn=None,
) -> ChunkResult:
    """Observe one chunk with its own tracking (a full-frame search at its start).

    Args:
        job: the chunk.
        det: the detector (default: ``job.make``'s, built once per process).
        out: where the frames go as they finish (inline); None: to ``send``.
        source: the input, open (inline); None: ``job.spec`` opened once per process.
        send: where each frame goes as it finishes, when ``out`` is None (a worker
            process's pipe).
        conn: a worker process's pipe to the main process, through which an idle
            worker may be lent to detect some of the chunk's frames; None: none.

    Returns:
        The ChunkResult.
    """
    if source is None:
        source = _cached(("source", job.spec), job.spec.open)
    if det is None:
        det = _cached(("detector", job.make, job.settings), lambda: job.make(job.settings))
    read = RangeRead(job.start, job.stop, job.size)
    tracker = FrameTracker(job.sign_map, job.camera, job.codes, job.settings)
    helper = None
    if conn is not None:
        helper = _HelpedChunk(conn, job, det)
        send = helper.send
    mine = _Collected(None, None, sink=send) if out is None else out
    before = dict(mine.timing), mine.tracked_frames, mine.full_frames
    _observe_chunk(read_range(source, read), tracker, det, mine, job.settings.prefetch, helper)
    return ChunkResult(
        job.number,
        read,
        {k: v - before[0].get(k, 0.0) for k, v in mine.timing.items()},
        mine.tracked_frames - before[1],
        mine.full_frames - before[2],
    )


@dataclass(frozen=True)
class ChunkFrame:
    """One frame of chunk ``number`` as a worker finished it (``obs.frame`` = position),
    with the tracker's PnP call on it (None without tracking).

    ``waits``: the chunk position of the next frame, when a lent worker was detecting
    it as this one was finished; the frame counts as observed once that one is
    detected (as without a lent worker: should the process die, the frames lost
    are the same; ``ChunkProcesses`` holds it back until then).
    """

    number: int
    obs: FrameObservations
    refused: tuple[RefusedObservation, ...]
    pnp: TrackedPose | None = None
    waits: int | None = None


# The main process tells a worker this when an idle worker may detect frames of its chunk.
HELP_OFFERED = "help offered"


@dataclass(frozen=True)
class DetectRequest:
    """A frame of chunk ``number`` its worker asks an idle worker to detect (through the
    main process), with what the detection needs."""

    number: int
    position: int
    gray: np.ndarray
    plan: FramePlan
    codes: tuple[str, ...]
    settings: ObserveSettings
    make: DetectorFactory


@dataclass(frozen=True)
class DetectAnswer:
    """What the lent worker detected on a DetectRequest's frame; None: no worker was lent,
    or it died on the frame (then the chunk's own worker detects it)."""

    position: int
    detected: DetectedFrame | None


class _HelpedChunk:
    """A worker's side of the idle worker the main process may lend it: one frame at a
    time is asked of it (the tracker allows ``track_lag_frames`` frames in flight).

    A frame finished while the next one is asked is sent marked as waiting for it
    (``ChunkFrame.waits``).
    """

    def __init__(self, conn, job: ChunkJob, det: Detector) -> None:
        self._conn = conn
        self._job = job
        self._det = det
        self._offered = False
        self._asked: tuple[int, np.ndarray] | None = None  # (position, gray)

    def send(
        self, obs: FrameObservations, refused: list[RefusedObservation], pnp: TrackedPose | None
    ) -> None:
        """A finished frame to the main process."""
        waits = None if self._asked is None else self._asked[0]
        self._conn.send(ChunkFrame(self._job.number, obs, tuple(refused), pnp, waits))

    def free(self) -> bool:
        """A worker is lent and has no frame of this chunk yet."""
        if not self._offered and self._conn.poll():
            self._offered = self._conn.recv() == HELP_OFFERED
        return self._offered and self._asked is None

    def ask(self, position: int, gray: np.ndarray, plan: FramePlan) -> None:
        job = self._job
        request = DetectRequest(job.number, position, gray, plan, job.codes, job.settings, job.make)
        self._conn.send(request)
        self._asked = (position, gray)

    def answer(self, position: int, plan: FramePlan, codes: tuple[str, ...]) -> DetectedFrame:
        """The lent worker's detection of the frame asked (detected here if it has none)."""
        assert self._asked is not None and self._asked[0] == position
        gray = self._asked[1]
        reply = self._conn.recv()
        if not isinstance(reply, DetectAnswer) or reply.position != position:
            raise RuntimeError(f"chunk {self._job.number}: unexpected answer {reply!r}")
        detected = reply.detected
        if detected is None:  # no worker lent any more: the rest here
            self._offered = False
            detected = detect_frame(self._det, gray, plan, codes, self._job.settings.detector_mode)
        self._asked = None
        return detected


def _detect_lent(request: DetectRequest) -> DetectAnswer:
    """A lent worker's detection of another worker's frame (None where it raised: the
    frame's own worker then detects it again, and raises what it raises)."""
    key = ("detector", request.make, request.settings)
    try:
        det = _cached(key, lambda: request.make(request.settings))
        mode = request.settings.detector_mode
        detected = detect_frame(det, request.gray, request.plan, request.codes, mode)
    except Exception:  # noqa: BLE001 - raised again where the frame's own worker detects it
        return DetectAnswer(request.position, None)
    return DetectAnswer(request.position, detected)


def _chunk_worker(conn) -> None:
    """A worker process: observe the chunks it is sent until it is sent None; each frame
    is sent as it finishes (so Ctrl-C keeps what the earliest chunk did), then the result.
    Between chunks, lent to another worker, it detects the frames it is sent."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C
    while True:
        try:
            job = conn.recv()
        except (EOFError, OSError):
            return
        if job is None:
            return
        if isinstance(job, str):  # HELP_OFFERED after its chunk ended: nothing to do
            continue
        if isinstance(job, DetectRequest):
            number = job.number * LENT_JOB_STRIDE + job.position
            try:
                conn.send(_profiled("lent", number, _detect_lent, job))
            except MemoryError:
                os._exit(WORKER_OUT_OF_MEMORY)
            continue
        try:
            answer: object = _profiled("chunk", job.number, run_chunk, job, conn=conn)
        except MemoryError:
            os._exit(WORKER_OUT_OF_MEMORY)
        except Exception as exc:  # noqa: BLE001 - raised again in the parent
            answer = exc
        conn.send(answer)


def _cpu_s(who: int = resource.RUSAGE_SELF) -> float:
    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def _profiled(kind: str, number: int, work: Callable[..., object], *args, **kwargs) -> object:
    """``work(*args, **kwargs)``; with ``PROFILE_ENV`` set, what it cost written into that
    folder."""
    folder = os.environ.get(PROFILE_ENV)
    if not folder:
        return work(*args, **kwargs)
    profile = cProfile.Profile(time.thread_time) if os.environ.get(PROFILE_STATS_ENV) else None
    cpu0, start = _cpu_s(), time.time()
    try:
        if profile is None:
            return work(*args, **kwargs)
        return profile.runcall(work, *args, **kwargs)
    finally:
        stem = Path(folder) / f"{kind}-{os.getpid()}-{number}"
        record = {"kind": kind, "job": number, "pid": os.getpid(), "cpu_before_s": cpu0}
        record |= {"cpu_s": _cpu_s() - cpu0, "start": start, "end": time.time()}
        stem.with_suffix(".json").write_text(json.dumps(record) + "\n", encoding="utf-8")
        if profile is not None:
            profile.dump_stats(stem.with_suffix(".prof"))


@dataclass(eq=False)
class _Worker:
    process: object  # multiprocessing.Process
    conn: object  # its end of the pipe
    job: ChunkJob | None = None
    lent: _Worker | None = None  # observing a chunk: the idle worker lent to it
    lent_to: _Worker | None = None  # idle: the worker it is lent to
    asked: DetectRequest | None = None  # lent: the frame it is detecting
    held: ChunkFrame | None = None  # its frame waiting for the next one's detection


class ChunkProcesses:
    """Worker processes that observe chunks; one that dies loses its chunk only.

    The processes are started with ``WORKER_START`` (not fork: a forked copy of
    a process that has run OpenCV's or OpenBLAS's threads may hang). A process
    that dies (killed, out of memory, a library crash) is replaced for the
    chunks still to do.
    """

    def __init__(self, workers: int) -> None:
        self._context = _process_context()
        self._wanted = workers
        self._workers: list[_Worker] = []
        self.lent_frames = 0  # frames detected by a worker lent to another one's chunk

    def _start(self) -> _Worker:
        mine, theirs = self._context.Pipe()
        process = self._context.Process(
            target=_chunk_worker, args=(theirs,), name="signpose-chunk", daemon=True
        )
        process.start()
        theirs.close()
        worker = _Worker(process, mine)
        self._workers.append(worker)
        return worker

    def run(self, jobs: Iterable[ChunkJob]) -> Iterator[ChunkFrame | ChunkResult | LostChunk]:
        """The chunks' frames and results as they finish (chunks in any order).

        Once no chunk is left to start, a worker that is idle is lent to a chunk still
        observed (``_lend``): its worker then has some frames detected by it.
        """
        todo = deque(jobs)
        idle = [self._start() for _ in range(min(self._wanted, len(todo)))]
        busy: list[_Worker] = []
        while todo or busy:
            while todo and idle:
                worker = idle.pop()
                worker.job = todo.popleft()
                worker.conn.send(worker.job)
                busy.append(worker)
            if not todo:
                self._lend(idle, busy)
            lent = [w for w in idle if w.lent_to is not None or w.asked is not None]
            watched = busy + lent
            waited = [w.conn for w in watched] + [w.process.sentinel for w in watched]
            ready = set(mp_connection.wait(waited))
            for worker in [w for w in watched if w.conn in ready or w.process.sentinel in ready]:
                if worker in lent:
                    yield from self._lent_answered(worker, idle)
                    continue
                busy.remove(worker)
                answer = self._answer(worker)
                if isinstance(answer, ChunkFrame | DetectRequest):
                    busy.append(worker)  # the chunk goes on
                    if isinstance(answer, DetectRequest):
                        self._forward(worker, answer)
                        continue
                else:
                    if isinstance(answer, LostChunk):
                        yield from self._settled(worker, idle)
                    self._unlend(worker)
                    if isinstance(answer, LostChunk):
                        self._workers.remove(worker)
                        if todo:
                            idle.append(self._start())
                    else:
                        idle.append(worker)
                if isinstance(answer, BaseException):
                    raise answer
                yield from self._released(worker, answer)

    def _lend(self, idle: list[_Worker], busy: list[_Worker]) -> None:
        """Each idle worker with nothing asked of it lent to the earliest chunk without one."""
        for helper in idle:
            owners = [w for w in busy if w.lent is None]
            if not owners:
                return
            if helper.lent_to is not None or helper.asked is not None:
                continue
            owner = min(owners, key=lambda w: w.job.number if w.job is not None else 0)
            with contextlib.suppress(OSError, ValueError):  # dead: its sentinel tells
                owner.conn.send(HELP_OFFERED)
            owner.lent, helper.lent_to = helper, owner

    def _forward(self, owner: _Worker, request: DetectRequest) -> None:
        """A frame to the worker lent to ``owner``; with none (it died), None back at once."""
        helper = owner.lent
        if helper is not None:
            try:
                helper.conn.send(request)
                helper.asked = request
                return
            except (OSError, ValueError):
                owner.lent = helper.lent_to = None  # dead: its sentinel tells
        with contextlib.suppress(OSError, ValueError):
            owner.conn.send(DetectAnswer(request.position, None))

    def _lent_answered(self, helper: _Worker, idle: list[_Worker]) -> Iterator[ChunkFrame]:
        """A lent worker's answer, to the worker it was lent to (if that one still waits
        for it); a lent worker that died: None to it (it detects the frame itself)."""
        request, owner, reply = helper.asked, helper.lent_to, None
        with contextlib.suppress(EOFError, OSError):
            if helper.conn.poll():
                reply = helper.conn.recv()
        helper.asked = None
        if reply is None:  # it died
            helper.process.join(WORKER_JOIN_S)
            idle.remove(helper)
            self._workers.remove(helper)
            if owner is not None:
                owner.lent = None
            if request is None:
                return
            reply = DetectAnswer(request.position, None)
        if owner is None or request is None or owner.job is None:
            return
        if owner.job.number == request.number:
            with contextlib.suppress(OSError, ValueError):
                owner.conn.send(reply)
            if reply.detected is not None:
                self.lent_frames += 1
                held = owner.held
                if held is not None and held.waits == request.position:
                    owner.held = None
                    yield held

    def _settled(self, owner: _Worker, idle: list[_Worker]) -> Iterator[ChunkFrame]:
        """A dead worker's frame held back: kept when the lent worker detects the frame
        it waits for (as without one: that frame was detected before the one it died on)."""
        helper = owner.lent
        if owner.held is not None and helper is not None and helper.asked is not None:
            mp_connection.wait([helper.conn, helper.process.sentinel])
            yield from self._lent_answered(helper, idle)
        owner.held = None

    @staticmethod
    def _released(
        worker: _Worker, answer: ChunkFrame | ChunkResult | LostChunk
    ) -> Iterator[ChunkFrame | ChunkResult | LostChunk]:
        """``answer`` with the frame held back before it, or held back itself (a frame
        finished while a lent worker detects the next one counts once that one is
        detected: ``ChunkFrame.waits``)."""
        if worker.held is not None:  # a later message: the frame it waited for is detected
            yield worker.held
            worker.held = None
        if isinstance(answer, ChunkFrame) and answer.waits is not None:
            worker.held = answer
            return
        yield answer

    @staticmethod
    def _unlend(owner: _Worker) -> None:
        """A chunk ended: the worker lent to it is free (its answer, if any, is dropped)."""
        if owner.lent is not None:
            owner.lent.lent_to = None
        owner.lent = None

    def _answer(self, worker: _Worker) -> ChunkFrame | ChunkResult | LostChunk | BaseException:
        job = worker.job
        assert job is not None
        try:
            if worker.conn.poll():
                return worker.conn.recv()
        except (EOFError, OSError):
            pass
        worker.process.join(WORKER_JOIN_S)
        code = worker.process.exitcode
        if code == WORKER_OUT_OF_MEMORY:
            how = "ran out of memory"
        elif code is not None and code < 0:
            how = f"was killed by signal {-code} ({signal.Signals(-code).name})"
        else:
            how = f"died (exit code {code})"
        return LostChunk(job.number, job.start, job.stop, how)

    def close(self) -> None:
        """Stop every process (SIGTERM, then SIGKILL after ``WORKER_JOIN_S``)."""
        for worker in self._workers:
            with contextlib.suppress(OSError, ValueError):
                worker.conn.send(None)
                worker.conn.close()
        deadline = time.monotonic() + WORKER_JOIN_S
        for worker in self._workers:
            worker.process.join(max(0.0, deadline - time.monotonic()))
        for worker in self._workers:
            if worker.process.is_alive():
                worker.process.terminate()
                worker.process.join(WORKER_JOIN_S)
            if worker.process.is_alive():
                worker.process.kill()
        self._workers = []

    def stop(self) -> None:
        """After Ctrl-C: end every process at once."""
        for worker in self._workers:
            with contextlib.suppress(OSError, ValueError):
                worker.process.kill()
        for worker in self._workers:
            worker.process.join(WORKER_JOIN_S)
        self._workers = []


def _process_context():
    """The ``WORKER_START`` context (chunk and plot processes)."""
    context = multiprocessing.get_context(WORKER_START)
    if WORKER_START == "forkserver":
        # The server imports the pipeline once; each worker is a copy of it.
        context.set_forkserver_preload([__name__])
    return context


def _worker_count(settings: ObserveSettings) -> int:
    n = settings.workers or min(2, os.cpu_count() or 1)
    # A daemonic process (a pool's worker) may not start processes of its own.
    return 1 if multiprocessing.current_process().daemon else max(1, n)


def _chunk_jobs(
    source: FrameSource,
    size: tuple[int, int],
    sign_map: SignMap | None,
    camera: CameraModel | None,
    codes: tuple[str, ...],
    s: ObserveSettings,
    make: DetectorFactory,
) -> list[ChunkJob]:
    """The flight cut every ``chunk_frames`` positions (the last chunk reads to the end)."""
    n, step = source.range_length or 0, max(1, s.chunk_frames)
    starts = list(range(0, max(n, 1), step))
    return [
        ChunkJob(
            k,
            source.spec,
            start,
            starts[k + 1] if k + 1 < len(starts) else None,
            size,
            sign_map,
            camera,
            codes,
            s,
            make,
        )
        for k, start in enumerate(starts)
    ]


def _first_frame_size(source: FrameSource, camera: CameraModel | None) -> tuple[int, int]:
    """The flight's frame size: its first readable frame's (checked against the camera)."""
    read = RangeRead(0, None)
    frames = read_range(source, read)
    try:
        first = next(frames, None)
    finally:
        frames.close()
    if first is None:
        source.range_problems([read])  # raises the InputError of an unreadable input
        raise InputError(f"{source.path}: no readable frame")
    if camera is not None:
        check_image_size(camera, *first.image_size, str(source.path))
    return first.image_size


def _merge_in_order(
    answers: Iterable[ChunkFrame | ChunkResult | LostChunk],
    out: _Collected,
    reads: dict[int, RangeRead],
) -> None:
    """The workers' frames into ``out`` in flight order: the earliest unfinished chunk's
    as they come, the later chunks' once every chunk before them is done."""
    done: dict[int, ChunkResult | LostChunk] = {}
    early: dict[int, list[ChunkFrame]] = {}
    last_position: dict[int, int] = {}
    following = 0
    for answer in answers:
        if isinstance(answer, ChunkFrame):
            last_position[answer.number] = answer.obs.frame
            if answer.number == following:
                out.add(answer.obs, list(answer.refused), answer.pnp)
            else:
                early.setdefault(answer.number, []).append(answer)
            continue
        done[answer.number] = answer
        while following in done:
            item = done.pop(following)
            if isinstance(item, ChunkResult):
                reads[following] = item.read
                _merge(item, out)
            else:  # the frames it sent before it died are kept
                after = last_position.get(following)
                lost = item if after is None else replace(item, start=after + 1)
                if lost.stop is None or lost.start < lost.stop:
                    _lose(lost, out)
            following += 1
            for frame in early.pop(following, []):
                out.add(frame.obs, list(frame.refused), frame.pnp)


def _merge(result: ChunkResult, out: _Collected) -> None:
    for key, value in result.timing_s.items():
        out.timing[key] += value
    out.tracked_frames += result.tracked_frames
    out.full_frames += result.full_frames


def _lose(lost: LostChunk, out: _Collected) -> None:
    """A chunk's frames are missing: the next chunk's indices still count its positions."""
    out.lost.append(lost)
    if lost.stop is not None:
        out.next_index += lost.stop - lost.start


def _observe_chunks(
    source: FrameSource,
    jobs: list[ChunkJob],
    workers: int,
    det: Detector | None,
    out: _Collected,
) -> list[RangeRead]:
    """Every chunk, in processes or inline; frames streamed in flight order as chunks finish.

    Tried and dropped (issue 14): this process observing the first chunk itself while the
    processes start and observe the rest (a thread taking their frames), so that the
    forkserver's start (importing the pipeline, ~1 s CPU) and the last chunk observed
    alone on one core leave no core idle. Same bytes, but on the 300-frame bench sim flight
    with 2 processes at load ~8 a fresh process per run took 31.4 s mean of 3 against 24.7
    s, 34.4 against 34.3 s within one process, and 1-3 s more CPU: three chunks observed
    at once on 2 cores cost 1.25-1.5x CPU per frame.

    Raises:
        RuntimeError: every chunk's process died (nothing was observed).
    """
    if workers <= 1 or det is not None or len(jobs) == 1:
        if det is None:
            det = jobs[0].make(jobs[0].settings)
        return [run_chunk(job, det, out, source).read for job in jobs]
    reads: dict[int, RangeRead] = {}
    pool = ChunkProcesses(workers)
    try:
        _merge_in_order(pool.run(jobs), out, reads)
    except BaseException:
        pool.stop()
        raise
    pool.close()
    out.lent_frames += pool.lent_frames
    if not reads:
        raise RuntimeError(
            f"{source.path}: every process observing the flight died ({out.lost[0].reason})"
        )
    return [reads[k] for k in sorted(reads)]


def _observe_in_order(
    source: FrameSource,
    sign_map: SignMap | None,
    camera: CameraModel | None,
    codes: tuple[str, ...],
    s: ObserveSettings,
    det: Detector,
    out: _Collected,
) -> None:
    """A source read in order only: the same chunks, counted in frames, inline."""
    frames = iter(source)
    step = max(1, s.chunk_frames)
    while True:
        before = out.next_index
        chunk = itertools.islice(frames, step)
        if before == 0:
            chunk = _size_checked(chunk, camera, str(source.path))
        tracker = FrameTracker(sign_map, camera, codes, s)
        _observe_chunk(chunk, tracker, det, out, s.prefetch)
        if out.next_index - before < step:
            return


def _size_checked(frames: Iterable[Frame], camera: CameraModel | None, name: str):
    for i, frame in enumerate(frames):
        if i == 0 and camera is not None:
            check_image_size(camera, *frame.image_size, name)
        yield frame


def observe(
    source: FrameSource,
    sign_map: SignMap | None,
    camera: CameraModel | None,
    settings: ObserveSettings | None = None,
    progress: bool = True,
    out_path: str | os.PathLike | None = None,
    detector: Detector | None = None,
    detector_factory: DetectorFactory | None = None,
    on_frame: Callable[[FrameObservations, SolvedPnP | None], None] | None = None,
) -> ObserveResult:
    """Detect and decode the signs in every frame of ``source``, in chunks.

    Args:
        source: the frames.
        sign_map: the map (codes to look for and tracking), or None.
        camera: the camera; its size must match the images. Tracking needs it
            and the map.
        settings: frontend settings.
        progress: show a tqdm bar over frames.
        out_path: stream the observations to this JSONL file as they are made.
        detector: one detector for every chunk, inline (tests).
        detector_factory: builds each process's detector (default
            ``make_detector``); a module-level function.
        on_frame: called with each frame of the flight in order, as soon as
            it is (the frames of a chunk once every chunk before it is in),
            and the tracker's PnP call on it (or None), while later chunks
            are still observed.

    Returns:
        The ObserveResult. On KeyboardInterrupt the frames done so far are in
        ``out_path`` (complete lines only) and the interrupt is re-raised.
    """
    s = settings or ObserveSettings()
    codes = _codes_to_find(s, sign_map)
    make = detector_factory or make_detector
    stream = ObservationStream(out_path) if out_path is not None else None
    bar = tqdm(total=source.length, desc="observe", unit="frame", disable=not progress)
    out = _Collected(stream, bar, sign_map=sign_map, camera=camera, on_frame=on_frame)
    try:
        if source.range_length is None or source.spec is None:
            _observe_in_order(source, sign_map, camera, codes, s, detector or make(s), out)
            problems = list(source.problems)
        else:
            size = _first_frame_size(source, camera)
            jobs = _chunk_jobs(source, size, sign_map, camera, codes, s, make)
            reads = _observe_chunks(source, jobs, _worker_count(s), detector, out)
            problems = _chunk_problems(source, reads, out.lost)
    except BaseException as exc:
        bar.close()
        if stream is not None and isinstance(exc, KeyboardInterrupt):
            kept = stream.finish_partial()
            if kept is not None:
                log.info("interrupted: %d complete frames kept in %s", stream.lines, kept)
        elif stream is not None:
            stream.abort()
        raise
    bar.close()
    if stream is not None:
        stream.finish()
    return ObserveResult(
        frames=tuple(out.frames),
        timing_s=out.timing,
        problems=tuple(problems),
        tracked_frames=out.tracked_frames,
        full_frames=out.full_frames,
        refused=tuple(out.refused),
        lost=tuple(out.lost),
        solved_pnp=tuple(out.solved),
        lent_frames=out.lent_frames,
    )


def _chunk_problems(
    source: FrameSource, reads: list[RangeRead], lost: list[LostChunk]
) -> list[str]:
    """The reading problems of the chunks read, then one line per chunk lost."""
    lines = []
    if any(r.good or r.odd for r in reads) or not lost:
        to_end = not any(c.stop is None for c in lost)
        lines = source.range_problems(reads, to_end)
    source.problems = lines + [c.describe(str(source.path)) for c in lost]
    return list(source.problems)


def _add_detector_time(timing: dict[str, float], result: DetectionResult, wall_s: float) -> None:
    """Split the detector's wall time into detect and decode (the detector reports ms)."""
    decode_s = min(float(result.timing.get("decode", 0.0)) / 1e3, wall_s)
    timing["decode"] += decode_s
    timing["detect"] += wall_s - decode_s


# --------------------------------------------------------------------------- run


def _camera_for(source: FrameSource, camera: CameraModel | None) -> CameraModel:
    if camera is not None:
        return camera
    if source.camera is not None:
        return source.camera
    raise InputError(
        f"{source.path}: no camera calibration; pass --camera (ROS camera_info, OpenCV "
        "or Kalibr YAML) or record a CameraCalibration/CameraInfo topic"
    )


def check_codes_seen(
    frames: tuple[FrameObservations, ...],
    sign_map: SignMap,
    where: str,
    refused: Iterable[RefusedObservation] = (),
) -> None:
    """InputError when none of the map's signs was seen in any frame (naming the
    codes that were read, the map's or not)."""
    seen = {o.code for f in frames for o in f.signs}
    if not seen & set(sign_map.codes):
        seen |= {r.observation.code for r in refused}
        extra = f" (the frames show {', '.join(sorted(seen))})" if seen else ""
        raise InputError(
            f"{sign_map.source or 'map'}: none of the map's codes "
            f"({', '.join(sign_map.codes)}) was seen in the {len(frames)} frames of "
            f"{where}{extra}; pass the map of this site"
        )


def _trajectories(
    estimate: EstimateResult,
) -> tuple[dict[str, Trajectory], dict[str, np.ndarray]]:
    """method -> Trajectory (NaN where no pose), method -> (N, 3) sigma [m]."""
    trajs, sigmas = {}, {}
    for name, m in estimate.methods.items():
        T = np.array(m.world_T_cam, dtype=float, copy=True)
        T[~np.asarray(m.valid, bool)] = np.nan
        pos = T[:, :3, 3]
        quat = np.full((len(T), 4), np.nan)
        ok = np.asarray(m.valid, bool)
        if np.any(ok):
            quat[ok] = Trajectory.from_matrices(m.stamps_s[ok], T[ok]).quat_xyzw
        trajs[name] = Trajectory(np.asarray(m.stamps_s, float), pos, quat)
        sig = np.asarray(m.sigma_xyz, float)
        if np.any(np.isfinite(sig)):
            sigmas[name] = sig
    return trajs, sigmas


def _valid_only(traj: Trajectory) -> Trajectory:
    ok = np.all(np.isfinite(traj.world_t_cam), axis=1)
    return Trajectory(traj.stamps_s[ok], traj.world_t_cam[ok], traj.quat_xyzw[ok])


@dataclass
class _RunTelemetry:
    """A run's telemetry (issue 17): what was asked, what was read, notes for the user."""

    request: TelemetryRequest | None
    telemetry: Telemetry | None = None
    notes: list[str] = field(default_factory=list)


def _telemetry_for(s: RunSettings, sign_map: SignMap, flight, source: FrameSource):
    """Read the requested telemetry (before observing: a bad file stops the run at once)."""
    check_geo_request(sign_map, s.geo)
    tel = _RunTelemetry(s.telemetry)
    if s.telemetry is not None:
        start_s = (getattr(source, "start_ns", None) or 0) * 1e-9  # an SRT's time zero
        tel.telemetry = read_requested(s.telemetry, flight.input_path, start_s)
        check_anchor(sign_map, tel.telemetry)
        tel.notes.append(describe(tel.telemetry))
    return replace(flight, telemetry=tel)


def _estimate(
    obs: ObserveResult,
    sign_map: SignMap,
    cam: CameraModel,
    s: RunSettings,
    progress,
    tel,
    per_frame: PerFrameRun | None,
):
    """estimate_trajectories, with the telemetry fused when the run has some; the per-frame
    methods from ``per_frame`` (run while observing), else reusing the tracker's PnP calls."""
    frames = list(obs.frames)
    reuse = {"solved_pnp": obs.solved_pnp, "per_frame_done": per_frame}
    if tel is None or tel.telemetry is None:
        return estimate_trajectories(frames, sign_map, cam, s.estimator, progress, **reuse)
    stamps = np.array([f.stamp_ns for f in frames], float) * 1e-9
    check_overlap(tel.telemetry, stamps, tel.request.clock_offset_s)
    fusion = replace(s.fusion or FusionSettings(), clock_offset_s=tel.request.clock_offset_s)
    return estimate_trajectories(
        frames,
        sign_map,
        cam,
        s.estimator,
        progress,
        telemetry=tel.telemetry,
        fusion=fusion,
        **reuse,
    )


def _run_geo(s: RunSettings, sign_map: SignMap, estimate: EstimateResult, tel) -> RunGeo:
    """The run's WGS84 tracks; the note why there are none goes to the user with telemetry."""
    telemetry = tel.telemetry if tel is not None else None
    gnss, offset, outlier = None, 0.0, None
    if telemetry is not None and telemetry.gnss is not None:
        gnss = telemetry.gnss
        given = tel.request.clock_offset_s
        offset, outlier = fused_clock_and_outliers(estimate.fusion, gnss, given)
        if (f := estimate.fusion) is not None:  # a refused fusion: its note only
            tel.notes.extend(f.notes if f.refused else (fusion_summary(f), *f.notes))
    geo = run_geo(sign_map, estimate.methods, gnss, offset, outlier, required=s.geo)
    if geo.note and telemetry is not None:
        tel.notes.append(f"note: {geo.note}")
    return geo


def _gnss_plot(out: Path, geo: RunGeo, trajs: dict[str, Trajectory]) -> list[tuple]:
    """gnss.png (its plot function and arguments): the fixes beside the georeferenced
    track, when the run has both."""
    if geo.track is None or geo.gnss is None or geo.track.name not in trajs:
        return []
    outlier = np.array([t == "outlier" for t in geo.gnss.status], bool)
    name = geo.track.name
    args = (out / "gnss.png", trajs[name], name, geo.gnss_world_m, geo.gnss.stamps_s, outlier)
    return [(plot_gnss_track, args)]


@dataclass(frozen=True)
class _Flight:
    """One flight's inputs as ``run`` was given them."""

    input_path: str | os.PathLike
    topic: str | None
    fps: float | None
    start_ns: int | None = None
    telemetry: _RunTelemetry | None = None

    def open(self) -> FrameSource:
        return open_source(self.input_path, topic=self.topic, fps=self.fps, start_ns=self.start_ns)


def run(
    input_path: str | os.PathLike,
    sign_map: SignMap,
    out_dir: str | os.PathLike,
    *,
    camera: CameraModel | None = None,
    gt_path: str | os.PathLike | None = None,
    topic: str | None = None,
    fps: float | None = None,
    settings: RunSettings | None = None,
    progress: bool = True,
    detector: Detector | None = None,
    echo: Callable[[str], None] | None = None,
    detector_factory: DetectorFactory | None = None,
) -> RunResult:
    """Observe, estimate and write every output of one flight into ``out_dir``.

    Args:
        input_path: video, image folder or MCAP log.
        sign_map: the site's map.
        out_dir: output folder (created).
        camera: the camera, or None to take it from the MCAP log.
        gt_path: ground truth TUM; when given the methods are compared with it.
        topic: MCAP image topic.
        fps: frame rate of an image folder without a times CSV.
        settings: what to run.
        progress: tqdm bars.
        detector: a detector (tests); default ``make_detector``.
        echo: where to print warnings for the user (e.g. stderr), or None.
        detector_factory: builds each worker process's detector (``observe``).

    Returns:
        The RunResult; ``report.json`` in ``out_dir`` holds the same numbers.
    """
    s = settings or RunSettings()
    t_start = time.perf_counter()
    out = ensure_dir(out_dir)
    flight = _Flight(input_path, topic, fps, s.start_ns)
    gt = read_ground_truth(gt_path, s.gt_offset_s) if gt_path is not None else None
    source = flight.open()
    cam = _camera_for(source, camera)
    flight, begun = _telemetry_for(s, sign_map, flight, source), begin_run(out)
    made = {"detector": detector, "detector_factory": detector_factory}
    obs, per_frame = _observe_run(source, sign_map, cam, s, progress, out, made)
    _warn(echo, obs.problems)
    unknown = _codes_checked(obs, sign_map, str(source.path))
    _check_gt_overlap(obs.frames, source.path, gt, gt_path)
    with _plotters(s) as plotters:  # started now: their start overlaps the estimation
        t0 = time.perf_counter()
        estimate = _estimate(obs, sign_map, cam, s, progress, flight.telemetry, per_frame)
        estimate, refined = _checked_against_survey(obs, sign_map, cam, estimate, unknown)
        timing = {**obs.timing_s, "estimate": time.perf_counter() - t0, **_seconds(per_frame)}
        _warn(echo, estimate.warnings, where=str(source.path))  # a camera file, map that do not fit
        t0 = time.perf_counter()
        trajs, sigmas = _trajectories(estimate)
        made = _RunFiles(out, s, flight, sign_map, cam, obs, estimate, trajs, sigmas, gt, refined)
        files = _write_run_files(made, progress, source.frame_id, plotters)
        comparison, table = _compare(out, gt_path, s.gt_offset_s)  # while the plots are drawn
        files = [out / OBSERVATIONS_NAME, *files.finish(plotters)]
        timing["outputs"] = time.perf_counter() - t0
    timing["total"] = time.perf_counter() - t_start
    n = len(obs.frames)
    result = RunResult(
        out_dir=out,
        n_frames=n,
        coverage={name: float(m.coverage) for name, m in estimate.methods.items()},
        status={name: status_shares(m) for name, m in estimate.methods.items()},
        position_rmse_m=_position_errors(trajs, gt, comparison),
        comparison=comparison,
        comparison_table=table,
        timing_s=timing,
        fps=n / timing["total"] if timing["total"] > 0 else float("nan"),
        problems=tuple(obs.problems),
        files=tuple(files),
        refused=refusal_counts(obs.refused),
        notes=tuple(flight.telemetry.notes),
    )
    section = _pipeline_section(result, source, obs, s) | {"run_id": begun.run_id}
    return _write_reports(out, result, section, begun)


def _codes_checked(obs: ObserveResult, sign_map: SignMap, where: str) -> list[str]:
    """``check_codes_seen``, then the warnings about codes the map does not have
    (``unknown_code_warnings``; told with the estimator's, and in report.json)."""
    check_codes_seen(obs.frames, sign_map, where, obs.refused)
    return unknown_code_warnings(obs.refused, sign_map.source or "the map")


def _checked_against_survey(
    obs: ObserveResult,
    sign_map: SignMap,
    cam: CameraModel,
    estimate: EstimateResult,
    more_warnings: list[str],
) -> tuple[EstimateResult, RefinedMap | None]:
    """``estimate`` with the poses of the frames that see a sign the flight moved far
    from its survey marked suspect (``refine.survey_checked``), and the flight's map;
    ``more_warnings`` added to its warnings (told to the user, in report.json)."""
    refined = refine_flight(list(obs.frames), sign_map, cam, estimate)
    checked = survey_checked(estimate, refined, obs.frames)
    if more_warnings:
        checked = replace(checked, warnings=(*checked.warnings, *more_warnings))
    return checked, refined


def _warn(
    echo: Callable[[str], None] | None, lines: Iterable[str], where: str | None = None
) -> None:
    """Each line to the user as a warning: through ``echo``; without one, when the
    line is about the outputs (``where``: the input it is about), through this
    module's logger, which the CLI prints as ``signpose run: warning: ...``.

    The estimator's warnings (a camera file or map that does not fit the video:
    every pose ``suspect``) were in report.json only on ``signpose run``, whose
    CLI passes no ``echo`` (scripts/eval_setup_faults.py: the sign diameter 10 %
    off, plumb_bob coefficients labelled equidistant, a sign hung 15 deg off,
    exit 0 with nothing on stderr about them). Reading problems (``where`` None)
    stay the caller's: the CLI prints them as its error line.
    """
    for line in lines:
        if echo is not None:
            echo(f"warning: {line}")
        elif where is not None:
            log.warning("%s: %s", where, line)


def _seconds(per_frame: PerFrameRun | None) -> dict[str, float]:
    """The ``per_frame`` stage: the per-frame methods' time while observing (none without)."""
    return {} if per_frame is None else {"per_frame": sum(per_frame.seconds.values())}


def _observe_run(
    source: FrameSource,
    sign_map: SignMap,
    cam: CameraModel,
    s: RunSettings,
    progress: bool,
    out: Path,
    made: dict,
) -> tuple[ObserveResult, PerFrameRun | None]:
    """``observe`` into observations.jsonl; with ``s.overlap`` the per-frame methods run on
    each frame as it arrives (``perframe.PerFrameRun``, reusing the tracker's PnP)."""
    per_frame = None
    if s.overlap:
        methods = per_frame_methods(s.estimator)
        per_frame = PerFrameRun(sign_map, cam, methods, s.estimator.per_frame)
        made = {**made, "on_frame": per_frame.add}
    obs = observe(source, sign_map, cam, s.observe, progress, out / OBSERVATIONS_NAME, **made)
    return obs, per_frame


def _write_reports(out: Path, result: RunResult, section: dict, begun: BegunRun) -> RunResult:
    """report.json's pipeline section, report.html (lists every file), run.json (last)."""
    _add_to_report(out / REPORT_NAME, "pipeline", section)
    if out / REPORT_NAME not in result.files:
        result = replace(result, files=(*result.files, out / REPORT_NAME))
    result = replace(result, files=(*result.files, write_run_report(out)))
    return replace(result, files=(*result.files, finish_run(out, begun, result.files)))


@dataclass(frozen=True)
class _RunFiles:
    """What a run's files are made of."""

    out: Path
    s: RunSettings
    flight: _Flight
    sign_map: SignMap
    camera: CameraModel
    obs: ObserveResult
    estimate: EstimateResult
    trajs: dict[str, Trajectory]
    sigmas: dict[str, np.ndarray]
    gt: Trajectory | None
    refined: RefinedMap | None = None  # the flight's map (``refine_flight``)


@dataclass(frozen=True)
class _Written:
    """A run's files in their order; the plots drawn elsewhere are not in yet."""

    estimator: list[Path]  # the estimator's and the geodetic files
    plots: list[Path]  # empty while other processes draw them
    logs: list[Path]  # result.mcap, result_bag

    def finish(self, plotters: PlotProcesses | None) -> list[Path]:
        """Every file, once ``plotters`` (if any) have drawn theirs."""
        plots = plotters.finish() if plotters is not None else self.plots
        return [*self.estimator, *plots, *self.logs]


def _write_run_files(
    r: _RunFiles,
    progress: bool,
    frame_id: str | None = None,
    plotters: PlotProcesses | None = None,
) -> _Written:
    """The estimator's files, the plots, ``result.mcap`` and the ROS 2 bag, as settings ask.

    With ``plotters`` the plots are only handed to them (drawn while the
    other files are written; ``_Written.finish`` waits for them).
    """
    out, s, obs = r.out, r.s, r.obs
    camera_frame = frame_id or mcap_io.CAMERA_FRAME  # the input's own name, if it has one
    geo = _run_geo(s, r.sign_map, r.estimate, r.flight.telemetry)
    plots = _plot_jobs(r, geo) if s.plots else []
    if plotters is not None:
        plotters.start(plots)
    files = [Path(p) for p in write_outputs(out, r.estimate, r.refined)]
    files += write_run_geo(out, geo)
    drawn = [] if plotters is not None else [p for job in plots for p in _draw(job)]
    logs = []
    if s.mcap:
        images = None
        if s.with_images:
            images = ((f.stamp_ns, f.image) for f in r.flight.open())
        mcap_io.write_result_mcap(
            out / RESULT_MCAP_NAME,
            r.sign_map,
            list(obs.frames),
            {k: _valid_only(v) for k, v in r.trajs.items()},
            r.camera,
            images,
            progress=progress,
            camera_frame=camera_frame,
            geo_tracks=geo.tracks(),
        )
        logs.append(out / RESULT_MCAP_NAME)
    if s.ros2_bag:
        bag = ResultBag(r.sign_map, tuple(obs.frames), r.trajs, r.camera, camera_frame)
        logs.append(write_result_bag(out / RESULT_BAG_NAME, bag))
    return _Written(files, drawn, logs)


# A plot job: plot functions (module level: a process is sent them) and their arguments.
PlotJob = tuple[tuple[Callable[..., Path | None], tuple], ...]


def _plot_jobs(r: _RunFiles, geo: RunGeo) -> list[PlotJob]:
    """The run's plots (``plots.PLOTS``, then gnss.png) in two jobs of about equal time.

    Drawn one after the other, the jobs give the plots in ``write_plots``' order.
    """
    obs, sign_map = r.obs, r.sign_map
    stamps = np.array([f.stamp_ns for f in obs.frames], float) * 1e-9
    map_codes = set(sign_map.codes)
    seen = np.array([sum(o.code in map_codes for o in f.signs) for f in obs.frames])
    statuses = {k: tuple(st.value for st in m.status) for k, m in r.estimate.methods.items()}
    data = PlotData(sign_map, r.trajs, r.sigmas, r.gt, stamps, seen, statuses=statuses)
    drawn = [(draw, (r.out / name, data)) for name, draw in PLOTS]
    drawn += _gnss_plot(r.out, geo, r.trajs)
    # trajectory_3d + views (0.6 + 1.4 s on a 300-frame flight), then the rest (1.0 + 0.7 s).
    return [tuple(drawn[:2]), tuple(drawn[2:])]


def _draw(job: PlotJob) -> list[Path]:
    """Draw a job's plots in order: the files written (a plot with nothing to show has none)."""
    written = [draw(*args) for draw, args in job]
    return [Path(p) for p in written if p is not None]


# Processes that draw a run's plots while the main process writes its other files: the
# plots were 3.8 of the 5.1 s of a 300-frame 1080p run's outputs drawn one after another.
PLOT_PROCESSES = 2


def _plot_worker(conn) -> None:
    """A plot process: draw the job it is sent (None: nothing), send back its files or
    the exception."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent handles Ctrl-C
    try:
        job = conn.recv()
    except (EOFError, OSError):
        return
    if job is None:
        return
    try:
        answer: object = _profiled("plots", len(job), _draw, job)
    except Exception as exc:  # noqa: BLE001 - raised again in the parent
        answer = exc
    conn.send(answer)


class PlotProcesses:
    """Processes that each draw one plot job, started before the jobs exist (their start
    then overlaps the estimation). A job whose process died is drawn in this process."""

    def __init__(self, processes: int) -> None:
        context = _process_context()
        self._workers: list[_Worker] = []
        self._jobs: list[PlotJob | None] = []
        for _ in range(processes):
            mine, theirs = context.Pipe()
            process = context.Process(
                target=_plot_worker, args=(theirs,), name="signpose-plots", daemon=True
            )
            process.start()
            theirs.close()
            self._workers.append(_Worker(process, mine))

    def start(self, jobs: list[PlotJob]) -> None:
        """Hand out the jobs, one per process (the processes without one stop)."""
        if len(jobs) > len(self._workers):
            raise ValueError(f"{len(jobs)} plot jobs for {len(self._workers)} processes")
        self._jobs = [*jobs, *[None] * (len(self._workers) - len(jobs))]
        for worker, job in zip(self._workers, self._jobs, strict=True):
            with contextlib.suppress(OSError, ValueError):  # dead: finish draws its job
                worker.conn.send(job)

    def finish(self) -> list[Path]:
        """The files of every job, in the jobs' order, once all are drawn."""
        files: list[Path] = []
        for worker, job in zip(self._workers, self._jobs, strict=True):
            if job is None:
                continue
            answer: object = None
            with contextlib.suppress(EOFError, OSError):
                answer = worker.conn.recv()
            if answer is None:
                worker.process.join(WORKER_JOIN_S)
                log.warning(
                    "a plot process died (exit code %s); its plots are drawn here",
                    worker.process.exitcode,
                )
                answer = _draw(job)
            if isinstance(answer, BaseException):
                raise answer
            files += answer
        self._jobs = []
        return files

    def close(self, kill: bool = False) -> None:
        """Stop every process (``kill``: at once, after Ctrl-C or an error)."""
        for worker in self._workers:
            with contextlib.suppress(OSError, ValueError):
                if kill:
                    worker.process.kill()
                worker.conn.close()
        for worker in self._workers:
            worker.process.join(WORKER_JOIN_S)
            if worker.process.is_alive():
                worker.process.kill()
                worker.process.join(WORKER_JOIN_S)
        self._workers = []


@contextlib.contextmanager
def _plotters(s: RunSettings) -> Iterator[PlotProcesses | None]:
    """The run's plot processes (None: the plots are drawn in this process)."""
    plotters = None
    # Only where observing may start processes too (not inline, not in a pool's daemonic
    # worker): a script without a __main__ guard runs again in every process started
    # (forkserver), and with --workers 1 it has never needed one.
    if s.overlap and s.plots and _worker_count(s.observe) > 1:
        try:
            plotters = PlotProcesses(PLOT_PROCESSES)
        except OSError as exc:
            log.warning("no plot processes (%s); the plots are drawn here", exc)
    if plotters is None:
        yield None
        return
    try:
        yield plotters
    except BaseException:
        plotters.close(kill=True)
        raise
    plotters.close()


def _pipeline_section(
    result: RunResult, source: FrameSource, obs: ObserveResult, s: RunSettings
) -> dict:
    """The ``pipeline`` section of report.json."""
    n = result.n_frames
    return {
        "input": str(source.path),
        "input_kind": source.kind,
        "frames": n,
        "problems": list(obs.problems),
        **({"notes": list(result.notes)} if result.notes else {}),  # telemetry, clock offset
        "missing_frames": [c.to_json() for c in obs.lost],
        "tracking": {"tracked_frames": obs.tracked_frames, "full_frames": obs.full_frames},
        "refused": {
            "counts": result.refused,
            "observations": [r.to_json() for r in obs.refused],
        },
        "coverage": result.coverage,
        "position_rmse_m": result.position_rmse_m,
        "timing_s": {k: round(v, 4) for k, v in result.timing_s.items()},
        "timing_ms_per_frame": {
            k: round(1000 * v / max(n, 1), 3) for k, v in result.timing_s.items() if k != "total"
        },
        "frames_per_second": round(result.fps, 3),
        "settings": {"observe": asdict(s.observe), "with_images": s.with_images},
    }


def _position_errors(
    trajs: dict[str, Trajectory], gt: Trajectory | None, comparison: dict | None
) -> dict[str, float]:
    """method -> RMS position error [m]: the comparison's ATE where it has one."""
    ate = {
        name: float(metrics["ate_rmse_m"])
        for name, metrics in (comparison or {}).items()
        if isinstance(metrics, dict) and metrics.get("ate_rmse_m") is not None
    }
    rmse = {}
    if gt is not None:
        rmse = {k: ate[k] if k in ate else position_rmse(v, gt) for k, v in trajs.items()}
    rmse.update(ate)  # a name only the comparison has comes last
    return rmse


def position_rmse(traj: Trajectory, gt: Trajectory) -> float:
    """RMS position error [m] of ``traj`` against ``gt`` at the stamps both have (NaN: none)."""
    _, dp, _ = pose_errors(_valid_only(traj), gt)
    return float(np.sqrt(np.mean(dp**2))) if len(dp) else float("nan")


def _compare(out: Path, gt_path, gt_offset_s: float) -> tuple[dict | None, str]:
    """The estimator's comparison (added to report.json): (method -> metrics, table)."""
    if gt_path is None:
        return None, ""
    return compare_dir(out, Path(gt_path), gt_offset_s), metrics_table(out)


def _check_gt_overlap(frames, source_path, gt: Trajectory | None, gt_path) -> None:
    """Before estimating: InputError when the ground truth misses the frames' times."""
    if gt is not None:
        stamps_s = np.array([f.stamp_ns for f in frames], float) * 1e-9
        check_time_overlap(stamps_s, source_path, gt, gt_path)


def _add_to_report(path: Path, key: str, section: dict) -> None:
    """Add ``section`` under ``key`` to the estimator's report.json (its module writes it)."""
    report = read_report(path) if path.exists() else {}
    report[key] = section
    write_json(path, report)


# --------------------------------------------------------------------------- run.json

# run.json names the run a folder holds: written "running" (with what an earlier run left)
# before the first output, "complete" (with this run's files) after the last one.
RUN_MANIFEST_NAME = "run.json"


class RunState(enum.StrEnum):
    """run.json's ``state``: a folder still ``running`` (or killed) holds a mix of two runs."""

    RUNNING = "running"
    COMPLETE = "complete"


@dataclass(frozen=True)
class BegunRun:
    """A run that has marked its folder.

    Attributes:
        run_id: this run's id (also in report.json's ``pipeline`` section).
        earlier_files: names in the folder that earlier runs wrote and this one
            has not replaced yet.
    """

    run_id: str
    earlier_files: tuple[str, ...]


def read_run_manifest(out_dir: str | os.PathLike) -> dict | None:
    """run.json of ``out_dir`` (run_id, state, files, earlier_files); None: absent, unreadable."""
    try:
        manifest = json.loads((Path(out_dir) / RUN_MANIFEST_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return manifest if isinstance(manifest, dict) else None


def _own_names(names) -> set[str]:
    """The plain names in a manifest's list (nothing outside the folder, no hidden file)."""
    if not isinstance(names, list):
        return set()
    return {n for n in names if isinstance(n, str) and n == Path(n).name and n[:1] not in ".~"}


def _write_manifest(out: Path, run_id: str, state: RunState, files, earlier) -> None:
    manifest = {
        "run_id": run_id,
        "state": state.value,
        "files": sorted(files),
        "earlier_files": sorted(earlier),
    }
    with atomic_write(out / RUN_MANIFEST_NAME, "w", encoding="utf-8") as f:
        json.dump(manifest, f, indent=2)
        f.write("\n")


def begin_run(out: Path) -> BegunRun:
    """Mark ``out`` as holding a run in progress, before its first output is written.

    Only over an earlier run's files: without them a folder with no ``complete``
    run.json already says it holds no finished run.
    """
    old = read_run_manifest(out) or {}
    earlier = _own_names(old.get("files")) | _own_names(old.get("earlier_files"))
    earlier.discard(RUN_MANIFEST_NAME)
    begun = BegunRun(uuid.uuid4().hex, tuple(sorted(earlier)))
    if earlier:  # else no earlier run to mix with: a refused first run leaves the folder empty
        _write_manifest(out, begun.run_id, RunState.RUNNING, (), earlier)
    return begun


def finish_run(out: Path, begun: BegunRun, files: Iterable[Path]) -> Path:
    """After the last output: remove what earlier runs left and this one did not rewrite,
    then mark ``out`` complete with this run's files. Returns run.json's path."""
    names = {Path(p).name for p in files if Path(p).parent == out} | {RUN_MANIFEST_NAME}
    for stale in set(begun.earlier_files) - names:
        path = out / stale
        with contextlib.suppress(OSError):
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            elif path.exists() or path.is_symlink():
                path.unlink()
    _write_manifest(out, begun.run_id, RunState.COMPLETE, names, ())
    return out / RUN_MANIFEST_NAME


# --------------------------------------------------------------------------- demo


@dataclass(frozen=True)
class DemoResult:
    """What ``run_demo`` wrote: the simulated flight's folder and the run's result."""

    flight_dir: Path
    run: RunResult


def run_demo(
    out_dir: str | os.PathLike = "demo-out",
    frames: int = 210,
    width: int = 1920,
    height: int = 1080,
    with_images: bool = False,
    progress: bool = True,
    cascade_path: str = "",
) -> DemoResult:
    """Simulate the bundled pylon flight into ``out_dir/flight`` and run everything on it.

    Results (observations, trajectories, comparison, plots, result.mcap) go
    into ``out_dir`` itself. ``cascade_path``: detector cascade XML ("" = bundled).
    """
    out = ensure_dir(out_dir)
    sign_map = load_map(bundled_map_path())
    sim = simulate(
        sign_map,
        out / "flight",
        SimSettings(frames=frames, width=width, height=height).validate(),
        progress=progress,
    )
    result = run(
        sim.frames_path,
        sign_map,
        out,
        camera=sim.camera,
        gt_path=sim.groundtruth_path,
        settings=RunSettings(
            observe=ObserveSettings(cascade_path=cascade_path), with_images=with_images
        ),
        progress=progress,
    )
    return DemoResult(sim.out_dir, result)
