"""Many flights at once: one ``pipeline.run`` per flight, in parallel, with a summary CSV.

Each flight gets ``OUT/<flight>/``; a flight is finished when its
``.done.json`` marker exists (written last, atomically), so a rerun skips
it. A failing flight is recorded in the summary and the others go on.
Ctrl-C or SIGTERM stops the batch at once: the queued flights are cancelled,
the running ones stopped, and summary.csv lists the finished flights, the
running ones as ``interrupted`` and the queued ones as ``not_started``
(neither has a done marker, so a rerun runs them).
Flights run in a local process pool, or on a Dask distributed cluster
(``scheduler="tcp://host:port"``, optional extra ``signpose[dask]``).
"""

from __future__ import annotations

import contextlib
import csv
import enum
import io
import json
import logging
import math
import os
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Protocol

from tqdm import tqdm

from signpose.core.errors import InputError, SignposeError, one_line
from signpose.core.fileio import atomic_write, ensure_dir
from signpose.estimator.estimate import EstimatorSettings, settings_from_options
from signpose.estimator.status import PoseStatus
from signpose.fingerprint import (
    FINGERPRINT_KEY,
    content_digest,
    flight_fingerprint,
    stored_fingerprint,
)
from signpose.io.camera_file import load_camera
from signpose.io.telemetry import TelemetryRequest
from signpose.maps.loader import load_map
from signpose.pipeline import ObserveSettings, RunSettings, make_detector, run
from signpose.report_html import write_batch_index

log = logging.getLogger(__name__)

DONE_MARKER = ".done.json"
SUMMARY_NAME = "summary.csv"
_METHOD_ORDER = ("baseline", "pnp", "smoothed", "causal")
# FlightJob fields that change a flight's results (with its files: see _fingerprint).
# plots and with_images only add files: changing them alone does not redo a flight (--force does).
_RESULT_FIELDS = ("topic", "fps")
# How long a stopped pool worker may take to flush its flight before it is killed [s].
_WORKER_GRACE_S = 1.0


class FlightStatus(enum.StrEnum):
    """How a flight went; the value is the token in summary.csv and .done.json."""

    OK = "ok"
    PARTIAL = "partial"  # input truncated/corrupt: the readable part was processed
    FAILED = "failed"
    INTERRUPTED = "interrupted"  # running when the batch was stopped (Ctrl-C, SIGTERM)
    NOT_STARTED = "not_started"  # still queued when the batch was stopped


class _Finished(Protocol):
    """A finished job of a process pool or of Dask."""

    def result(self) -> FlightOutcome: ...


@dataclass(frozen=True)
class FlightJob:
    """One flight to run (plain data, so it pickles to worker processes).

    Attributes:
        flight: the flight's name (its sub-folder).
        input_path: video, image folder or MCAP log.
        map_path: the sign map.
        out_dir: the flight's output folder.
        camera_path: the camera file, or "" (camera.yaml beside the input, else the log's).
        gt_path: ground truth TUM, or "" (groundtruth.tum beside the input when present).
        topic: MCAP image topic, or "".
        fps: frame rate for an image folder without times, or 0.
        with_images: put images into result.mcap.
        plots: write the PNG plots.
        cascade_path: detector cascade XML, or "" (the bundled one).
        fingerprint: digest of what the outputs are made from (kept in the done marker).
        workers: observing processes within the flight (0 = as ``signpose run``);
            1 when flights already run in parallel, so that ``--jobs 2`` is two
            processes, not four. Not in the fingerprint: the output does not
            depend on it.
        telemetry: the drone's telemetry file beside each input, as a name in
            which ``{stem}`` is the input's name without its suffix (DJI:
            ``{stem}.SRT``), or "" (none: vision only); a flight without it fails.
        telemetry_offset_s: telemetry time minus video time [s]; None: estimated.
        focal_sigma_rel: the calibration's focal length sigma as a fraction,
            added to the pose sigmas (``EstimatorSettings.focal_sigma_rel``).
        solver: the smoother's solver, "batch" or "isam2" (``signpose run --solver``).
        map_fixed: the survey taken as exact (``--map-fixed``).
        sigmas: compute the smoother's marginal sigmas (False: ``--no-sigmas``).
        principal_sigma_px: the calibration's principal point sigma [px], added
            to the pose sigmas (``EstimatorSettings.principal_sigma_px``).
        The estimator's fields are in the fingerprint only when not at their
        defaults, so that runs of before they existed stay finished.
    """

    flight: str
    input_path: str
    map_path: str
    out_dir: str
    camera_path: str = ""
    gt_path: str = ""
    topic: str = ""
    fps: float = 0.0
    with_images: bool = False
    plots: bool = True
    cascade_path: str = ""
    fingerprint: str = ""
    workers: int = 0
    telemetry: str = ""
    telemetry_offset_s: float | None = None
    focal_sigma_rel: float = 0.0
    solver: str = "batch"
    map_fixed: bool = False
    sigmas: bool = True
    principal_sigma_px: float = 0.0


