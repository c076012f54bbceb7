"""Batch reruns that are right (issue 16 item 2): fingerprints, --force, --root names, summary rows.

Flights are tiny simulated ones whose detector replays the truth (boxes.jsonl
beside each input), without plots, so each takes well under a second.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import pytest
from conftest import TruthDetector, simulate_tiny
from signpose.maps.loader import bundled_map_path

from signpose import batch, pipeline
from signpose.cli import main
from signpose.fingerprint import FINGERPRINT_KEY
from signpose.io.boxes import read_boxes


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    root = tmp_path_factory.mktemp("sims")
    simulate_tiny(root / "f1", frames=5)
    simulate_tiny(root / "f2", frames=5, seed=1, trajectory="orbit")
    simulate_tiny(root / "f3", frames=5, seed=2)
    return root


@pytest.fixture
def site(simulated, tmp_path, monkeypatch):
    """A copy of the three flights (each test may change its files) and of the map."""
    root = tmp_path / "site"
    shutil.copytree(simulated, root)
    shutil.copy(bundled_map_path(), tmp_path / "map.yaml")
    real_observe = pipeline.observe

    def observe(source, *args, **kw):
        kw["detector"] = TruthDetector(read_boxes(source.path.parent / "boxes.jsonl"))
        return real_observe(source, *args, **kw)

    monkeypatch.setattr(pipeline, "observe", observe)
    return root


def _batch(site: Path, out: Path, *inputs: str, extra: tuple[str, ...] = ()) -> int:
    paths = [str(site / name / "video.mp4") for name in inputs]
    argv = ["batch", *paths, "--map", str(site.parent / "map.yaml"), "--out", str(out)]
    return main([*argv, "--root", str(site), "--no-plots", "-q", *extra])


def _rows(out: Path) -> list[dict]:
    with open(out / batch.SUMMARY_NAME, newline="") as f:
        return list(csv.DictReader(f))


def _skipped(out: Path) -> dict[str, bool]:
    return {r["flight"]: r["skipped"] == "yes" for r in _rows(out)}


def test_unchanged_flights_are_skipped_changed_ones_redone(site, tmp_path):
    out = tmp_path / "out"
    assert _batch(site, out, "f1", "f2", "f3") == 0
    assert _skipped(out) == {"f1_video": False, "f2_video": False, "f3_video": False}
    marker = json.loads((out / "f1_video" / batch.DONE_MARKER).read_text())
    assert len(marker[FINGERPRINT_KEY]) == 64
    assert _batch(site, out, "f1", "f2", "f3") == 0  # nothing changed
    assert _skipped(out) == {"f1_video": True, "f2_video": True, "f3_video": True}
    with open(site / "f2" / "camera.yaml", "a") as f:  # another calibration for f2 only
        f.write("# recalibrated\n")
    assert _batch(site, out, "f1", "f2", "f3") == 0
    assert _skipped(out) == {"f1_video": True, "f2_video": False, "f3_video": True}
    with open(site.parent / "map.yaml", "a") as f:  # the map changed: every flight
        f.write("# resurveyed\n")
    assert _batch(site, out, "f1", "f2", "f3") == 0
    assert not any(_skipped(out).values())
    assert _batch(site, out, "f1", "f2", "f3", extra=("--fps", "12")) == 0  # a setting
    assert not any(_skipped(out).values())


def test_force_redoes_everything_and_old_markers_are_redone(site, tmp_path):
    out = tmp_path / "out"
    assert _batch(site, out, "f1", "f2") == 0
    assert _batch(site, out, "f1", "f2", extra=("--force",)) == 0
    assert _skipped(out) == {"f1_video": False, "f2_video": False}
    marker = out / "f1_video" / batch.DONE_MARKER  # written before fingerprints existed
    data = json.loads(marker.read_text())
    del data[FINGERPRINT_KEY]
    marker.write_text(json.dumps(data))
    assert _batch(site, out, "f1", "f2") == 0
    assert _skipped(out) == {"f1_video": False, "f2_video": True}


def test_names_stable_under_root_and_summary_keeps_earlier_rows(site, tmp_path):
    out = tmp_path / "out"
    assert _batch(site, out, "f1", "f2") == 0
    assert _batch(site, out, "f3") == 0  # alone: same naming, no new folder for f1/f2
    assert [r["flight"] for r in _rows(out)] == ["f1_video", "f2_video", "f3_video"]
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == [
        "f1_video",
        "f2_video",
        "f3_video",
    ]
    before = _rows(out)
    (site / "f1" / "video.mp4").touch()  # f1 "changed": its row is updated in place
    assert _batch(site, out, "f1") == 0
    after = _rows(out)
    assert [r["flight"] for r in after] == ["f1_video", "f2_video", "f3_video"]
    assert after[1:] == before[1:]
    assert after[0]["skipped"] == "" and after[0]["status"] == "ok"


def test_flight_names_below_a_root(tmp_path):
    root = tmp_path / "season"
    names = batch.flight_names([root / "f1" / "video.mp4", root / "day2" / "log"], root)
    assert names == ["f1_video", "day2_log"]
    with pytest.raises(batch.InputError, match="not inside --root"):
        batch.flight_names([tmp_path / "elsewhere.mp4"], root)
    with pytest.raises(batch.InputError, match="share the flight name"):
        batch.flight_names([root / "a" / "v.mp4", root / "a" / "v.mkv"], root)
