"""Bad input through the CLI: exit code 2 (130 on Ctrl-C), one line on stderr, no traceback."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import simulate_tiny, truth_detector
from signpose.estimator.camera import pinhole_camera
from signpose.maps.loader import bundled_map_path

from signpose import pipeline
from signpose.cli import main
from signpose.io import mcap as mcap_io
from signpose.io.camera_file import write_camera_info
from signpose.io.observations import read_observations

MAP = str(bundled_map_path())


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    return simulate_tiny(tmp_path_factory.mktemp("flight"), frames=12)


@pytest.fixture
def replay(flight, monkeypatch):
    """The pipeline's detector replays the simulator's truth (no trained cascade needed)."""
    made = []

    def make(settings):
        made.append(truth_detector(flight))
        return made[-1]

    monkeypatch.setattr(pipeline, "make_detector", make)
    return made


def _one_error_line(capsys, *needles: str) -> str:
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def test_run_ok(flight, replay, tmp_path, capsys):
    out = tmp_path / "out"
    code = main(
        ["run", str(flight.frames_path), "--map", MAP, "--camera", str(flight.camera_path),
         "--out", str(out), "--quiet", "--workers", "1"]
    )  # fmt: skip
    assert code == 0
    assert capsys.readouterr().err == ""
    assert (out / "report.json").is_file()


def test_truncated_video(flight, replay, tmp_path, capsys):
    import cv2

    from signpose.io.sources import open_source

    # A streamable container, cut in half.
    full = tmp_path / "full.avi"
    frames = list(open_source(flight.frames_path))
    writer = cv2.VideoWriter(str(full), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (320, 240))
    for f in frames:
        writer.write(f.image)
    writer.release()
    cut = tmp_path / "cut.avi"
    cut.write_bytes(full.read_bytes()[: full.stat().st_size // 2])
    out = tmp_path / "out"
    code = main(
        ["run", str(cut), "--map", MAP, "--camera", str(flight.camera_path), "--out", str(out),
         "--no-plots", "--quiet", "--workers", "1"]
    )  # fmt: skip
    assert code == 2
    line = _one_error_line(capsys, "cut.avi", "video stopped at frame", "of 12")
    n = len(read_observations(out / "observations.jsonl"))
    assert 0 < n < 12
    assert f"the {n} readable frames were processed" in line
    report = json.loads((out / "report.json").read_text())
    assert report["pipeline"]["frames"] == n
    assert "video stopped at frame" in report["pipeline"]["problems"][0]


def test_truncated_mcap(tmp_path, replay, flight, capsys):
    from signpose.io.sources import open_source

    path = tmp_path / "flight.mcap"
    with mcap_io.McapFrameWriter(path, flight.camera, chunk_size=8192) as w:
        for f in open_source(flight.frames_path):
            w.write(f.index, f.stamp_ns, f.image)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size * 2 // 3])
    out = tmp_path / "out"
    code = main(
        [
            "run",
            str(cut),
            "--map",
            MAP,
            "--out",
            str(out),
            "--no-plots",
            "--quiet",
            "--workers",
            "1",
        ]
    )
    assert code == 2
    _one_error_line(capsys, "cut.mcap", "log stopped after", "truncated or corrupt")
    n = len(read_observations(out / "observations.jsonl"))
    assert 0 < n < 12


def _mcap_with_topics(path: Path, topics: list[tuple[str, str]]) -> None:
    img = np.zeros((240, 320), np.uint8)
    with mcap_io.McapJsonWriter(path) as w:
        for topic, schema in topics:
            msg = (
                mcap_io.compressed_image(0, img)
                if schema == "CompressedImage"
                else mcap_io.pose_in_frame(0, "w", np.eye(4))
            )
            w.write(topic, schema, msg, 0)


@pytest.mark.parametrize(
    ("topics", "arg", "needles"),
    [
        ([("/pose", "PoseInFrame")], [], ["no image topic", "/pose (foxglove.PoseInFrame)"]),
        (
            [("/a/image", "CompressedImage"), ("/b/image", "CompressedImage")],
            [],
            ["several image topics", "/a/image, /b/image", "--topic"],
        ),
        (
            [("/a/image", "CompressedImage")],
            ["--topic", "/cam"],
            ["no topic '/cam'", "image topics in the log: /a/image"],
        ),
    ],
    ids=["no_image_topic", "several_topics", "wrong_topic"],
)
def test_mcap_topic_problems(tmp_path, flight, capsys, topics, arg, needles):
    path = tmp_path / "log.mcap"
    _mcap_with_topics(path, topics)
    code = main(
        ["run", str(path), "--map", MAP, "--camera", str(flight.camera_path), "--out",
         str(tmp_path / "out"), "--quiet", "--workers", "1", *arg]
    )  # fmt: skip
    assert code == 2
    _one_error_line(capsys, "log.mcap", *needles)


def test_camera_size_mismatch(flight, replay, tmp_path, capsys):
    cam = tmp_path / "cam.yaml"
    write_camera_info(cam, pinhole_camera(640, 480))
    out = tmp_path / "out"
    code = main(
        ["run", str(flight.frames_path), "--map", MAP, "--camera", str(cam), "--out", str(out),
         "--quiet", "--workers", "1"]
    )  # fmt: skip
    assert code == 2
    _one_error_line(capsys, "images are 320x240", "640x480")
    assert not (out / "observations.jsonl").exists()
    assert list(out.iterdir()) == []  # no half-written file


def test_map_codes_never_seen(flight, replay, tmp_path, capsys):
    other = tmp_path / "other.yaml"
    other.write_text(
        'frame: x\nsigns:\n  - code: "1111"\n    center_m: [0, 0, 10]\n'
        "    diameter_m: 0.8\n    sigma_m: 0.01\n"
    )
    code = main(
        ["run", str(flight.frames_path), "--map", str(other), "--camera",
         str(flight.camera_path), "--out", str(tmp_path / "out"), "--quiet", "--workers", "1"]
    )  # fmt: skip
    assert code == 2
    _one_error_line(capsys, "other.yaml", "none of the map's codes (1111)")


@pytest.mark.parametrize("kind", ["empty_folder", "empty_file"])
def test_empty_input(tmp_path, capsys, kind, flight):
    if kind == "empty_folder":
        inp = tmp_path / "frames"
        inp.mkdir()
    else:
        inp = tmp_path / "flight.mp4"
        inp.write_bytes(b"")
    code = main(
        ["run", str(inp), "--map", MAP, "--camera", str(flight.camera_path), "--out",
         str(tmp_path / "out"), "--quiet", "--workers", "1"]
    )  # fmt: skip
    assert code == 2
    _one_error_line(capsys, inp.name)


def test_unwritable_output(flight, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    code = main(
        ["run", str(flight.frames_path), "--map", MAP, "--camera", str(flight.camera_path),
         "--out", str(blocker / "out"), "--quiet", "--workers", "1"]
    )  # fmt: skip
    assert code == 2
    _one_error_line(capsys, "cannot create output folder")


def test_ctrl_c(flight, monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(
        pipeline, "make_detector", lambda settings: truth_detector(flight, interrupt_at=4)
    )
    out = tmp_path / "out"
    code = main(
        ["run", str(flight.frames_path), "--map", MAP, "--camera", str(flight.camera_path),
         "--out", str(out), "--quiet", "--workers", "1"]
    )  # fmt: skip
    assert code == 130
    _one_error_line(capsys, "interrupted")
    assert [f.frame for f in read_observations(out / "observations.jsonl")] == [0, 1, 2, 3]
    assert sorted(p.name for p in out.iterdir()) == ["observations.jsonl"]


def test_observe_command(flight, replay, tmp_path, capsys):
    out = tmp_path / "obs.jsonl"
    code = main(
        ["observe", str(flight.frames_path), "--out", str(out), "--map", MAP, "--camera",
         str(flight.camera_path), "--quiet", "--workers", "1"]
    )  # fmt: skip
    assert code == 0
    assert len(read_observations(out)) == 12
    code = main(["observe", str(flight.frames_path), "--out", str(tmp_path / "no" / "o.jsonl")])
    assert code == 2
    _one_error_line(capsys, "folder does not exist")


@pytest.mark.parametrize("value", ["-0.01", "0.5", "nan"])
def test_focal_sigma_out_of_range(flight, replay, tmp_path, capsys, value):
    code = main(
        ["run", str(flight.frames_path), "--map", MAP, "--camera", str(flight.camera_path),
         "--out", str(tmp_path / "out"), "--quiet", "--workers", "1", "--focal-sigma", value]
    )  # fmt: skip
    assert code == 2
    _one_error_line(capsys, f"--focal-sigma {float(value)}", "fraction in [0, 0.5)")
    assert not (tmp_path / "out" / "report.json").exists()


def test_focal_sigma_widens_the_reported_sigmas(flight, replay, tmp_path):
    outs = {}
    for rel in ("0", "0.02"):
        out = tmp_path / f"out{rel}"
        args = ["run", str(flight.frames_path), "--map", MAP, "--camera", str(flight.camera_path),
                "--out", str(out), "--quiet", "--workers", "1", "--no-plots",
                "--focal-sigma", rel]  # fmt: skip
        assert main(args) == 0
        report = json.loads((out / "report.json").read_text())
        assert report["settings"]["focal_sigma_rel"] == float(rel)
        rows = [r.split(",") for r in (out / "trajectory.csv").read_text().splitlines()]
        col = {name: i for i, name in enumerate(rows[0])}
        smoothed = [r for r in rows[1:] if r[col["method"]] == "smoothed"]
        outs[rel] = np.array([[float(r[col[f"sigma_{a}_m"]]) for a in "xyz"] for r in smoothed])
    # 2 % of the camera's distance to the signs (several metres), in quadrature
    grown = np.sqrt(np.sum(outs["0.02"] ** 2 - outs["0"] ** 2, axis=1))
    assert np.all(np.isfinite(grown)) and np.all(grown > 0.05)