# FlightJob's estimator fields and their defaults (the fingerprint leaves defaults out).
_ESTIMATOR_FIELDS = ("focal_sigma_rel", "solver", "map_fixed", "sigmas", "principal_sigma_px")
_ESTIMATOR_DEFAULTS = {f.name: f.default for f in fields(FlightJob) if f.name in _ESTIMATOR_FIELDS}


def estimator_settings(job: FlightJob) -> EstimatorSettings:
    """The estimator's settings of one flight, as ``signpose run`` makes them from the same
    options (``estimate.settings_from_options``)."""
    return settings_from_options(
        job.solver, job.map_fixed, job.sigmas, job.focal_sigma_rel, job.principal_sigma_px
    )


@dataclass(frozen=True)
class FlightOutcome:
    """How one flight went.

    Attributes:
        flight: the flight's name.
        status: how it went.
        frames: frames processed.
        coverage: method -> fraction of frames with a pose.
        position_rmse_m: method -> RMS position error vs ground truth [m].
        pose_status: method -> share of frames with each pose status token
            (``ok``, ``weak``, ``bridged``, ``suspect``, or a failure token).
        errors: method -> the errors against ground truth named in
            ``ERROR_COLUMNS`` (per-axis MAE and aligned ATE [m], rotation RMSE
            [deg]); empty without ground truth.
        time_s: wall time of the flight [s].
        message: why it failed / where the input stopped, else "".
        skipped: True when a previous run had finished it.
        internal: it failed on a bug (an internal error, a worker that died),
            not on bad input.
    """

    flight: str
    status: FlightStatus
    frames: int = 0
    coverage: dict[str, float] = field(default_factory=dict)
    position_rmse_m: dict[str, float] = field(default_factory=dict)
    time_s: float = 0.0
    message: str = ""
    skipped: bool = False
    internal: bool = False
    pose_status: dict[str, dict[str, float]] = field(default_factory=dict)
    errors: dict[str, dict[str, float]] = field(default_factory=dict)

    def bridged(self, method: str) -> int | None:
        """Frames of ``method`` bridged by the motion prior (None when not recorded)."""
        share = self.pose_status.get(method, {}).get(PoseStatus.BRIDGED.value)
        if share is None:
            return 0 if method in self.pose_status else None
        return round(share * self.frames)


# summary.csv's error columns per method (``<column>_<method>``) and where each comes from
# in a method's ``Metrics.to_dict()``: (key, index into a per-axis list or None).
ERROR_COLUMNS = {
    "mae_x_m": ("mae_xyz_m", 0),
    "mae_y_m": ("mae_xyz_m", 1),
    "mae_z_m": ("mae_xyz_m", 2),
    "ate_aligned_m": ("ate_rmse_aligned_m", None),
    "rot_rmse_deg": ("rot_rmse_deg", None),
}
STATUS_TOKENS = tuple(s.value for s in PoseStatus)  # summary.csv's share columns


def errors_from_metrics(metrics: dict | None) -> dict[str, float]:
    """``ERROR_COLUMNS`` of one method's ``Metrics.to_dict()`` (missing or null: left out)."""
    out = {}
    for column, (key, index) in ERROR_COLUMNS.items():
        value = (metrics or {}).get(key)
        if index is not None:
            value = value[index] if isinstance(value, list) and len(value) == 3 else None
        if isinstance(value, int | float):
            out[column] = float(value)
    return out


