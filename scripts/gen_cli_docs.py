#!/usr/bin/env python
"""Write docs/cli.md, the command reference, from the argparse definitions of ``signpose``.

    .venv/bin/python scripts/gen_cli_docs.py            # rewrite docs/cli.md
    .venv/bin/python scripts/gen_cli_docs.py --check    # exit 1 when docs/cli.md is stale

The page is built from the parser's actions (not from ``format_help``), so it
does not depend on the terminal width or on how a Python version lays out
argparse's help: one section per command (nested subcommands included) with
its description, a usage line and a table of every option with its default.
tests/test_cli_docs.py fails when the committed page differs from what this
script writes, so a new or changed option means running it again.

argparse has no public way to list a parser's arguments: ``_actions``,
``_SubParsersAction`` and ``_choices_actions`` are read here (stable since
Python 3.2), and nowhere else in the project.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from signpose.cli import (
    EXIT_INPUT,
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_TERMINATED,
    build_parser,
)
from signpose.core.fileio import atomic_write

REPO = Path(__file__).resolve().parent.parent
OUT = REPO / "docs" / "cli.md"
REGENERATE = ".venv/bin/python scripts/gen_cli_docs.py"
EXIT_CODES = (
    (EXIT_OK, "success"),
    (EXIT_INTERNAL, "internal error (`signpose --debug ...` shows the traceback)"),
    (EXIT_INPUT, "bad input: one line on stderr naming the file and what to fix"),
    (EXIT_INTERRUPTED, "interrupted (Ctrl-C); what was done is flushed and valid"),
    (
        EXIT_TERMINATED,
        "terminated (SIGTERM: timeout, Docker, Slurm); flushed and valid as on Ctrl-C",
    ),
)


def _subparsers(parser: argparse.ArgumentParser) -> argparse._SubParsersAction | None:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action
    return None


def _flags(action: argparse.Action) -> str:
    """``-q, --quiet`` or ``--map MAP`` or ``INPUT`` for the table's first column."""
    if not action.option_strings:
        name = action.metavar or action.dest.upper()
        return f"`{name} ...`" if action.nargs in ("*", "+") else f"`{name}`"
    takes_value = action.nargs != 0
    metavar = action.metavar or action.dest.upper()
    if action.choices is not None and action.metavar is None:
        metavar = "{" + ",".join(map(str, action.choices)) + "}"
    if takes_value and action.nargs in ("*", "+"):
        metavar = f"{metavar} ..."
    names = ", ".join(action.option_strings)
    return f"`{names} {metavar}`" if takes_value else f"`{names}`"


def _default(action: argparse.Action) -> str:
    if action.required:
        return "required"
    value = action.default
    if value is None or value is False or value == argparse.SUPPRESS or action.nargs == 0:
        return ""
    if isinstance(value, list | tuple):
        return " ".join(map(str, value)) or ""
    return f"`{value}`"


def _help(action: argparse.Action, prog: str) -> str:
    text = action.help or ""
    if "%(" in text:
        text = text % dict(vars(action), prog=prog)
    return text.replace("|", "\\|").replace("\n", " ")


def _usage(prog: str, parser: argparse.ArgumentParser) -> str:
    """``signpose run INPUT --map MAP --out DIR [options]``: what must be given, then the rest."""
    parts = [prog]
    optional = False
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction | argparse._VersionAction):
            continue
        if isinstance(action, argparse._SubParsersAction):
            parts.append("COMMAND ...")
        elif not action.option_strings:
            name = action.metavar or action.dest.upper()
            repeat = {"*": f"[{name} ...]", "?": f"[{name}]", "+": f"{name} ..."}
            parts.append(repeat.get(action.nargs, name))
        elif action.required:
            parts.append(_flags(action).strip("`"))
        else:
            optional = True
    if optional:
        parts.append("[options]")
    return " ".join(parts)


def _options_table(parser: argparse.ArgumentParser, prog: str) -> list[str]:
    rows = ["| Argument | Default | What |", "| --- | --- | --- |"]
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction | argparse._SubParsersAction):
            continue
        rows.append(f"| {_flags(action)} | {_default(action)} | {_help(action, prog)} |")
    return rows


def _section(prog: str, parser: argparse.ArgumentParser, summary: str, level: int) -> list[str]:
    """One command's section, then its subcommands' sections."""
    lines = [f"{'#' * level} `{prog}`", ""]
    if summary:
        lines += [f"*{summary}*", ""]
    if parser.description:
        lines += [parser.description, ""]
    lines += ["```", _usage(prog, parser), "```", ""]
    lines += [*_options_table(parser, prog), ""]
    if parser.epilog:
        lines += [parser.epilog, ""]
    sub = _subparsers(parser)
    if sub is not None:
        helps = {a.dest: a.help or "" for a in sub._choices_actions}
        seen: set[int] = set()
        for name, child in sub.choices.items():
            if id(child) in seen:  # an alias of a command already written
                continue
            seen.add(id(child))
            lines += _section(f"{prog} {name}", child, helps.get(name, ""), level + 1)
    return lines


def _contents(parser: argparse.ArgumentParser) -> list[str]:
    sub = _subparsers(parser)
    if sub is None:
        return []
    rows = ["| Command | What |", "| --- | --- |"]
    for action in sub._choices_actions:
        anchor = f"signpose-{action.dest}".replace("_", "-")
        rows.append(f"| [`{action.dest}`](#{anchor}) | {action.help or ''} |")
    return [*rows, ""]


def render(parser: argparse.ArgumentParser | None = None) -> str:
    """docs/cli.md's text for ``parser`` (default: the ``signpose`` command's)."""
    parser = parser or build_parser()
    head = [
        "# The `signpose` command line",
        "",
        f"Generated from the argparse definitions by `{REGENERATE}`; do not edit by hand "
        "(tests/test_cli_docs.py fails when this page is stale). Every command also takes "
        "`-h, --help`.",
        "",
        "## Exit codes",
        "",
        "| Code | Meaning |",
        "| ---: | --- |",
        *(f"| {code} | {meaning} |" for code, meaning in EXIT_CODES),
        "",
        "A reader that closes the pipe early (`| head`) ends a command quietly with 0. For "
        "`batch` the worst flight decides: 1 if a flight failed on an internal error, else 2 "
        "if one failed on bad input or was read only in part, else 0.",
        "",
        "## Commands",
        "",
        *_contents(parser),
    ]
    body = _section(parser.prog, parser, "", 2)
    return "\n".join(head + body).rstrip() + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="exit 1 when the page is stale")
    ap.add_argument("--out", type=Path, default=OUT, help="the page (default docs/cli.md)")
    args = ap.parse_args(argv)
    text = render()
    if args.check:
        current = args.out.read_text(encoding="utf-8") if args.out.is_file() else ""
        if current != text:
            print(f"{args.out} is stale: run {REGENERATE}", file=sys.stderr)
            return 1
        return 0
    with atomic_write(args.out) as f:
        f.write(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
