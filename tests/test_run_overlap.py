"""A run's overlap (issue 14): per-frame methods while observing, plots in other processes.

The files must be the same bytes as a run that does one stage after the other,
and the estimator's PnP reuses the tracker's calls where their inputs match.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from conftest import simulate_tiny, truth_detector
from signpose.estimator import perframe
from signpose.estimator.perframe import PerFrameRun, run_per_frame
from signpose.maps.loader import bundled_map_path, load_map

from signpose import pipeline
from signpose.io.sources import open_source
from signpose.sim.flight import SimSettings, simulate

# Numbers of report.json that measure the run's time (or name the run), not its result.
_TIMED = ("timing_s", "timing_ms_per_frame", "frames_per_second", "run_id")


@pytest.fixture(scope="module")
def real_flight(tmp_path_factory):
    """8 frames at 960x540, big enough for the trained cascade and the decoder."""
    settings = SimSettings(frames=8, width=960, height=540)
    return simulate(
        load_map(bundled_map_path()), tmp_path_factory.mktemp("real"), settings, progress=False
    )


def _untimed_report(path: Path) -> dict:
    report = json.loads(path.read_text(encoding="utf-8"))
    for section in (report, report["pipeline"]):
        for key in _TIMED:
            section.pop(key, None)
    return report


def test_overlapped_run_writes_the_same_files_as_one_stage_after_another(real_flight, tmp_path):
    """Chunks of 3 frames in 2 processes: the per-frame methods run as chunks come in,
    the plots are drawn in 2 processes; every file is the same bytes."""
    sign_map = load_map(bundled_map_path())
    results = {}
    for overlap in (False, True):
        settings = pipeline.RunSettings(
            observe=pipeline.ObserveSettings(workers=2, chunk_frames=3), overlap=overlap
        )
        results[overlap] = pipeline.run(
            real_flight.frames_path,
            sign_map,
            tmp_path / f"overlap_{overlap}",
            camera=real_flight.camera,
            gt_path=real_flight.groundtruth_path,
            settings=settings,
            progress=False,
        )
    names = [[p.name for p in results[k].files] for k in (False, True)]
    assert names[0] == names[1]
    assert {"views.png", "errors.png", "result.mcap", "pnp.tum"} <= set(names[0])
    assert "per_frame" in results[True].timing_s and "per_frame" not in results[False].timing_s
    for name in names[0]:
        a, b = (tmp_path / f"overlap_{k}" / name for k in (False, True))
        if name == pipeline.REPORT_NAME:
            assert _untimed_report(a) == _untimed_report(b)
        elif name not in ("report.html", pipeline.RUN_MANIFEST_NAME):  # timings, run_id
            assert a.read_bytes() == b.read_bytes(), name
    manifests = [pipeline.read_run_manifest(tmp_path / f"overlap_{k}") for k in (False, True)]
    assert manifests[0]["files"] == manifests[1]["files"]
    assert all(m["state"] == "complete" for m in manifests)
    assert not [p for p in (tmp_path / "overlap_True").iterdir() if p.name.startswith(".")]


def test_the_estimators_pnp_reuses_the_trackers_calls(real_flight, monkeypatch):
    """Frames observed in processes: the tracker's PnP comes back with each frame and the
    estimator's chained PnP takes it where its prior is the tracker's (not at a chunk's
    start: the tracker starts again there); the poses are the same bits as solved anew."""
    sign_map = load_map(bundled_map_path())
    camera = real_flight.camera
    run = PerFrameRun(sign_map, camera, ("baseline", "pnp"))
    observed = pipeline.observe(
        open_source(real_flight.frames_path),
        sign_map,
        camera,
        pipeline.ObserveSettings(workers=2, chunk_frames=3),
        progress=False,
        on_frame=run.add,
    )
    frames = list(observed.frames)
    assert len(observed.solved_pnp) == len(frames) == 8
    assert all(k.observations is f for k, f in zip(observed.solved_pnp, frames, strict=True))
    # The first frames of chunks 1 and 2 are solved again (the chain has a prior there, the
    # tracker none); after one, the chain takes the tracker's again once a pose comes out
    # the same bits (a cold solve that wins over the warm one).
    assert 2 <= run.pnp_solves < len(frames)
    count = [0]
    real = perframe.solve_frame_pnp

    def counted(*args, **kw):
        count[0] += 1
        return real(*args, **kw)

    monkeypatch.setattr(perframe, "solve_frame_pnp", counted)
    fresh = run_per_frame(frames, sign_map, camera, "pnp")
    assert count[0] == len(frames)
    for a, b in zip(fresh, run.poses["pnp"], strict=True):
        assert a.frame == b.frame and a.inlier_codes == b.inlier_codes
        assert a.world_T_cam.tobytes() == b.world_T_cam.tobytes()
        assert a.cov6.tobytes() == b.cov6.tobytes() and a.rms_px == b.rms_px
    baseline = run_per_frame(frames, sign_map, camera, "baseline")
    for a, b in zip(baseline, run.poses["baseline"], strict=True):
        assert a.reason == b.reason
        assert (a.world_T_cam is None) == (b.world_T_cam is None)
        if a.world_T_cam is not None:
            assert a.world_T_cam.tobytes() == b.world_T_cam.tobytes()


def test_per_frame_poses_of_other_frames_are_refused(real_flight):
    sign_map = load_map(bundled_map_path())
    camera = real_flight.camera
    frames = [
        f
        for f in pipeline.observe(
            open_source(real_flight.frames_path), sign_map, camera, progress=False
        ).frames
    ]
    run = PerFrameRun(sign_map, camera, ("baseline", "pnp"))
    for f in frames[:-1]:
        run.add(f)
    with pytest.raises(ValueError, match="other frames"):
        pipeline.estimate_trajectories(frames, sign_map, camera, progress=False, per_frame_done=run)
    run.add(frames[-1])
    done = pipeline.estimate_trajectories(
        frames, sign_map, camera, progress=False, per_frame_done=run
    )
    again = pipeline.estimate_trajectories(frames, sign_map, camera, progress=False)
    for name in ("baseline", "pnp", "smoothed"):
        assert done.methods[name].world_T_cam.tobytes() == again.methods[name].world_T_cam.tobytes()


def draw_or_die(path: Path, parent_pid: int) -> Path:
    """A plot function that kills any process but the test's (a crash while drawing)."""
    if os.getpid() != parent_pid:
        os._exit(3)
    path.write_bytes(b"drawn")
    return path


