"""The flight pipeline: frames -> observations -> trajectories -> files.

``observe`` runs the frontend over a frame source and streams every frame's
observations to ``observations.jsonl`` (one flushed line per frame; on
Ctrl-C the complete lines are moved into place before the interrupt goes on).
In tracking mode each frame's signs are searched where the previous frame's
pose (``estimator.perframe.solve_frame_pnp``) projects the map; a frame whose
prediction finds too little falls back to full-frame detection.

``run`` = ``observe`` + ``estimator.estimate.estimate_trajectories`` + the
estimator's files + plots + ``result.mcap`` (+ ``compare`` against a ground
truth), with the time split by stage (the paper's Table 5) in ``report.json``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np
from tqdm import tqdm

from signpose.core.errors import InputError, OutputError
from signpose.core.fileio import atomic_write, ensure_dir
from signpose.estimator.camera import CameraModel, check_image_size, pixel_from_world_point
from signpose.frontend.observations import FrameObservations
from signpose.io.observations import append_observation
from signpose.io.sources import FrameSource, open_source, prefetch
from signpose.maps.loader import SignMap

log = logging.getLogger(__name__)

OBSERVATIONS_NAME = "observations.jsonl"
REPORT_NAME = "report.json"
RESULT_MCAP_NAME = "result.mcap"
# The stages of the paper's Table 5, plus the ones signpose adds.
STAGES = ("decode_video", "detect", "decode", "track", "estimate", "outputs")


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
        prefetch: read and decode the input in a background thread.
        workers: frames detected at once, each in its own thread with its own
            detector (0 = 2 on a multi-core machine). With more than one,
            tracking predicts frame i from the pose of frame i - workers.
    """

    codes: tuple[str, ...] | None = None
    tracking: bool = True
    detector_mode: str = "fast"
    max_track_rms_px: float = 4.0
    prediction_margin: float = -0.6
    cascade_path: str = ""
    prefetch: bool = True
    workers: int = 0


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
    """

    frames: tuple[FrameObservations, ...]
    timing_s: dict[str, float]
    problems: tuple[str, ...]
    tracked_frames: int
    full_frames: int


@dataclass(frozen=True)
class RunSettings:
    """What ``run`` does beyond observing.

    Attributes:
        observe: frontend settings.
        estimator: ``estimator.estimate.EstimatorSettings`` or None (defaults).
        with_images: put the images (JPEG) into ``result.mcap``.
        plots: write the PNG plots.
        mcap: write ``result.mcap``.
    """

    observe: ObserveSettings = field(default_factory=ObserveSettings)
    estimator: Any = None
    with_images: bool = False
    plots: bool = True
    mcap: bool = True


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
) -> list[tuple[str, tuple[float, float], float]]:
    """Where the map's signs should appear from ``world_T_cam``.

    Args:
        sign_map: the map.
        camera: the camera.
        world_T_cam: (4, 4) predicted camera pose.
        codes: the codes of interest.
        margin: keep signs up to ``margin`` diameters outside the image.

    Returns:
        [(code, (u, v) centre [px], diameter [px])] for the signs in front of
        the camera that fall in (or near) the image.
    """
    signs = [s for s in sign_map.signs if s.code in codes]
    if not signs:
        return []
    centers = np.array([s.center_m for s in signs])
    px, depth = pixel_from_world_point(camera, world_T_cam, centers)
    out = []
    for s, (u, v), z in zip(signs, px, depth, strict=True):
        if not (z > 0.5 and np.isfinite(u) and np.isfinite(v)):
            continue
        d = camera.fx * s.diameter_m / z
        m = margin * d
        if -m <= u <= camera.width - 1 + m and -m <= v <= camera.height - 1 + m:
            out.append((s.code, (float(u), float(v)), float(d)))
    return out


def _extrapolate(prev: np.ndarray, prev2: np.ndarray | None, steps: int = 1) -> np.ndarray:
    """Constant velocity in translation from the last two poses, ``steps`` frames on."""
    if prev2 is None:
        return prev
    out = prev.copy()
    out[:3, 3] = prev[:3, 3] + steps * (prev[:3, 3] - prev2[:3, 3])
    return out


def _no_prefetch(source: FrameSource):
    from signpose.io.sources import PrefetchedFrame

    for frame in source:
        t0 = time.perf_counter()
        gray = frame.gray()
        yield PrefetchedFrame(frame, gray, time.perf_counter() - t0)


def _close(it) -> None:
    close = getattr(it, "close", None)
    if close is not None:
        close()


def _detect_full(det: Any, gray: np.ndarray, codes: tuple[str, ...], mode: str):
    try:
        return det.detect(gray, codes, mode=mode)
    except TypeError:  # a detector without modes
        return det.detect(gray, codes)


def _to_observations(
    result: Any, frame: int, stamp_ns: int, image_size: tuple[int, int]
) -> FrameObservations:
    """A detector result as the frame's observations.

    A tuple of ``SignObservation`` (e.g. from a replay or test detector) is
    taken as is; anything else goes through ``frontend.detector.to_frame_observations``.
    """
    if isinstance(result, tuple):
        return FrameObservations(frame, stamp_ns, image_size, result)
    from signpose.frontend.detector import to_frame_observations

    return to_frame_observations(result, frame, stamp_ns, image_size)


def make_detector(settings: ObserveSettings):
    """The frontend's detector (``frontend.detector.SignDetector``)."""
    from signpose.frontend.detector import SignDetector

    return SignDetector(settings.cascade_path or None)


