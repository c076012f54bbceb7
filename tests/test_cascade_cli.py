"""``--cascade`` wherever a detector runs (issue 16 item 3), exit 2 for a malformed XML."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import pytest
from conftest import TruthDetector, simulate_tiny
from signpose.frontend.detector import SignDetector, bundled_cascade_path
from signpose.maps.loader import bundled_map_path

from signpose import batch, pipeline
from signpose.cli import main
from signpose.core.errors import InputError
from signpose.io.boxes import read_boxes

MAP = str(bundled_map_path())
MALFORMED = '<?xml version="1.0"?>\n<opencv_storage><cascade><stageType>BOOST</stageType'


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    return simulate_tiny(tmp_path_factory.mktemp("flight") / "f", frames=4)


@pytest.fixture
def bad_xml(tmp_path):
    path = tmp_path / "bad.xml"
    path.write_text(MALFORMED)
    return path


@pytest.fixture
def cascade_copy(tmp_path):
    return shutil.copy(bundled_cascade_path(), tmp_path / "mine.xml")


@pytest.fixture
def seen_cascades(monkeypatch):
    """The cascade_path of every observe call; the detector replays the truth."""
    seen: list[str] = []
    real_observe = pipeline.observe

    def observe(source, sign_map, camera, settings=None, *args, **kw):
        seen.append(settings.cascade_path)
        kw["detector"] = TruthDetector(read_boxes(source.path.parent / "boxes.jsonl"))
        return real_observe(source, sign_map, camera, settings, *args, **kw)

    monkeypatch.setattr(pipeline, "observe", observe)
    return seen


def test_a_malformed_cascade_is_bad_input():
    with pytest.raises(InputError, match="not a readable OpenCV cascade XML"):
        SignDetector(bundled_map_path())  # YAML, not XML: OpenCV's parser fails


@pytest.mark.parametrize("command", ["run", "observe", "batch", "detect", "demo"])
def test_malformed_cascade_exits_2_with_one_line(command, flight, bad_xml, tmp_path, capsys):
    out = tmp_path / "out"
    argv = {
        "run": ["run", str(flight.frames_path), "--map", MAP, "--out", str(out)],
        "observe": ["observe", str(flight.frames_path), "--out", str(tmp_path / "o.jsonl")],
        "batch": ["batch", str(flight.frames_path), "--map", MAP, "--out", str(out)],
        "detect": ["detect", str(flight.frames_path)],  # the cascade is read first
        "demo": ["demo", "--out", str(out), "--frames", "2", "--width", "160", "--height", "120"],
    }[command]
    if command in ("run", "observe"):
        argv += ["--camera", str(flight.camera_path)]
    code = main([*argv, "--cascade", str(bad_xml), "-q"] if command != "detect" else
                [*argv, "--cascade", str(bad_xml)])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "bad.xml: not a readable OpenCV cascade XML" in lines[0], err
    assert "internal error" not in err


def test_run_observe_demo_use_the_given_cascade(flight, cascade_copy, seen_cascades, tmp_path):
    run_out = tmp_path / "run"
    common = ["--camera", str(flight.camera_path), "--cascade", str(cascade_copy), "-q"]
    assert main(["run", str(flight.frames_path), "--map", MAP, "--out", str(run_out),
                 "--no-plots", *common]) == 0  # fmt: skip
    report = json.loads((run_out / "report.json").read_text())
    assert report["pipeline"]["settings"]["observe"]["cascade_path"] == str(cascade_copy)
    assert main(["observe", str(flight.frames_path), "--map", MAP,
                 "--out", str(tmp_path / "o.jsonl"), *common]) == 0  # fmt: skip
    demo = ["demo", "--out", str(tmp_path / "demo"), "--frames", "4", "--width", "320"]
    assert main([*demo, "--height", "240", "--cascade", str(cascade_copy), "-q"]) == 0
    assert seen_cascades == [str(cascade_copy)] * 3


def test_batch_passes_the_cascade_and_a_new_one_redoes_the_flights(flight, cascade_copy, tmp_path):
    jobs: list[batch.FlightJob] = []

    def runner(job):
        jobs.append(job)
        return batch.FlightOutcome(job.flight, batch.FlightStatus.OK)

    out = tmp_path / "out"
    batch.run_batch([flight.frames_path], MAP, out, progress=False, runner=runner,
                    cascade_path=cascade_copy)  # fmt: skip
    plain = batch.run_batch([flight.frames_path], MAP, out, progress=False, runner=runner)
    assert jobs[0].cascade_path == str(cascade_copy.resolve()) and jobs[1].cascade_path == ""
    assert jobs[0].fingerprint != jobs[1].fingerprint
    assert not plain[0].skipped


def test_an_incompatible_cascade_is_bad_input(tmp_path):
    body = Path(cv2.data.haarcascades) / "haarcascade_fullbody.xml"  # 14 x 28 windows
    with pytest.raises(InputError, match="14x28 px, not square"):
        SignDetector(body)
    short = tmp_path / "short.xml"  # the bundled cascade with features outside its window
    text = bundled_cascade_path().read_text(encoding="utf-8")
    short.write_text(text.replace("<height>24</height>", "<height>12</height>", 1))
    with pytest.raises(InputError, match="not a readable OpenCV cascade XML .*HAAR feature"):
        SignDetector(short)
