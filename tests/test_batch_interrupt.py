"""Issue 15 #17: an interrupted batch writes summary.csv with every flight's state.

The finished flights keep their rows, the running one is ``interrupted``, the
queued ones ``not_started``; a rerun runs exactly those.
"""

from __future__ import annotations

import csv
import signal
import time
from types import SimpleNamespace

import pytest
from signpose.maps.loader import bundled_map_path

from signpose import batch
from signpose.cli import Terminated


def _inputs(tmp_path, n: int) -> list[str]:
    site = tmp_path / "site"
    site.mkdir()
    paths = []
    for i in range(n):
        path = site / f"f{i}.mp4"
        path.write_bytes(b"not read: the run function is replaced")
        paths.append(str(path))
    return paths


def _fake_run(interrupt_on: str | None, seen: list[str], error=KeyboardInterrupt):
    def run(input_path, *args, **kwargs):
        seen.append(input_path.stem)
        if input_path.stem == interrupt_on:
            raise error()
        return SimpleNamespace(
            problems=(),
            n_frames=3,
            coverage={"smoothed": 1.0},
            position_rmse_m={},
            status={},
            comparison=None,
        )

    return run


def _states(out) -> dict[str, str]:
    with open(out / batch.SUMMARY_NAME, newline="") as f:
        return {r["flight"]: r["status"] for r in csv.DictReader(f)}


@pytest.mark.parametrize("error", [KeyboardInterrupt, Terminated])
def test_interrupt_marks_running_and_queued_and_a_rerun_does_them(tmp_path, monkeypatch, error):
    inputs = _inputs(tmp_path, 4)
    out = tmp_path / "out"
    seen: list[str] = []
    monkeypatch.setattr(batch, "run", _fake_run("f1", seen, error))
    with pytest.raises(error):
        batch.run_batch(inputs, bundled_map_path(), out, progress=False, plots=False)
    assert seen == ["f0", "f1"]  # the queued flights never started
    assert _states(out) == {
        "f0": "ok",
        "f1": "interrupted",
        "f2": "not_started",
        "f3": "not_started",
    }
    assert not (out / "f1" / batch.DONE_MARKER).exists()

    seen.clear()
    monkeypatch.setattr(batch, "run", _fake_run(None, seen))
    outcomes = batch.run_batch(inputs, bundled_map_path(), out, progress=False, plots=False)
    assert seen == ["f1", "f2", "f3"]
    assert [o.skipped for o in outcomes] == [True, False, False, False]
    assert set(_states(out).values()) == {"ok"}


def _slow_runner(job: batch.FlightJob) -> batch.FlightOutcome:
    signal.signal(signal.SIGTERM, signal.SIG_IGN)  # a worker that goes on after SIGTERM
    time.sleep(60)  # stopped long before: the test fails on a pool that waits for it
    return batch.FlightOutcome(job.flight, batch.FlightStatus.OK)


def test_interrupt_stops_a_pool_at_once(tmp_path, monkeypatch):
    inputs = _inputs(tmp_path, 12)
    out = tmp_path / "out"

    def interrupted_wait(futures):
        while not any(f.running() for f in futures):
            time.sleep(0.01)
        time.sleep(0.2)  # the workers are inside their flights
        raise KeyboardInterrupt

    monkeypatch.setattr(batch, "as_completed", interrupted_wait)
    t0 = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        batch.run_batch(
            inputs, bundled_map_path(), out, progress=False, jobs=2, runner=_slow_runner
        )
    assert time.monotonic() - t0 < 20  # not the 60 s of a flight: SIGKILL after the grace
    states = _states(out)
    assert list(states) == [f"f{i}" for i in range(12)]
    assert set(states.values()) <= {"interrupted", "not_started"}
    assert states["f11"] == "not_started"  # 2 workers take at most 2 + 3 queued calls
    # The pool hands a few calls ahead to its workers; those count as started.
    assert "interrupted" in states.values()
