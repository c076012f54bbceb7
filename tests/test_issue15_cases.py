"""Issue 15's cases that are not a reader's: outputs, ground truth time bases, the CLI.

Each user mistake or fault gives one line naming the file and what to fix
(``OutputError`` / ``InputError``; the CLI prints it and exits 2), never a
traceback or a silent result.
"""

from __future__ import annotations

import errno
import os

import pytest

from signpose.core import fileio
from signpose.core.errors import OutputError
from signpose.core.fileio import atomic_path, atomic_write


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
