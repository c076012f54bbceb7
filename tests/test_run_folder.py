"""Issue 15 #20: a run folder is one unit (run.json names the run it holds)."""

from __future__ import annotations

import json

import pytest
from conftest import simulate_tiny, truth_detector
from signpose.maps.loader import bundled_map_path, load_map

from signpose import pipeline


def _run(flight, out, **settings):
    return pipeline.run(
        flight.frames_path,
        load_map(bundled_map_path()),
        out,
        camera=flight.camera,
        settings=pipeline.RunSettings(**settings),
        progress=False,
        detector=truth_detector(flight),
    )


def _report_run_id(out) -> str:
    return json.loads((out / pipeline.REPORT_NAME).read_text())["pipeline"]["run_id"]


def test_a_killed_rerun_is_marked_and_the_next_run_removes_the_older_runs_files(
    tmp_path, monkeypatch
):
    flight = simulate_tiny(tmp_path / "flight", frames=8)
    out = tmp_path / "out"
    first = _run(flight, out)
    manifest = pipeline.read_run_manifest(out)
    assert manifest["state"] == "complete"
    assert manifest["run_id"] == _report_run_id(out)
    assert set(manifest["files"]) == {p.name for p in first.files}
    assert {"result.mcap", "views.png", "run.json"} <= set(manifest["files"])

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    real_estimate = pipeline.estimate_trajectories
    monkeypatch.setattr(pipeline, "estimate_trajectories", killed)
    with pytest.raises(KeyboardInterrupt):
        _run(flight, out, plots=False, mcap=False)
    mixed = pipeline.read_run_manifest(out)
    assert mixed["state"] == "running"  # the folder says it holds a mix
    assert mixed["run_id"] != manifest["run_id"] == _report_run_id(out)  # report.json is older
    assert set(mixed["earlier_files"]) == set(manifest["files"]) - {"run.json"}

    monkeypatch.setattr(pipeline, "estimate_trajectories", real_estimate)
    (out / "notes.txt").write_text("the user's own file")
    third = _run(flight, out, plots=False, mcap=False)
    done = pipeline.read_run_manifest(out)
    assert done["state"] == "complete"
    assert done["earlier_files"] == []
    assert done["run_id"] == _report_run_id(out)
    assert set(done["files"]) == {p.name for p in third.files}
    assert not (out / "result.mcap").exists()  # the older run's files are gone
    assert not list(out.glob("*.png"))
    assert (out / "notes.txt").is_file()  # what no run wrote stays
    on_disk = {p.name for p in out.iterdir() if not p.name.startswith(".")}
    assert on_disk == set(done["files"]) | {"notes.txt"}
