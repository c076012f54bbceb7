"""What a new user met at the command line: each bad input one line on stderr, exit 2.

Found by a review as a new user (README and docs/cli.md in hand): argparse's
usage block before its error, OpenCV's own warning beside signpose's line for
a cut PNG, ``--workers -1`` / ``--seed -1`` accepted or crashing, ``--gt-offset
nan`` reported as a ground truth spanning "nan to nan s", ``--out`` naming a
file refused only as "cannot create output folder (File exists)" (``estimate``:
after the whole solve), and ``--fps`` with a video ignored without a word.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import cv2
import pytest
from conftest import simulate_tiny, truth_detector
from signpose.maps.loader import bundled_map_path

from signpose import pipeline
from signpose.cli import CommandLogFormatter, check_fps_input, main
from signpose.cli.run import trust_warnings

MAP = str(bundled_map_path())


def _one_line(err: str, *needles: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err and "usage:" not in err
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def _exit_code(argv: list[str]) -> int:
    with pytest.raises(SystemExit) as info:
        main(argv)
    return info.value.code


@pytest.fixture
def no_pipeline(monkeypatch):
    """Any work at all fails the test: the refusal must come before it."""

    def refuse(*args, **kwargs):
        raise AssertionError("the command started working on a refused input")

    monkeypatch.setattr(pipeline, "run", refuse)
    monkeypatch.setattr(pipeline, "observe", refuse)


def test_a_usage_error_is_one_line_naming_the_option(tmp_path, capsys, no_pipeline):
    argv = ["run", "v.mp4", "--map", MAP, "--out", str(tmp_path / "o"), "--workers", "abc"]
    assert _exit_code(argv) == 2
    _one_line(capsys.readouterr().err, "signpose run: error:", "--workers", "'abc'", "--help")
    assert _exit_code(["run", "v.mp4", "--out", str(tmp_path / "o")]) == 2  # no --map
    _one_line(capsys.readouterr().err, "--map")
    assert _exit_code(["run", "--help"]) == 0  # the usage is still there when asked for
    assert "usage: signpose run" in capsys.readouterr().out


@pytest.mark.parametrize(
    "argv, needles",
    [
        (["run", "v.mp4", "--map", MAP, "--out", "o", "--workers", "-1"], ("--workers", "-1")),
        (["observe", "v.mp4", "--out", "o.jsonl", "--workers", "-2"], ("--workers", "-2")),
        (["simulate", "--out", "s", "--seed", "-1"], ("--seed", "-1")),  # was: internal error
        (["train-detector", "--out", "c.xml", "--seed", "-3"], ("--seed", "-3")),
        (["compare", "d", "--gt", "gt.tum", "--gt-offset", "nan"], ("--gt-offset", "nan")),
        (["run", "v.mp4", "--map", MAP, "--out", "o", "--gt-offset", "inf"], ("--gt-offset",)),
    ],
)
def test_numbers_out_of_range_are_refused_by_name(argv, needles, capsys, no_pipeline):
    assert _exit_code(argv) == 2
    _one_line(capsys.readouterr().err, *needles)


def test_out_naming_a_file_is_refused_before_any_work(tmp_path, capsys, no_pipeline, monkeypatch):
    monkeypatch.chdir(tmp_path)
    Path("taken").write_text("a user's file\n")
    for argv in (
        ["run", "v.mp4", "--map", MAP, "--out", "taken"],
        ["estimate", "obs.jsonl", "--map", MAP, "--camera", "c.yaml", "--out", "taken"],
        ["simulate", "--out", "taken", "--frames", "2"],
        ["batch", "v.mp4", "--map", MAP, "--out", "taken"],
        ["demo", "--out", "taken"],
    ):
        assert _exit_code(argv) == 2, argv
        _one_line(capsys.readouterr().err, f"signpose {argv[0]}: error:", "taken is a file")
    assert Path("taken").read_text() == "a user's file\n"
    assert sorted(os.listdir(".")) == ["taken"]


def test_fps_with_a_video_or_log_file_is_refused(tmp_path, capsys, no_pipeline):
    video = tmp_path / "flight.mp4"
    video.write_bytes(b"\x00" * 64)  # never opened: refused on the option alone
    for command, out in (("run", tmp_path / "o"), ("observe", tmp_path / "o.jsonl")):
        argv = [command, str(video), "--map", MAP, "--out", str(out), "--fps", "25"]
        assert main(argv) == 2
        _one_line(capsys.readouterr().err, str(video), "--fps is for an image folder")
    check_fps_input(tmp_path, 25.0)  # a folder takes it
    check_fps_input(video, None)  # and a file without it is fine


@pytest.fixture
def opencv_warnings_on(monkeypatch):
    """OpenCV as a fresh process has it: warnings on, no OPENCV_LOG_LEVEL."""
    level = cv2.utils.logging.getLogLevel()
    monkeypatch.delenv("OPENCV_LOG_LEVEL", raising=False)
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_WARNING)
    yield
    cv2.utils.logging.setLogLevel(level)


def test_a_cut_png_gives_signpose_s_line_only(tmp_path, capfd, monkeypatch, opencv_warnings_on):
    flight = simulate_tiny(tmp_path / "sim", frames=6, fmt="png")
    monkeypatch.setattr(pipeline, "make_detector", lambda settings: truth_detector(flight))
    frames = Path(flight.frames_path)
    cut = frames / "000003.png"
    cut.write_bytes(cut.read_bytes()[:400])  # OpenCV: "PNG input buffer is incomplete"
    out = tmp_path / "out"
    code = main(
        ["run", str(frames), "--map", MAP, "--camera", str(flight.camera_path),
         "--out", str(out), "--no-plots", "--quiet", "--workers", "1"]
    )  # fmt: skip
    assert code == 2
    err = capfd.readouterr().err  # the file descriptor: OpenCV writes past sys.stderr
    assert "WARN" not in err, err
    _one_line(err, "000003.png: cannot read image; skipped", "5 readable frames")
    assert os.environ["OPENCV_LOG_LEVEL"] == "ERROR"  # for the processes that observe chunks


def _write_json(path: Path, data: dict) -> Path:
    path.write_text(json.dumps(data))
    return path


def _report(tmp_path: Path, bridged: int, misdecoded: list[dict] | None = None) -> Path:
    """report.json of 60 frames, 50 with signs: 10 bridged frames are the sign-free ones."""
    return _write_json(
        tmp_path / "report.json",
        {
            "frames": 60,
            "frames_with_signs": 50,
            "coverage": {"pnp": {"bridged": 0}, "smoothed": {"bridged": bridged}},
            "outliers": {"misdecoded": misdecoded or []},
        },
    )


def test_trust_warnings_name_what_to_check(tmp_path):
    clean = _report(tmp_path, bridged=10)
    refined = _write_json(tmp_path / "map_refined.json", {"moved": [], "moved_sigmas": 3.0})
    assert trust_warnings([clean, refined]) == []
    # Signs in view, every observation rejected: "bridged" frames beyond the sign-free ones.
    (line,) = trust_warnings([_report(tmp_path, bridged=55)])
    assert "smoothed: at least 45 frames with signs in view" in line and "survey" in line
    swapped = [{"code": "0001", "likely_code": "0010"}] * 3 + [
        {"code": "0010", "likely_code": "0001"}
    ]
    (line,) = trust_warnings([_report(tmp_path, bridged=10, misdecoded=swapped)])
    assert "4 readings" in line and "0001 where the map has 0010: 3" in line
    moved = _write_json(tmp_path / "map_refined.json", {"moved": ["0100"], "moved_sigmas": 3.0})
    (line,) = trust_warnings([moved])
    assert "sign(s) 0100 more than 3 survey sigmas" in line
    # a sign past the survey check is named by that check's own warning, not twice
    signs = [{"code": "0100", "moved_sigmas": 3.5}, {"code": "0101", "moved_sigmas": 45.0}]
    both = {"moved": ["0100", "0101"], "moved_sigmas": 3.0, "signs": signs}
    (line,) = trust_warnings([_write_json(tmp_path / "map_refined.json", both)])
    assert "sign(s) 0100 more than" in line and "0101" not in line
    far = {"moved": ["0101"], "moved_sigmas": 3.0, "signs": signs[1:]}
    assert trust_warnings([_write_json(tmp_path / "map_refined.json", far)]) == []
    assert trust_warnings([]) == []  # files of an earlier run in the folder are not read


def test_run_prints_the_warnings_on_stderr_and_exits_0(tmp_path, capsys, monkeypatch):
    report = _report(tmp_path, bridged=55)
    result = pipeline.RunResult(
        out_dir=tmp_path, n_frames=60, coverage={"smoothed": 1.0}, position_rmse_m={},
        comparison=None, comparison_table="", timing_s={}, fps=1.0, problems=(),
        files=(report,),
    )  # fmt: skip
    monkeypatch.setattr(pipeline, "run", lambda *a, **k: result)
    video = tmp_path / "v.mp4"
    video.write_bytes(b"\x00")
    argv = ["run", str(video), "--map", MAP, "--out", str(tmp_path / "o"), "-q"]
    assert main(argv) == 0
    _one_line(capsys.readouterr().err, "signpose run: warning: smoothed: at least 45 frames")


def test_library_warnings_read_like_the_command_s_own_lines():
    record = logging.LogRecord(
        "signpose.estimator.refine", logging.WARNING, __file__, 1,
        "map_refined.yaml not written: %d frames", (60,), None,
    )  # fmt: skip
    line = CommandLogFormatter("run").format(record)
    assert line == "signpose run: warning: map_refined.yaml not written: 60 frames"
    verbose = CommandLogFormatter("run", with_logger=True).format(record)
    assert verbose.startswith("signpose run: warning [signpose.estimator.refine]: map_refined")
