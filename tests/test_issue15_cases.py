"""Issue 15's cases that are not a reader's: outputs, ground truth time bases, the CLI.

Each user mistake or fault gives one line naming the file and what to fix
(``OutputError`` / ``InputError``; the CLI prints it and exits 2), never a
traceback or a silent result.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from signpose.estimator.camera import pinhole_camera
from signpose.estimator.trajectory import Trajectory
from signpose.maps.loader import MAX_MAP_BYTES, bundled_map_path, load_map

from signpose.cli import EXIT_TERMINATED
from signpose.cli import main as cli_main
from signpose.cli import sign as sign_cli
from signpose.core import fileio
from signpose.core.errors import InputError, OutputError
from signpose.core.fileio import atomic_path, atomic_write
from signpose.io.camera_file import write_camera_info
from signpose.io.groundtruth import check_time_overlap
from signpose.io.results import read_report
from signpose.io.tum import write_tum


def _one_line(exc: pytest.ExceptionInfo, path, *parts: str) -> None:
    text = str(exc.value)
    assert text.startswith(str(path)) and "\n" not in text
    for part in parts:
        assert part in text


# --------------------------------------------------------------------------- #6, #7 outputs


@pytest.mark.parametrize("opener", [atomic_write, atomic_path])
def test_an_output_naming_a_folder_is_refused(tmp_path, opener):
    target = tmp_path / "observations.jsonl"
    target.mkdir()
    with pytest.raises(OutputError) as exc, opener(target):
        pass
    _one_line(exc, target, "is a folder")
    assert [p.name for p in tmp_path.iterdir()] == ["observations.jsonl"]  # no temporary


def test_a_full_disk_while_writing_names_the_final_file(tmp_path, monkeypatch):
    target = tmp_path / "out.tum"
    target.write_text("old")

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(fileio.os, "fsync", full)
    with pytest.raises(OutputError) as exc, atomic_write(target) as f:
        f.write("new")
    _one_line(exc, target, "No space left on device", "free space")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.tum"]


def test_a_full_disk_inside_the_callers_writes_names_the_final_file(tmp_path):
    target = tmp_path / "out.txt"
    with pytest.raises(OutputError) as exc, atomic_write(target):
        raise OSError(errno.ENOSPC, "No space left on device")
    _one_line(exc, target, "No space left on device")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("opener", [atomic_write, atomic_path])
@pytest.mark.parametrize(
    "code, hint",
    [(errno.EROFS, "read-only"), (errno.EACCES, "may not write"), (errno.ENOSPC, "free space")],
)
def test_a_failed_rename_names_the_final_file(tmp_path, monkeypatch, opener, code, hint):
    target = tmp_path / "plot.png"

    def refuse(*args, **kwargs):
        raise OSError(code, os.strerror(code))

    monkeypatch.setattr(fileio.os, "replace", refuse)
    with pytest.raises(OutputError) as exc, opener(target) as handle:
        if isinstance(handle, os.PathLike):
            handle.write_bytes(b"png")
        else:
            handle.write("x")
    _one_line(exc, target, os.strerror(code), hint)
    assert list(tmp_path.iterdir()) == []


def test_an_oserror_that_is_not_the_outputs_passes_through(tmp_path):
    with pytest.raises(FileNotFoundError), atomic_write(tmp_path / "out.txt"):
        (tmp_path / "missing-input.txt").read_text()
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- #4, #9, #21 maps

MAP_HEAD = "frame: site\nsigns:\n"
ONE_SIGN = (
    '- {code: "0101", center_m: [0, 0, 10], normal: [0, 1, 0], up: [0, 0, 1], '
    "diameter_m: 0.8, sigma_m: 0.01}\n"
)


@pytest.mark.parametrize(
    "text, expect",
    [
        (MAP_HEAD + "- " + "[" * 5000 + "]" * 5000 + "\n", "nested deeper than 64"),
        ("frame: site\nsigns: !!python/object/apply:os.system [echo]\n", "tag !!python/object"),
        (MAP_HEAD + ONE_SIGN + "extra: 1\n", "unknown top-level key 'extra'"),
        (MAP_HEAD + ONE_SIGN.replace("[0, 0, 10]", "[1e300, 0, 10]"), "beyond 1e+07 m"),
        (MAP_HEAD + ONE_SIGN.replace("diameter_m: 0.8", "diameter_m: 1e308"), "above 100 m"),
        (MAP_HEAD + ONE_SIGN.replace("normal: [0, 1, 0]", "normal: [0, 1e-300, 0]"), "zero"),
    ],
)
def test_bad_maps_are_one_line_naming_the_file(tmp_path, text, expect):
    path = tmp_path / "map.yaml"
    path.write_text(text)
    with pytest.raises(InputError) as exc:
        load_map(path)
    _one_line(exc, path, expect)


def test_huge_components_of_a_direction_are_normalised_not_nan(tmp_path):
    path = tmp_path / "map.yaml"
    path.write_text(MAP_HEAD + ONE_SIGN.replace("up: [0, 0, 1]", "up: [1e308, 0, 1e308]"))
    sign = load_map(path).signs[0]
    assert np.allclose(sign.up, [np.sqrt(0.5), 0.0, np.sqrt(0.5)], atol=1e-12)
    assert np.allclose(sign.world_R_sign() @ sign.world_R_sign().T, np.eye(3), atol=1e-12)


def test_a_map_over_the_size_limit_is_refused_at_once(tmp_path):
    path = tmp_path / "map.yaml"
    with path.open("w") as f:
        f.write(MAP_HEAD)
        f.write(ONE_SIGN * (MAX_MAP_BYTES // len(ONE_SIGN) + 1))
    t0 = time.perf_counter()
    with pytest.raises(InputError) as exc:
        load_map(path)
    assert time.perf_counter() - t0 < 1.0
    _one_line(exc, path, f"at most {MAX_MAP_BYTES} bytes")


# --------------------------------------------------------------------------- #12 estimate


def test_estimate_on_observations_without_any_sign_exits_2(tmp_path, capsys):
    path = tmp_path / "observations.jsonl"
    path.write_text(
        "".join(
            json.dumps(
                {"frame": i, "stamp_ns": i * 33_000_000, "image_size": [640, 360], "signs": []}
            )
            + "\n"
            for i in range(5)
        )
    )
    camera = tmp_path / "camera.yaml"
    write_camera_info(camera, pinhole_camera(640, 360))
    argv = ["estimate", str(path), "--map", str(bundled_map_path()), "--camera", str(camera)]
    code = cli_main([*argv, "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.count("\n") == 0 and str(path) in err and "no sign was decoded" in err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


# --------------------------------------------------------------------------- #18 SIGTERM


def test_sigterm_cleans_up_like_ctrl_c_and_exits_143(tmp_path, monkeypatch, capsys):
    def render_then_terminated(code, diameter_mm):
        os.kill(os.getpid(), signal.SIGTERM)  # arrives while the output is being written
        return "<svg/>"

    monkeypatch.setattr(sign_cli, "render_sign_svg", render_then_terminated)
    before = signal.getsignal(signal.SIGTERM)
    code = cli_main(["sign", "0101", "--out", str(tmp_path / "sign.svg")])
    assert code == EXIT_TERMINATED == 143
    assert "terminated (SIGTERM)" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []  # no half-written file, no temporary
    assert signal.getsignal(signal.SIGTERM) is before  # the handler is the command's only


# --------------------------------------------------------------------------- #14 ground truth time


def _trajectory(stamps_s: np.ndarray) -> Trajectory:
    n = len(stamps_s)
    positions = np.column_stack([np.linspace(0.0, 5.0, n), np.zeros(n), np.full(n, 10.0)])
    return Trajectory(np.asarray(stamps_s, float), positions, np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)))


def _estimate_folder(tmp_path) -> tuple:
    out = tmp_path / "est"
    out.mkdir()
    stamps = np.arange(40) / 30.0
    write_tum(out / "smoothed.tum", _trajectory(stamps))
    write_tum(out / "pnp.tum", _trajectory(stamps[10:]))
    return out, stamps


def test_compare_with_a_ground_truth_on_another_clock_exits_2_naming_both(tmp_path, capsys):
    out, stamps = _estimate_folder(tmp_path)
    gt = tmp_path / "groundtruth.tum"
    write_tum(gt, _trajectory(stamps + 1_733_000_000.0))  # epoch vs. from 0
    code = cli_main(["compare", str(out), "--gt", str(gt)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "\n" not in err
    for part in (str(gt), str(out), "1733000000.000 to 1733000001.300 s", "0.000 to 1.300 s"):
        assert part in err
    assert "--gt-offset SECONDS" in err and "-1733000000.000" in err
    assert not (out / "report.json").exists()


def test_gt_offset_shifts_the_ground_truth_onto_the_trajectory(tmp_path, capsys):
    out, stamps = _estimate_folder(tmp_path)
    gt = tmp_path / "groundtruth.tum"
    write_tum(gt, _trajectory(stamps + 1_733_000_000.0))
    code = cli_main(["compare", str(out), "--gt", str(gt), "--gt-offset", "-1733000000"])
    assert code == 0
    methods = read_report(out / "report.json")["metrics"]["methods"]
    assert methods["smoothed"]["ate_rmse_m"] == pytest.approx(0.0, abs=1e-6)
    assert "smoothed" in capsys.readouterr().out


def test_a_ground_truth_covering_under_half_the_flight_is_refused(tmp_path):
    stamps = np.arange(40) / 30.0
    gt = _trajectory(stamps[:15])  # 14 of 39 intervals: 36 %
    with pytest.raises(InputError) as exc:
        check_time_overlap(stamps, "flight.mp4", gt, "gt.tum")
    _one_line(exc, "gt.tum", "36% of it covered", "15 shared stamps")
    check_time_overlap(stamps, "flight.mp4", _trajectory(stamps[:30]), "gt.tum")  # 74 %: fine


# ------------------------------------------------------------------ #19 killed runs' temporaries


def _dead_pid() -> int:
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    return child.pid


def test_the_next_run_removes_a_killed_runs_temporaries(tmp_path):
    dead = _dead_pid()
    stale = tmp_path / f".observations.jsonl.{dead}.abcd1234.tmp"
    stale_plot = tmp_path / f".views.{dead}.wxyz_987.png"
    live = tmp_path / f".trajectory.csv.{os.getpid()}.abcd1234.tmp"  # a writer still running
    other = tmp_path / ".hidden.tmp"  # not a signpose temporary
    for p in (stale, stale_plot, live, other):
        p.write_text("x")
    with atomic_write(tmp_path / "observations.jsonl") as f:  # its own leftovers first
        f.write("{}\n")
    assert not stale.exists() and stale_plot.exists()
    fileio.ensure_dir(tmp_path)  # a run's output folder: every dead writer's leftover
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == sorted([live.name, other.name, "observations.jsonl"])


def test_temporary_names_carry_the_writers_pid(tmp_path):
    seen = []
    with atomic_path(tmp_path / "views.png") as tmp:
        seen.append(tmp.name)
        tmp.write_bytes(b"png")
    with atomic_write(tmp_path / "a.tum") as f:
        seen += [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
        f.write("x")
    assert all(f".{os.getpid()}." in name for name in seen) and len(seen) == 2
