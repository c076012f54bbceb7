"""docs/cli.md is what scripts/gen_cli_docs.py writes from the argparse definitions (issue 16.9)."""

from __future__ import annotations

import argparse
import importlib.util
import sys
from pathlib import Path

import pytest

from signpose.cli import COMMANDS, build_parser

REPO = Path(__file__).resolve().parent.parent
SCRIPT = REPO / "scripts" / "gen_cli_docs.py"
PAGE = REPO / "docs" / "cli.md"


@pytest.fixture(scope="module")
def gen():
    spec = importlib.util.spec_from_file_location("gen_cli_docs", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_docs_cli_md_is_not_stale(gen):
    assert PAGE.read_text(encoding="utf-8") == gen.render(), (
        f"docs/cli.md is stale: run {gen.REGENERATE}"
    )


def test_every_command_and_option_is_on_the_page(gen):
    text = gen.render()
    assert "`-h, --help`" in text
    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name in COMMANDS:
        command = name.replace("_", "-")
        assert f"## `signpose {command}`" in text, command
        assert f"(#signpose-{command})" in text, command
        for action in sub.choices[command]._actions:
            if isinstance(action, argparse._HelpAction):  # said once, at the top
                continue
            for flag in action.option_strings:
                assert flag in text, (command, flag)


def test_defaults_and_required_are_shown(gen):
    parser = argparse.ArgumentParser(prog="tool", description="A tool.")
    parser.add_argument("input", help="the input")
    parser.add_argument("--map", required=True, help="the map")
    parser.add_argument("--jobs", type=int, default=3, help="workers (%(default)s)")
    parser.add_argument("--mode", choices=("a", "b"), default="a", help="which | mode")
    parser.add_argument("-q", "--quiet", action="store_true", help="quiet")
    text = gen.render(parser)
    assert "tool INPUT --map MAP [options]" in text
    assert "| `INPUT` | required | the input |" in text
    assert "| `--jobs JOBS` | `3` | workers (3) |" in text
    assert "| `--mode {a,b}` | `a` | which \\| mode |" in text
    assert "| `-q, --quiet` |  | quiet |" in text


def test_check_mode_says_when_the_page_is_stale(gen, tmp_path, capsys):
    page = tmp_path / "cli.md"
    page.write_text("old\n")
    assert gen.main(["--check", "--out", str(page)]) == 1
    assert "stale" in capsys.readouterr().err
    assert gen.main(["--out", str(page)]) == 0
    assert gen.main(["--check", "--out", str(page)]) == 0