def flight_names(
    inputs: Iterable[str | os.PathLike], root: str | os.PathLike | None = None
) -> list[str]:
    """Unique, readable sub-folder names for the inputs.

    Without ``root``: the stem, parent_stem on clashes (so a name depends on
    which inputs come together). With ``root``: the path below ``root``
    without its suffix, folders joined by "_" (``ROOT/f1/video.mp4`` ->
    ``f1_video``), the same whichever subset is passed.
    """
    paths = [Path(p) for p in inputs]
    if root is not None:
        return _names_below(paths, Path(root))
    names = [p.stem if p.suffix else p.name for p in paths]
    clash = {n for n in names if names.count(n) > 1}
    names = [
        f"{p.parent.name}_{n}" if n in clash and p.parent.name else n
        for p, n in zip(paths, names, strict=True)
    ]
    out, seen = [], {}
    for n in names:
        k = seen.get(n, 0)
        seen[n] = k + 1
        out.append(n if k == 0 else f"{n}_{k + 1}")
    return out


def _names_below(paths: list[Path], root: Path) -> list[str]:
    base = root.resolve()
    names = []
    for p in paths:
        try:
            rel = p.resolve().relative_to(base)
        except ValueError:
            raise InputError(
                f"{p}: not inside --root {root}; pass a --root above every input"
            ) from None
        parts = rel.with_suffix("").parts if rel.suffix else rel.parts
        names.append("_".join(parts) or base.name)
    clash = sorted({n for n in names if names.count(n) > 1})
    if clash:
        raise InputError(f"--root {root}: inputs share the flight name {clash[0]}; rename one")
    return names


def _beside(input_path: Path, name: str) -> str:
    base = input_path if input_path.is_dir() else input_path.parent
    for candidate in (base / name, base.parent / name if input_path.is_dir() else None):
        if candidate is not None and candidate.is_file():
            return str(candidate)
    return ""


def telemetry_name(pattern: str, input_path: Path) -> str:
    """The telemetry file's name for one input (``{stem}``: the input's name without suffix)."""
    try:
        return pattern.format(stem=input_path.stem, name=input_path.name)
    except (KeyError, IndexError, ValueError):
        raise InputError(
            f"--telemetry {pattern}: a file name, where {{stem}} stands for the input's name "
            "without its suffix (e.g. {stem}.SRT); no other {...} fields"
        ) from None


def _telemetry_found(job: FlightJob) -> tuple[str, str]:
    """The flight's telemetry file name (with --telemetry) and its path beside it, or ""."""
    inp = Path(job.input_path)
    name = telemetry_name(job.telemetry, inp)
    return name, _beside(inp, name)


def _telemetry_beside(job: FlightJob) -> str:
    """The flight's telemetry file ("" without --telemetry); InputError when it is missing."""
    if not job.telemetry:
        return ""
    name, found = _telemetry_found(job)
    if not found:
        raise InputError(
            f"{Path(job.input_path)}: no telemetry file {name} beside it "
            f"(--telemetry {job.telemetry})"
        )
    return found


def run_flight(job: FlightJob) -> FlightOutcome:
    """Run one flight; never raises (failures are outcomes). Writes the done marker last."""
    t0 = time.perf_counter()
    try:
        out = ensure_dir(job.out_dir)
        inp = Path(job.input_path)
        sign_map = load_map(job.map_path)
        camera_path = job.camera_path or _beside(inp, "camera.yaml")
        camera = load_camera(camera_path) if camera_path else None
        gt_path = job.gt_path or _beside(inp, "groundtruth.tum")
        telemetry_path = _telemetry_beside(job)
        telemetry = (
            TelemetryRequest(path=Path(telemetry_path), clock_offset_s=job.telemetry_offset_s)
            if telemetry_path
            else None
        )
        result = run(
            inp,
            sign_map,
            out,
            camera=camera,
            gt_path=gt_path or None,
            topic=job.topic or None,
            fps=job.fps or None,
            settings=RunSettings(
                observe=ObserveSettings(cascade_path=job.cascade_path, workers=job.workers),
                estimator=estimator_settings(job),
                with_images=job.with_images,
                plots=job.plots,
                telemetry=telemetry,
            ),
            progress=False,
        )
        outcome = FlightOutcome(
            job.flight,
            FlightStatus.PARTIAL if result.problems else FlightStatus.OK,
            frames=result.n_frames,
            coverage=result.coverage,
            position_rmse_m=result.position_rmse_m,
            time_s=time.perf_counter() - t0,
            message="; ".join(result.problems),
            pose_status=result.status,
            errors={k: errors_from_metrics(v) for k, v in (result.comparison or {}).items()},
        )
    except SignposeError as exc:
        return FlightOutcome(
            job.flight, FlightStatus.FAILED, time_s=time.perf_counter() - t0, message=one_line(exc)
        )
    except Exception as exc:  # noqa: BLE001 - one flight's bug must not stop the batch
        log.debug("flight %s failed:\n%s", job.flight, traceback.format_exc())
        return FlightOutcome(
            job.flight,
            FlightStatus.FAILED,
            time_s=time.perf_counter() - t0,
            message=f"internal error: {type(exc).__name__}: {one_line(exc)}",
            internal=True,
        )
    with atomic_write(Path(job.out_dir) / DONE_MARKER) as f:
        json.dump(_clean(asdict(outcome)) | {FINGERPRINT_KEY: job.fingerprint}, f, indent=2)
    return outcome