# --------------------------------------------------------------------------- observe


def observe(
    source: FrameSource,
    sign_map: SignMap | None,
    camera: CameraModel | None,
    settings: ObserveSettings | None = None,
    progress: bool = True,
    out_path: str | os.PathLike | None = None,
    detector: Any = None,
) -> ObserveResult:
    """Detect and decode the signs in every frame of ``source``.

    Args:
        source: the frames.
        sign_map: the map (codes to look for and tracking), or None.
        camera: the camera; its size must match the images. Tracking needs it
            and the map.
        settings: frontend settings.
        progress: show a tqdm bar over frames.
        out_path: stream the observations to this JSONL file as they are made.
        detector: a detector object (default: ``make_detector(settings)``).

    Returns:
        The ObserveResult. On KeyboardInterrupt the frames done so far are in
        ``out_path`` (complete lines only) and the interrupt is re-raised.
    """
    s = settings or ObserveSettings()
    if s.codes is not None:
        codes = tuple(s.codes)
    elif sign_map is not None:
        codes = tuple(sign_map.codes)
    else:
        from signpose.frontend.sign import ALL_CODES

        codes = tuple(ALL_CODES)
    tracking = s.tracking and sign_map is not None and camera is not None
    if tracking:
        from signpose.estimator.perframe import solve_frame_pnp
    timing = dict.fromkeys(("decode_video", "wait_video", "detect", "decode", "track"), 0.0)
    stream = ObservationStream(out_path) if out_path is not None else None
    frames: list[FrameObservations] = []
    counts = {"tracked": 0, "full": 0}
    # Frames in flight at once: with our own detector, two worker threads
    # (one detector each) overlap frames; frame i is then predicted from the
    # pose of frame i - 2. A detector passed in is called from this thread only.
    depth = 1 if detector is not None else max(1, s.workers or min(2, os.cpu_count() or 1))
    local = threading.local()

    def detector_here():
        if detector is not None:
            return detector
        det = getattr(local, "det", None)
        if det is None:
            det = local.det = make_detector(s)
        return det

    def detect(gray: np.ndarray, predictions) -> tuple[Any, bool, float]:
        """(result, tracked without falling back, seconds spent) for one frame."""
        det = detector_here()
        t = time.perf_counter()
        if predictions:
            # The detector searches the full frame itself when a prediction is lost.
            result = det.detect_tracked(gray, predictions, codes)
            tracked = not getattr(result, "fell_back", False)
        else:
            result, tracked = _detect_full(det, gray, codes, s.detector_mode), False
        return result, tracked, time.perf_counter() - t

    pool = ThreadPoolExecutor(depth, thread_name_prefix="signpose-detect") if depth > 1 else None
    prev_T = prev2_T = None
    size_checked = False
    pending: deque = deque()
    bar = tqdm(total=source.length, desc="observe", unit="frame", disable=not progress)
    frame_iter: Iterator = prefetch(source) if s.prefetch else _no_prefetch(source)

    def finish_one() -> None:
        nonlocal prev_T, prev2_T
        frame, job = pending.popleft()
        result, was_tracked, spent_s = job if pool is None else job.result()
        t_done = time.perf_counter()
        _add_detector_time(timing, result, spent_s)
        counts["tracked" if was_tracked else "full"] += 1
        obs = _to_observations(result, frame.index, frame.stamp_ns, frame.image_size)
        if tracking:
            pose = solve_frame_pnp(obs, sign_map, camera, prior_world_T_cam=prev_T)
            ok = pose.world_T_cam is not None and (
                not math.isfinite(pose.rms_px) or pose.rms_px <= s.max_track_rms_px
            )
            prev2_T = prev_T if ok else None
            prev_T = pose.world_T_cam if ok else None
            timing["track"] += time.perf_counter() - t_done
        if stream is not None:
            stream.append(obs)
        frames.append(obs)
        bar.update(1)

    try:
        while True:
            t0 = time.perf_counter()
            try:
                item = next(frame_iter)
            except StopIteration:
                break
            frame, gray = item.frame, item.gray
            t1 = time.perf_counter()
            # Reading runs ahead in its own thread: its cost is the reader's time,
            # the wall-clock wait for it is "wait_video".
            timing["decode_video"] += item.read_s
            timing["wait_video"] += t1 - t0
            if not size_checked:
                if camera is not None:
                    check_image_size(camera, *frame.image_size, str(source.path))
                size_checked = True
                detector_here()  # a bad model file fails here, once
            predictions = None
            if tracking and prev_T is not None:
                predicted_T = _extrapolate(prev_T, prev2_T, steps=len(pending) + 1)
                predictions = predict_signs(
                    sign_map, camera, predicted_T, codes, s.prediction_margin
                )
            if pool is None:
                pending.append((frame, detect(gray, predictions)))
            else:
                pending.append((frame, pool.submit(detect, gray, predictions)))
            while len(pending) >= depth:
                finish_one()
        while pending:
            finish_one()
    except KeyboardInterrupt:
        bar.close()
        _close(frame_iter)
        _stop(pool, pending)
        if stream is not None:
            kept = stream.finish_partial()
            if kept is not None:
                log.info("interrupted: %d complete frames kept in %s", stream.lines, kept)
        raise
    except BaseException:
        bar.close()
        _close(frame_iter)
        _stop(pool, pending)
        if stream is not None:
            stream.abort()
        raise
    bar.close()
    if pool is not None:
        pool.shutdown(wait=True)
    if stream is not None:
        stream.finish()
    return ObserveResult(
        tuple(frames), timing, tuple(source.problems), counts["tracked"], counts["full"]
    )


