"""``batch --scheduler`` on a stock Dask worker: several threads, plots on (issue 16 item 1)."""

from __future__ import annotations

import csv

import pytest
from conftest import simulate_tiny, truth_detector
from signpose.maps.loader import bundled_map_path

from signpose import batch, pipeline
from signpose.cli import main

MAP = str(bundled_map_path())
THREADS_PER_WORKER = 2
# What must be the same whichever way the flights ran.
COMPARED = ("observations.jsonl", "baseline.tum", "pnp.tum", "smoothed.tum", "trajectory.csv")


@pytest.fixture(scope="module")
def three_flights(tmp_path_factory):
    root = tmp_path_factory.mktemp("flights")
    return [
        simulate_tiny(root / "a", frames=6),
        simulate_tiny(root / "b", frames=6, seed=1, trajectory="orbit"),
        simulate_tiny(root / "c", frames=6, seed=2),
    ]


@pytest.fixture
def replay(three_flights, monkeypatch):
    """Each flight's detector replays that flight's truth (the worker threads share the patch)."""
    by_dir = {str(s.out_dir.resolve()): s for s in three_flights}
    real_observe = pipeline.observe

    def observe(source, *args, **kw):
        kw["detector"] = truth_detector(by_dir[str(source.path.resolve().parent)])
        return real_observe(source, *args, **kw)

    monkeypatch.setattr(pipeline, "observe", observe)


def test_batch_on_a_local_cluster_with_two_threads_per_worker(three_flights, replay, tmp_path):
    distributed = pytest.importorskip("dask.distributed")
    inputs = [str(s.frames_path) for s in three_flights]
    on_dask, one_by_one = tmp_path / "dask", tmp_path / "jobs1"
    with distributed.LocalCluster(
        n_workers=1,
        threads_per_worker=THREADS_PER_WORKER,
        processes=False,  # one worker process, its threads run flights side by side
        dashboard_address=None,
    ) as cluster:
        code = main(
            ["batch", *inputs, "--map", MAP, "--out", str(on_dask),
             "--scheduler", cluster.scheduler_address, "-q"]
        )  # fmt: skip
    assert code == 0
    with open(on_dask / batch.SUMMARY_NAME) as f:
        rows = list(csv.DictReader(f))
    assert [r["status"] for r in rows] == ["ok", "ok", "ok"], [r["message"] for r in rows]
    names = [r["flight"] for r in rows]
    for name in names:  # the plots that crashed matplotlib when drawn from two threads
        for plot in ("errors.png", "views.png", "trajectory_3d.png"):
            assert (on_dask / name / plot).stat().st_size > 0, (name, plot)
    assert main(["batch", *inputs, "--map", MAP, "--out", str(one_by_one), "--no-plots", "-q"]) == 0
    for name in names:
        for file in COMPARED:
            a, b = on_dask / name / file, one_by_one / name / file
            assert a.read_bytes() == b.read_bytes(), (name, file)