def _clean(value):
    """JSON-safe copy: NaN/inf -> None."""
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_clean(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def read_done(out_dir: Path) -> FlightOutcome | None:
    """The outcome recorded by a finished earlier run, or None."""
    marker = out_dir / DONE_MARKER
    if not marker.is_file():
        return None
    try:
        d = json.loads(marker.read_text(encoding="utf-8"))
        d = {k: v for k, v in d.items() if k in FlightOutcome.__dataclass_fields__}
        d["status"] = FlightStatus(d["status"])
        d["skipped"] = True
        return FlightOutcome(**d)
    except (OSError, ValueError, TypeError, KeyError):
        return None  # unreadable marker: run the flight again


def write_summary(path: Path, outcomes: list[FlightOutcome]) -> None:
    """summary.csv (atomically): flight, status, frames, per method coverage, pose status
    shares, bridged frames and errors, time.

    Per method ``m``: ``coverage_m`` (share of frames posed), ``share_<token>_m``
    for ok / weak / bridged / suspect (share of all frames), ``bridged_m``
    (frames), ``position_rmse_m_m``, ``mae_x_m_m`` / ``mae_y_m_m`` /
    ``mae_z_m_m``, ``ate_aligned_m_m`` [m] and ``rot_rmse_deg_m`` [deg]
    (errors empty without ground truth).

    Rows an earlier call wrote into the same file stay: a flight of
    ``outcomes`` replaces its own row in place, other flights' rows are kept
    as they were, new flights come last.
    """
    methods = sorted(
        {m for o in outcomes for m in (*o.coverage, *o.position_rmse_m, *o.pose_status)},
        key=lambda m: (_METHOD_ORDER.index(m) if m in _METHOD_ORDER else 99, m),
    )
    header = ["flight", "status", "frames"]
    header += [f"coverage_{m}" for m in methods]
    header += [f"share_{t}_{m}" for t in STATUS_TOKENS for m in methods]
    header += [f"bridged_{m}" for m in methods]
    header += [f"position_rmse_m_{m}" for m in methods]
    header += [f"{c}_{m}" for c in ERROR_COLUMNS for m in methods]
    header += ["time_s", "skipped", "message"]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")

    def fmt(x, digits):
        return (
            ""
            if x is None or (isinstance(x, float) and not math.isfinite(x))
            else f"{x:.{digits}f}"
        )

    rows = {}
    for o in outcomes:
        row = [o.flight, o.status, o.frames]
        row += [fmt(o.coverage.get(m), 4) for m in methods]
        row += [_share(o, t, m) for t in STATUS_TOKENS for m in methods]
        row += ["" if o.bridged(m) is None else o.bridged(m) for m in methods]
        row += [fmt(o.position_rmse_m.get(m), 4) for m in methods]
        row += [fmt(o.errors.get(m, {}).get(c), 4) for c in ERROR_COLUMNS for m in methods]
        row += [fmt(o.time_s, 2), "yes" if o.skipped else "", o.message]
        rows[o.flight] = dict(zip(header, row, strict=True))
    header, merged = _with_earlier_rows(path, header, rows)
    w.writerow(header)
    for row in merged:
        w.writerow([row.get(h, "") for h in header])
    with atomic_write(path) as f:
        f.write(buf.getvalue())


def _share(outcome: FlightOutcome, token: str, method: str) -> str:
    """The share of ``method``'s frames with status ``token`` (4 decimals; "" if not recorded)."""
    shares = outcome.pose_status.get(method)
    return "" if shares is None else f"{shares.get(token, 0.0):.4f}"


def _with_earlier_rows(
    path: Path, header: list[str], rows: dict[str, dict]
) -> tuple[list[str], list[dict]]:
    """(header, rows): the earlier rows in their order, updated by ``rows``, then new ones."""
    try:
        with open(path, encoding="utf-8", newline="") as f:
            reader = csv.DictReader(f)
            earlier = [r for r in reader if r.get("flight")]
            earlier_header = list(reader.fieldnames or [])
    except (OSError, csv.Error, UnicodeDecodeError):
        return header, list(rows.values())
    merged = [rows.pop(r["flight"], r) for r in earlier]
    merged += rows.values()
    extra = [h for h in earlier_header if h not in header]
    at = header.index("time_s") if "time_s" in header else len(header)
    return header[:at] + extra + header[at:], merged


def _dask_client(scheduler: str):
    try:
        from dask.distributed import Client
    except ImportError:
        raise InputError(
            f"--scheduler {scheduler} needs Dask; install it with: pip install signpose[dask]"
        ) from None
    try:
        return Client(scheduler, timeout="10s")
    except (OSError, TimeoutError) as exc:
        raise InputError(
            f"--scheduler {scheduler}: cannot connect to the Dask scheduler ({exc})"
        ) from None


def _fingerprint(job: FlightJob) -> str:
    """The job's fingerprint: its input, map, the camera and ground truth it will use, settings."""
    inp = Path(job.input_path)
    return flight_fingerprint(
        inp,
        job.map_path,
        job.camera_path or _beside(inp, "camera.yaml") or None,
        job.gt_path or _beside(inp, "groundtruth.tum") or None,
        {k: getattr(job, k) for k in _RESULT_FIELDS}
        | {"cascade": content_digest(job.cascade_path)}
        | _telemetry_key(job)
        # only when set: the runs of before they existed match
        | {k: getattr(job, k) for k, v in _ESTIMATOR_DEFAULTS.items() if getattr(job, k) != v},
    )


def _telemetry_key(job: FlightJob) -> dict:
    """The telemetry's part of the fingerprint: nothing without --telemetry (old runs match)."""
    if not job.telemetry:
        return {}
    _, found = _telemetry_found(job)
    return {
        "telemetry": content_digest(found) if found else "missing",
        "telemetry_offset_s": job.telemetry_offset_s,
    }


def _jobs(
    inputs: list[str | os.PathLike],
    names: list[str],
    map_path: str | os.PathLike,
    out: Path,
    options: FlightJob,
    force: bool = False,
) -> tuple[dict[str, FlightOutcome], list[FlightJob]]:
    """(flight -> outcome of an earlier run, the flights still to run).

    ``options`` holds the settings shared by every flight (its flight and
    paths are ignored). A finished flight is run again when its fingerprint
    changed (or was never stored), or with ``force``.
    """
    done: dict[str, FlightOutcome] = {}
    todo: list[FlightJob] = []
    for name, inp in zip(names, inputs, strict=True):
        job = replace(
            options,
            flight=name,
            input_path=str(Path(inp).resolve()),
            map_path=str(Path(map_path).resolve()),
            out_dir=str((out / name).resolve()),
        )
        job = replace(job, fingerprint=_fingerprint(job))
        earlier = None if force else read_done(out / name)
        if earlier is not None and stored_fingerprint(out / name / DONE_MARKER) == job.fingerprint:
            done[name] = earlier
            continue
        if earlier is not None:
            log.info("flight %s: input, map, camera, settings or version changed: redone", name)
        todo.append(job)
    return done, todo


def _run_jobs(
    todo: list[FlightJob],
    runner: Callable[[FlightJob], FlightOutcome],
    jobs: int,
    scheduler: str | None,
    running: set[str],
) -> Iterator[FlightOutcome]:
    """The flights' outcomes as they finish: on Dask, in a process pool, or one by one.

    On KeyboardInterrupt (Ctrl-C, SIGTERM) the queued flights are cancelled at
    once and the flights a worker had started are added to ``running`` (the
    caller marks them interrupted) before the interrupt goes on.
    """
    if not todo:
        return
    if scheduler:
        yield from _run_on_dask(todo, runner, scheduler, running)
    elif jobs <= 1:
        for job in todo:
            running.add(job.flight)
            outcome = runner(job)
            running.discard(job.flight)
            yield outcome
    else:
        yield from _run_in_pool(todo, runner, jobs, running)


def _run_in_pool(
    todo: list[FlightJob],
    runner: Callable[[FlightJob], FlightOutcome],
    jobs: int,
    running: set[str],
) -> Iterator[FlightOutcome]:
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        futures = {pool.submit(runner, job): job for job in todo}
        try:
            for fut in as_completed(futures):
                yield _outcome_of(fut, futures[fut])
        except KeyboardInterrupt:
            # running() is also true of the few calls queued to a worker that has not taken
            # them yet: those are marked interrupted too (a rerun runs both states).
            running.update(job.flight for fut, job in futures.items() if fut.running())
            # Else leaving the pool would first run every running and queued flight to its end.
            processes = list((getattr(pool, "_processes", None) or {}).values())
            pool.shutdown(wait=False, cancel_futures=True)
            _stop_workers(processes)
            raise


def _stop_workers(processes: list) -> None:
    """SIGTERM (a worker flushes its flight as `signpose run` does), then SIGKILL after a grace:
    a worker that caught the SIGTERM would go on with the calls already queued to it."""
    for process in processes:
        with contextlib.suppress(OSError, ValueError):
            process.terminate()
    deadline = time.monotonic() + _WORKER_GRACE_S
    for process in processes:
        with contextlib.suppress(OSError, ValueError, AssertionError):
            process.join(max(deadline - time.monotonic(), 0.0))
            if process.is_alive():
                process.kill()


def _run_on_dask(
    todo: list[FlightJob],
    runner: Callable[[FlightJob], FlightOutcome],
    scheduler: str,
    running: set[str],
) -> Iterator[FlightOutcome]:
    client = _dask_client(scheduler)
    try:
        from dask.distributed import as_completed as dask_completed

        futures = {client.submit(runner, job, pure=False): job for job in todo}
        try:
            for fut in dask_completed(futures):
                yield _outcome_of(fut, futures[fut])
        except KeyboardInterrupt:
            with contextlib.suppress(Exception):  # best effort: the scheduler may be gone
                busy = {key for keys in client.processing().values() for key in keys}
                running.update(job.flight for fut, job in futures.items() if fut.key in busy)
            with contextlib.suppress(Exception):
                client.cancel(list(futures))
            raise
    finally:
        client.close()


def run_batch(
    inputs: list[str | os.PathLike],
    map_path: str | os.PathLike,
    out_dir: str | os.PathLike,
    *,
    camera_path: str | os.PathLike | None = None,
    topic: str | None = None,
    fps: float | None = None,
    with_images: bool = False,
    plots: bool = True,
    jobs: int = 1,
    scheduler: str | None = None,
    progress: bool = True,
    runner: Callable[[FlightJob], FlightOutcome] = run_flight,
    force: bool = False,
    root: str | os.PathLike | None = None,
    cascade_path: str | os.PathLike | None = None,
    telemetry: str | None = None,
    telemetry_offset_s: float | None = None,
    focal_sigma_rel: float = 0.0,
    solver: str = "batch",
    map_fixed: bool = False,
    sigmas: bool = True,
    principal_sigma_px: float = 0.0,
) -> list[FlightOutcome]:
    """Run every flight not finished yet (or changed since) and write ``summary.csv``.

    Args:
        inputs: the flights (videos, image folders, MCAP logs).
        map_path: the sign map shared by all flights.
        out_dir: output folder; one sub-folder per flight.
        camera_path: camera for all flights; None: ``camera.yaml`` beside each
            input, else the log's calibration.
        topic, fps, with_images, plots: as for ``signpose run``.
        jobs: parallel worker processes (local pool).
        scheduler: ``tcp://host:port`` of a Dask scheduler instead of the local pool.
        progress: one tqdm bar over flights.
        runner: the per-flight function (picklable; tests swap it).
        force: run every flight again, finished or not.
        root: name each flight by its input's path below this folder (see
            ``flight_names``), so that names do not depend on which flights
            are passed together.
        cascade_path: detector cascade XML for every flight; None: the bundled one.
        telemetry, telemetry_offset_s, focal_sigma_rel, solver, map_fixed, sigmas,
            principal_sigma_px: as ``FlightJob``'s.

    Returns:
        One outcome per input, in input order.
    """
    if not inputs:
        raise InputError("no flights given")
    cascade = _check_shared(map_path, cascade_path, telemetry)
    out, names = ensure_dir(out_dir), flight_names(inputs, root)
    options = FlightJob(
        flight="",
        input_path="",
        map_path="",
        out_dir="",
        camera_path=str(Path(camera_path).resolve()) if camera_path else "",
        topic=topic or "",
        fps=float(fps or 0.0),
        with_images=with_images,
        plots=plots,
        cascade_path=cascade,
        telemetry=telemetry or "",
        telemetry_offset_s=telemetry_offset_s,
        focal_sigma_rel=focal_sigma_rel,
        solver=solver,
        map_fixed=map_fixed,
        sigmas=sigmas,
        principal_sigma_px=principal_sigma_px,
        workers=1 if (jobs > 1 or scheduler) else 0,  # flights in parallel: 1 process each
    )
    outcomes, todo = _jobs(inputs, names, map_path, out, options, force)
    bar = _flights_bar(len(inputs), len(outcomes), progress)
    return _run_and_summarise(todo, outcomes, names, out, bar, runner, jobs, scheduler)


def _run_and_summarise(
    todo: list[FlightJob],
    outcomes: dict[str, FlightOutcome],
    names: list[str],
    out: Path,
    bar: tqdm,
    runner: Callable[[FlightJob], FlightOutcome],
    jobs: int,
    scheduler: str | None,
) -> list[FlightOutcome]:
    """Run ``todo`` into ``outcomes`` (the earlier runs' outcomes, by flight), then write
    summary.csv and index.html, also when stopped; the outcomes in ``names``' order."""
    outcomes, running = dict(outcomes), set()
    try:
        for outcome in _run_jobs(todo, runner, jobs, scheduler, running):
            outcomes[outcome.flight] = outcome
            bar.update(1)
    except KeyboardInterrupt:
        outcomes |= _stopped(todo, outcomes, running)
        raise
    finally:
        bar.close()
        ordered = [outcomes[n] for n in names if n in outcomes]
        write_summary(out / SUMMARY_NAME, ordered)
        write_batch_index(out)
    return ordered


def _check_shared(
    map_path: str | os.PathLike, cascade_path: str | os.PathLike | None, telemetry: str | None
) -> str:
    """Fail once, early, on a bad map, cascade or telemetry name; the cascade's full path."""
    load_map(map_path)
    if telemetry:
        telemetry_name(telemetry, Path("flight.mp4"))
    cascade = str(Path(cascade_path).resolve()) if cascade_path else ""
    if cascade:
        make_detector(ObserveSettings(cascade_path=cascade))
    return cascade


def _flights_bar(total: int, done: int, progress: bool) -> tqdm:
    return tqdm(total=total, initial=done, desc="flights", unit="flight", disable=not progress)


def _stopped(
    todo: list[FlightJob], outcomes: dict[str, FlightOutcome], running: set[str]
) -> dict[str, FlightOutcome]:
    """Outcomes for the flights an interrupt stopped: interrupted if started, else not started.

    Neither has a done marker, so a rerun runs them.
    """
    stopped = {}
    for job in todo:
        if job.flight in outcomes:
            continue
        started = job.flight in running
        stopped[job.flight] = FlightOutcome(
            job.flight,
            FlightStatus.INTERRUPTED if started else FlightStatus.NOT_STARTED,
            message="stopped while running" if started else "stopped before it started",
        )
    return stopped


def _outcome_of(fut: _Finished, job: FlightJob) -> FlightOutcome:
    try:
        return fut.result()
    except Exception as exc:  # noqa: BLE001 - a worker died: record it, go on
        return FlightOutcome(
            job.flight,
            FlightStatus.FAILED,
            message=f"worker failed: {type(exc).__name__}: {one_line(exc)}",
            internal=True,
        )