def _stop(pool: ThreadPoolExecutor | None, pending: deque) -> None:
    if pool is None:
        return
    for _, job in pending:
        job.cancel()
    pool.shutdown(wait=True, cancel_futures=True)


def _add_detector_time(timing: dict[str, float], result: Any, wall_s: float) -> None:
    """Split the detector's wall time into detect and decode (the detector reports ms)."""
    split = getattr(result, "timing", None)
    decode_s = 0.0
    if isinstance(split, dict) and "decode" in split:
        decode_s = min(float(split["decode"]) / 1e3, wall_s)
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


def check_codes_seen(frames: tuple[FrameObservations, ...], sign_map: SignMap, where: str) -> None:
    """InputError when none of the map's signs was seen in any frame."""
    seen = {o.code for f in frames for o in f.signs}
    if not seen & set(sign_map.codes):
        extra = f" (the frames show {', '.join(sorted(seen))})" if seen else ""
        raise InputError(
            f"{sign_map.source or 'map'}: none of the map's codes "
            f"({', '.join(sign_map.codes)}) was seen in the {len(frames)} frames of "
            f"{where}{extra}; pass the map of this site"
        )


def _trajectories(estimate) -> tuple[dict, dict]:
    """method -> Trajectory (NaN where no pose), method -> (N, 3) sigma [m]."""
    from signpose.estimator.trajectory import Trajectory

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