def draw_or_fail(path: Path) -> Path:
    raise ValueError(f"cannot draw {path.name}")


def draw_here(path: Path, value: int) -> Path:
    path.write_bytes(np.full(4, value, np.uint8).tobytes())
    return path


def test_plot_processes_give_files_in_order_and_a_dead_ones_plots_are_drawn_here(tmp_path):
    plotters = pipeline.PlotProcesses(2)
    try:
        plotters.start(
            [
                ((draw_here, (tmp_path / "a.png", 1)), (draw_here, (tmp_path / "b.png", 2))),
                ((draw_or_die, (tmp_path / "c.png", os.getpid())),),
            ]
        )
        files = plotters.finish()
    finally:
        plotters.close()
    assert [p.name for p in files] == ["a.png", "b.png", "c.png"]
    assert (tmp_path / "b.png").read_bytes() == bytes([2] * 4)
    assert (tmp_path / "c.png").read_bytes() == b"drawn"  # by this process
    plotters = pipeline.PlotProcesses(1)
    try:
        plotters.start([((draw_or_fail, (tmp_path / "d.png",)),)])
        with pytest.raises(ValueError, match="cannot draw d.png"):
            plotters.finish()
    finally:
        plotters.close(kill=True)


def test_an_inline_run_starts_no_plot_process(monkeypatch, tmp_path):
    """--workers 1 never needed a __main__ guard: no process is started for the plots."""

    def refused(*args, **kw):
        raise AssertionError("a plot process was started")

    monkeypatch.setattr(pipeline, "PlotProcesses", refused)
    flight = simulate_tiny(tmp_path / "flight")
    result = pipeline.run(
        flight.frames_path,
        load_map(bundled_map_path()),
        tmp_path / "run",
        camera=flight.camera,
        settings=pipeline.RunSettings(observe=pipeline.ObserveSettings(workers=1), mcap=False),
        progress=False,
        detector=truth_detector(flight),
    )
    assert {"views.png", "trajectory_3d.png"} <= {p.name for p in result.files}
    assert "per_frame" in result.timing_s  # the per-frame methods still ran as frames came
