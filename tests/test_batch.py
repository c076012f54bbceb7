"""Batch runs: parallel flights, a bad flight, rerun skips, Dask, and the demo end to end."""

from __future__ import annotations

import csv
import shutil

import pytest
from conftest import TruthDetector, simulate_tiny, truth_detector
from signpose.maps.loader import bundled_map_path

from signpose import batch, pipeline
from signpose.cli import main
from signpose.core.errors import InputError

MAP = str(bundled_map_path())


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    """Two simulated flights (video + camera.yaml + groundtruth.tum each) and a corrupt one."""
    root = tmp_path_factory.mktemp("flights")
    a = simulate_tiny(root / "a", frames=8)
    b = simulate_tiny(root / "b", frames=8, seed=1, trajectory="orbit")
    bad = root / "bad"
    bad.mkdir()
    (bad / "video.mp4").write_bytes(b"\x00" * 4096)
    shutil.copy(a.camera_path, bad / "camera.yaml")
    return [a, b], [a.frames_path, b.frames_path, bad / "video.mp4"]


@pytest.fixture
def replay(flights, monkeypatch):
    """Each flight's detector replays that flight's truth (found by the frame size check)."""
    sims, _ = flights
    by_dir = {str(s.out_dir.resolve()): s for s in sims}
    real_observe = pipeline.observe

    def observe(source, *args, **kw):
        sim = by_dir[str(source.path.resolve().parent)]
        kw["detector"] = truth_detector(sim)
        return real_observe(source, *args, **kw)

    monkeypatch.setattr(pipeline, "observe", observe)


def _summary(out):
    with open(out / batch.SUMMARY_NAME) as f:
        return {row["flight"]: row for row in csv.DictReader(f)}


def test_flight_names_are_unique():
    assert batch.flight_names(["x/a/video.mp4", "x/b/video.mp4", "c.mcap"]) == [
        "a_video",
        "b_video",
        "c",
    ]
    assert batch.flight_names(["a/v.mp4", "a/v.mkv"]) == ["a_v", "a_v_2"]


def test_batch_with_a_bad_flight_then_rerun(flights, replay, tmp_path, capsys):
    _, inputs = flights
    out = tmp_path / "out"
    code = main(
        ["batch", *map(str, inputs), "--map", MAP, "--out", str(out), "--jobs", "2", "--no-plots",
         "-q"]
    )  # fmt: skip
    assert code == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "bad_video" in err and "Traceback" not in err
    rows = _summary(out)
    assert list(rows) == ["a_video", "b_video", "bad_video"]
    assert rows["a_video"]["status"] == "ok" and rows["b_video"]["status"] == "ok"
    assert rows["a_video"]["frames"] == "8"
    assert float(rows["a_video"]["coverage_smoothed"]) == pytest.approx(1.0)
    assert float(rows["a_video"]["position_rmse_m_pnp"]) < 0.05  # groundtruth.tum beside it
    assert rows["bad_video"]["status"] == "failed"
    assert "video.mp4" in rows["bad_video"]["message"]
    assert (out / "a_video" / batch.DONE_MARKER).is_file()
    assert not (out / "bad_video" / batch.DONE_MARKER).exists()
    # Rerun: finished flights are skipped, the bad one is tried again.
    seen = []

    def runner(job):
        seen.append(job.flight)
        return batch.FlightOutcome(job.flight, batch.FlightStatus.FAILED, message="still bad")

    outcomes = batch.run_batch(inputs, MAP, out, progress=False, runner=runner)
    assert seen == ["bad_video"]
    assert [o.skipped for o in outcomes] == [True, True, False]
    assert _summary(out)["a_video"]["skipped"] == "yes"


def _fake_runner(job: batch.FlightJob) -> batch.FlightOutcome:
    return batch.FlightOutcome(
        job.flight, batch.FlightStatus.OK, frames=3, coverage={"smoothed": 1.0}
    )


def test_dask_local_cluster(tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    with (
        distributed.LocalCluster(
            n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None
        ) as cluster,
    ):
        outcomes = batch.run_batch(
            [tmp_path / "f1.mp4", tmp_path / "f2.mp4"],
            MAP,
            tmp_path / "out",
            scheduler=cluster.scheduler_address,
            progress=False,
            runner=_fake_runner,
        )
    assert [o.flight for o in outcomes] == ["f1", "f2"]
    assert all(o.status == "ok" for o in outcomes)
    assert set(_summary(tmp_path / "out")) == {"f1", "f2"}


def test_scheduler_without_dask_says_how_to_install(monkeypatch, tmp_path):
    import builtins

    real_import = builtins.__import__

    def no_dask(name, *args, **kw):
        if name.startswith("dask"):
            raise ImportError(name)
        return real_import(name, *args, **kw)

    monkeypatch.setattr(builtins, "__import__", no_dask)
    with pytest.raises(InputError, match=r"pip install signpose\[dask\]"):
        batch.run_batch([tmp_path / "f.mp4"], MAP, tmp_path / "out", scheduler="tcp://127.0.0.1:1")


def test_demo_end_to_end(monkeypatch, tmp_path, capsys):
    from signpose.io.boxes import read_boxes

    real_observe = pipeline.observe

    def observe(source, *args, **kw):
        boxes = read_boxes(source.path.parent / "boxes.jsonl")
        kw["detector"] = TruthDetector(boxes)
        return real_observe(source, *args, **kw)

    monkeypatch.setattr(pipeline, "observe", observe)
    out = tmp_path / "demo-out"
    code = main(
        ["demo", "--out", str(out), "--frames", "10", "--width", "320", "--height", "240", "-q"]
    )
    assert code == 0
    printed = capsys.readouterr().out
    assert "result.mcap" in printed and str(out) in printed
    for name in ("result.mcap", "report.json", "trajectory_3d.png", "errors.png"):
        assert (out / name).is_file(), name
    assert (out / "flight" / "groundtruth.tum").is_file()


def _workers_runner(job: batch.FlightJob) -> batch.FlightOutcome:
    # frames carries the observing processes the flight was given.
    return batch.FlightOutcome(job.flight, batch.FlightStatus.OK, frames=job.workers)


@pytest.mark.parametrize(("jobs", "workers"), [(1, 0), (2, 1)])
def test_parallel_flights_observe_in_one_process_each(tmp_path, jobs, workers):
    # --jobs 2 means two processes on the machine, not two flights x two chunk workers.
    inputs = [tmp_path / "f1.mp4", tmp_path / "f2.mp4"]
    outcomes = batch.run_batch(
        inputs, MAP, tmp_path / "out", jobs=jobs, progress=False, runner=_workers_runner
    )
    assert [o.frames for o in outcomes] == [workers, workers]