def _valid_only(traj):
    from signpose.estimator.trajectory import Trajectory

    ok = np.all(np.isfinite(traj.world_t_cam), axis=1)
    return Trajectory(traj.stamps_s[ok], traj.world_t_cam[ok], traj.quat_xyzw[ok])


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
    detector: Any = None,
    echo: Callable[[str], None] | None = None,
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
        detector: detector object (tests); default ``make_detector``.
        echo: where to print warnings for the user (e.g. stderr), or None.

    Returns:
        The RunResult; ``report.json`` in ``out_dir`` holds the same numbers.
    """
    from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
    from signpose.io.tum import read_tum

    s = settings or RunSettings()
    t_start = time.perf_counter()
    out = ensure_dir(out_dir)
    gt = read_tum(gt_path) if gt_path is not None else None
    source = open_source(input_path, topic=topic, fps=fps)
    cam = _camera_for(source, camera)
    obs = observe(
        source,
        sign_map,
        cam,
        s.observe,
        progress,
        out_path=out / OBSERVATIONS_NAME,
        detector=detector,
    )
    for line in obs.problems:
        if echo is not None:
            echo(f"warning: {line}")
    files: list[Path] = [out / OBSERVATIONS_NAME]
    check_codes_seen(obs.frames, sign_map, str(source.path))
    t0 = time.perf_counter()
    est_settings = s.estimator if s.estimator is not None else EstimatorSettings()
    estimate = estimate_trajectories(list(obs.frames), sign_map, cam, est_settings, progress)
    t_estimate = time.perf_counter() - t0

    t0 = time.perf_counter()
    trajs, sigmas = _trajectories(estimate)
    files += _write_estimator_outputs(out, estimate)
    if s.plots:
        from signpose.plots import PlotData, write_plots

        stamps = np.array([f.stamp_ns for f in obs.frames], float) * 1e-9
        map_codes = set(sign_map.codes)
        seen = np.array([sum(o.code in map_codes for o in f.signs) for f in obs.frames])
        files += write_plots(out, PlotData(sign_map, trajs, sigmas, gt, stamps, seen))
    if s.mcap:
        from signpose.io import mcap as mcap_io

        images = None
        if s.with_images:
            images = ((f.stamp_ns, f.image) for f in open_source(input_path, topic=topic, fps=fps))
        valid = {k: _valid_only(v) for k, v in trajs.items()}
        mcap_io.write_result_mcap(
            out / RESULT_MCAP_NAME,
            sign_map,
            list(obs.frames),
            valid,
            cam,
            images,
            progress=progress,
        )
        files.append(out / RESULT_MCAP_NAME)
    comparison, table = None, ""
    if gt_path is not None:
        comparison, table = _compare(out, Path(gt_path))
    t_outputs = time.perf_counter() - t0
    total = time.perf_counter() - t_start
    timing = dict(obs.timing_s)
    timing["estimate"] = t_estimate
    timing["outputs"] = t_outputs
    timing["total"] = total
    n = len(obs.frames)
    coverage = {name: float(m.coverage) for name, m in estimate.methods.items()}
    rmse = {} if gt is None else {k: position_rmse(v, gt) for k, v in trajs.items()}
    for name, metrics in (comparison or {}).items():
        if isinstance(metrics, dict) and metrics.get("ate_rmse") is not None:
            rmse[name] = float(metrics["ate_rmse"])
    fps_run = n / total if total > 0 else float("nan")
    section = {
        "input": str(source.path),
        "input_kind": source.kind,
        "frames": n,
        "problems": list(obs.problems),
        "tracking": {"tracked_frames": obs.tracked_frames, "full_frames": obs.full_frames},
        "coverage": coverage,
        "position_rmse_m": rmse,
        "timing_s": {k: round(v, 4) for k, v in timing.items()},
        "timing_ms_per_frame": {
            k: round(1000 * v / max(n, 1), 3) for k, v in timing.items() if k != "total"
        },
        "frames_per_second": round(fps_run, 3),
        "settings": {"observe": asdict(s.observe), "with_images": s.with_images},
    }
    _add_to_report(out / REPORT_NAME, "pipeline", section)
    if out / REPORT_NAME not in files:
        files.append(out / REPORT_NAME)
    return RunResult(
        out,
        n,
        coverage,
        rmse,
        comparison,
        table,
        timing,
        fps_run,
        tuple(obs.problems),
        tuple(files),
    )


def position_rmse(traj, gt) -> float:
    """RMS position error [m] of ``traj`` against ``gt`` at the stamps both have (NaN: none)."""
    from signpose.plots import pose_errors

    _, dp, _ = pose_errors(_valid_only(traj), gt)
    return float(np.sqrt(np.mean(dp**2))) if len(dp) else float("nan")


def _write_estimator_outputs(out: Path, estimate) -> list[Path]:
    """The estimator's files: ``<method>.tum``, ``trajectory.csv``, ``report.json``."""
    from signpose.io.results import write_outputs

    return [Path(p) for p in write_outputs(out, estimate)]


def _compare(out: Path, gt_path: Path) -> tuple[dict, str]:
    """The estimator's comparison (added to report.json): (method -> metrics, table)."""
    from signpose.io.results import compare_dir, metrics_table

    return compare_dir(out, gt_path), metrics_table(out)


def _add_to_report(path: Path, key: str, section: dict) -> None:
    """Add ``section`` under ``key`` to the estimator's report.json (its module writes it)."""
    from signpose.io.results import read_report, write_json

    report = read_report(path) if path.exists() else {}
    report[key] = section
    write_json(path, report)


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
) -> DemoResult:
    """Simulate the bundled pylon flight into ``out_dir/flight`` and run everything on it.

    Results (observations, trajectories, comparison, plots, result.mcap) go
    into ``out_dir`` itself.
    """
    from signpose.maps.loader import bundled_map_path, load_map
    from signpose.sim.flight import SimSettings, simulate

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
        settings=RunSettings(with_images=with_images),
        progress=progress,
    )
    return DemoResult(sim.out_dir, result)
