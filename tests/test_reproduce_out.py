"""scripts/reproduce_paper.py writes into its work folder unless --out names a place (issue 16.6).

Every step is skipped, so each call only composes the report (well under a second).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SCRIPT = REPO / "scripts" / "reproduce_paper.py"
COMMITTED = REPO / "docs" / "results.md"


@pytest.fixture(scope="module")
def mod():
    spec = importlib.util.spec_from_file_location("reproduce_paper_out", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the file runs
    spec.loader.exec_module(module)
    return module


def _skip_all(mod) -> list[str]:
    return [a for name in mod.STEP_NAMES for a in ("--skip", name)]


def test_without_out_the_committed_report_is_left_alone(mod, tmp_path, capsys):
    before = COMMITTED.read_bytes()
    work = tmp_path / "work"
    assert mod.main(["--quick", "--work", str(work), *_skip_all(mod)]) == 0
    assert COMMITTED.read_bytes() == before
    report = work / "results.md"
    assert report.is_file()
    assert f"wrote {report}" in capsys.readouterr().out
    command = next(ln for ln in report.read_text().splitlines() if "reproduce_paper.py" in ln)
    assert "--out" not in command.split("#")[0]


def test_without_out_or_work_it_writes_into_a_new_temporary_folder(mod, capsys):
    before = COMMITTED.read_bytes()
    assert mod.main(["--quick", *_skip_all(mod)]) == 0
    assert COMMITTED.read_bytes() == before
    out = capsys.readouterr().out
    written = Path(out.split("wrote ", 1)[1].split(" in ", 1)[0])
    assert written.name == "results.md" and written.is_file()
    assert written.parent.name.startswith("signpose-reproduce-")
    assert not written.resolve().is_relative_to(REPO)


def test_out_as_a_folder_or_as_a_file(mod, tmp_path):
    folder = tmp_path / "docs"
    assert mod.main(["--quick", "--work", str(tmp_path / "w1"), "--out", str(folder),
                     *_skip_all(mod)]) == 0  # fmt: skip
    assert (folder / "results.md").is_file()
    file = tmp_path / "elsewhere" / "report.md"
    assert mod.main(["--quick", "--work", str(tmp_path / "w2"), "--out", str(file),
                     *_skip_all(mod)]) == 0  # fmt: skip
    assert file.is_file()
    assert f"--out {file}" in file.read_text()


def test_the_committed_report_names_out_docs(mod):
    assert mod.report_path(REPO / "docs", Path("/tmp/w")) == COMMITTED.resolve()
    text = COMMITTED.read_text(encoding="utf-8")
    assert "scripts/reproduce_paper.py --out docs" in text
