"""One CLI (issue 16 item 7): global options anywhere, quiet broken pipes, exit codes by rule."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest
from signpose.maps.loader import bundled_map_path

from signpose import batch
from signpose.cli import COMMANDS, EXIT_INPUT, EXIT_INTERNAL, EXIT_OK, build_parser, main
from signpose.cli.batch import exit_code
from signpose.cli.run import print_result
from signpose.core.errors import InputError
from signpose.pipeline import RunResult

MAP = str(bundled_map_path())
RUN = ["run", "in.mp4", "--map", "m.yaml", "--out", "o"]
ENTRY = "import sys; from signpose.cli import main; sys.exit(main())"  # what `signpose` runs


@pytest.mark.parametrize(
    ("argv", "quiet", "debug", "verbose"),
    [
        (RUN, False, False, False),
        (["-q", *RUN], True, False, False),
        ([*RUN, "-q"], True, False, False),
        (["--quiet", "--debug", *RUN], True, True, False),
        ([*RUN, "--debug", "-v"], False, True, True),
        (["-v", *RUN, "--quiet"], True, False, True),
    ],
)
def test_global_options_before_or_after_the_command(argv, quiet, debug, verbose):
    args = build_parser().parse_args(argv)
    assert (args.quiet, args.debug, args.verbose) == (quiet, debug, verbose)


def test_every_command_takes_the_global_options():
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name in COMMANDS:
        flags = {f for a in sub.choices[name.replace("_", "-")]._actions for f in a.option_strings}
        assert {"-q", "--quiet", "-v", "--verbose", "--debug"} <= flags, name


def test_help_names_the_defaults(capsys):
    with pytest.raises(SystemExit):
        main(["run", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "smoother solver (default: batch)" in text


def test_a_broken_pipe_ends_quietly_with_exit_0(monkeypatch, capsys):
    def func(args):
        raise BrokenPipeError(32, "Broken pipe")

    parser = build_parser()
    monkeypatch.setattr("signpose.cli.build_parser", lambda: parser)
    parser.set_defaults(func=func)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    sub.choices["sign"].set_defaults(func=func)
    assert main(["sign", "0101", "--out", "x.svg"]) == EXIT_OK
    assert capsys.readouterr().err == ""


def test_a_real_pipe_closed_by_its_reader():
    """``signpose detect`` prints one JSON line per image; the reader takes one and leaves."""
    images = [f"missing-{i}.png" for i in range(3000)]
    proc = subprocess.Popen(
        [sys.executable, "-c", ENTRY, "detect", *images],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    assert proc.stdout.readline().startswith(b'{"image": "missing-0.png"')
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == EXIT_OK, err
    assert err == ""


def _outcome(status: str, internal: bool = False) -> batch.FlightOutcome:
    return batch.FlightOutcome("f", batch.FlightStatus(status), internal=internal)


def test_batch_exit_code_is_the_worst_flights():
    assert exit_code([_outcome("ok"), _outcome("ok")]) == EXIT_OK
    assert exit_code([_outcome("ok"), _outcome("partial")]) == EXIT_INPUT
    assert exit_code([_outcome("failed"), _outcome("ok")]) == EXIT_INPUT
    assert exit_code([_outcome("failed"), _outcome("failed", internal=True)]) == EXIT_INTERNAL


@pytest.mark.parametrize(
    ("error", "code"), [(InputError("in.mp4: unreadable"), 2), (RuntimeError("a bug"), 1)]
)
def test_batch_of_failing_flights_exits_by_their_class(monkeypatch, tmp_path, capsys, error, code):
    def run(*args, **kw):
        raise error

    monkeypatch.setattr(batch, "run", run)
    inputs = [str(tmp_path / "f1.mp4"), str(tmp_path / "f2.mp4")]
    assert main(["batch", *inputs, "--map", MAP, "--out", str(tmp_path / "out"), "-q"]) == code
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "failed flights: f1" in err[0]


@pytest.mark.parametrize(
    ("argv", "tty", "progress"),
    [
        ([], False, False),  # a log file: no bars
        ([], True, True),  # a terminal
        (["--progress"], False, True),
        (["-q", "--progress"], True, False),  # --quiet wins
        (["--quiet"], True, False),
    ],
)
def test_progress_bars_only_on_a_terminal(monkeypatch, argv, tty, progress):
    seen = []
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    sub.choices["sign"].set_defaults(func=lambda args: seen.append(args.progress))
    monkeypatch.setattr("signpose.cli.build_parser", lambda: parser)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: tty)
    assert main(["sign", "0101", "--out", "x.svg", *argv]) == EXIT_OK
    assert seen == [progress]


def test_run_quiet_prints_the_result_without_timing_or_file_list(capsys):
    result = RunResult(
        out_dir=Path("out"),
        n_frames=3,
        coverage={"smoothed": 1.0},
        position_rmse_m={"smoothed": 0.02},
        comparison=None,
        comparison_table="",
        timing_s={"total": 1.0},
        fps=3.0,
        problems=(),
        files=(Path("out/a.tum"), Path("out/report.html")),
    )
    print_result(result, quiet=True)
    quiet = capsys.readouterr().out.splitlines()
    assert quiet == [
        "3 frames; poses for smoothed 100.0%",
        "position RMSE vs ground truth: smoothed 0.020 m",
        "wrote 2 files into out",
    ]
    print_result(result)
    assert len(capsys.readouterr().out.splitlines()) == len(quiet) + 3  # timing + 2 files


def test_simulate_quiet_prints_one_line(tmp_path, capsys):
    argv = ["simulate", "--out", str(tmp_path / "sim"), "--frames", "2", "--width", "160"]
    assert main([*argv, "--height", "120", "-q"]) == EXIT_OK
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 1 and out[0].startswith("simulated 2 frames")
