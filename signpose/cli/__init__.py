"""The ``signpose`` command: argument parsing only; the work is in library functions.

Each subcommand lives in its own module here with ``register(subparsers)``,
which adds its parser and sets ``func`` to a function taking the parsed
namespace and returning an exit code. Namespaces never leave this package.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import logging
import math
import os
import signal
import sys
import threading
from pathlib import Path
from typing import NoReturn

import cv2

from signpose import __version__
from signpose.core.errors import InputError, SignposeError, one_line
from signpose.frontend.sign import ALL_CODES
from signpose.pipeline import ObserveSettings

# Subcommand modules, in the order `signpose --help` lists them.
COMMANDS = (
    "sign",
    "camera",
    "simulate",
    "decode",
    "detect",
    "train_detector",
    "observe",
    "estimate",
    "refine_map",
    "compare",
    "run",
    "batch",
    "demo",
)

EXIT_OK, EXIT_INTERNAL, EXIT_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130
EXIT_TERMINATED = 143  # 128 + SIGTERM, what a shell reports for a terminated job


class Terminated(KeyboardInterrupt):
    """SIGTERM (timeout, Docker, Slurm, Dask), raised where the main thread is.

    A KeyboardInterrupt, so every path that flushes and cleans up on Ctrl-C
    (observations written so far, temporary files removed) does so on SIGTERM.
    """


def _raise_terminated(signum, frame) -> None:
    raise Terminated()


@contextlib.contextmanager
def _sigterm_as_interrupt():
    """SIGTERM raises Terminated while the command runs (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


# Options every command takes before or after its name: ``signpose -q run`` = ``signpose run -q``.
GLOBAL_OPTIONS = (
    (("-q", "--quiet"), "no progress bars, no timing or file lists: the result and errors"),
    (("-v", "--verbose"), "log diagnostics"),
    (("--debug",), "show tracebacks of internal errors"),
    (("--progress",), "progress bars also when stderr is not a terminal (a log file)"),
)


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """``--help`` names each option's default, unless it is None/False or the help says it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (
            "default" in text
            or any(default is v for v in (None, False, argparse.SUPPRESS))  # 0 and 0.0 shown
            or action.nargs == 0
            or isinstance(default, list | tuple)
            and not default
        ):
            return text
        return f"{text} (default: %(default)s)"


class OneLineErrorParser(argparse.ArgumentParser):
    """argparse's usage errors as one line on stderr and exit 2, like every other bad input.

    argparse prints the whole usage block (ten lines for ``run``) before the one
    line that says what is wrong; ``--help`` still shows the usage.
    """

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_INPUT, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


class CommandLogFormatter(logging.Formatter):
    """Library warnings as the CLI's own lines: ``signpose run: warning: MESSAGE``.

    Was ``WARNING signpose.estimator.refine: MESSAGE`` beside ``signpose run:
    warning: ...`` from the commands. ``with_logger`` (``--verbose``) adds the
    logger's name, for diagnostics; a traceback (``--debug``) follows as usual.
    """

    def __init__(self, command: str, with_logger: bool = False):
        super().__init__("%(message)s")
        self.command = command
        self.with_logger = with_logger

    def format(self, record: logging.LogRecord) -> str:
        where = f" [{record.name}]" if self.with_logger else ""
        text = super().format(record)
        return f"signpose {self.command}: {record.levelname.lower()}{where}: {text}"


def add_global_options(parser: argparse.ArgumentParser, top: bool) -> None:
    """GLOBAL_OPTIONS on ``parser``; below the top they only override when given."""
    for flags, help_text in GLOBAL_OPTIONS:
        default = False if top else argparse.SUPPRESS
        try:
            parser.add_argument(*flags, action="store_true", default=default, help=help_text)
        except argparse.ArgumentError:  # the command has it already (add_quiet)
            continue


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineErrorParser(
        prog="signpose",
        description="UAV trajectories from coded signs on power pylons.",
        formatter_class=DefaultsHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"signpose {__version__}")
    add_global_options(parser, top=True)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    # By name, not imported above: each subcommand imports ``add_quiet`` and
    # ``codes_arg`` from this module.
    for name in COMMANDS:
        importlib.import_module(f"signpose.cli.{name}").register(sub)
    for command in dict.fromkeys(sub.choices.values()):
        command.formatter_class = DefaultsHelpFormatter
        add_global_options(command, top=False)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    # Commands read args.progress: bars on a terminal, or when asked for; never with --quiet.
    args.progress = not args.quiet and (args.progress or sys.stderr.isatty())
    handler = logging.StreamHandler()
    handler.setFormatter(CommandLogFormatter(args.command, with_logger=args.verbose))
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, handlers=[handler])
    if not (args.verbose or args.debug):
        quiet_opencv()
    try:
        with _sigterm_as_interrupt():
            code = args.func(args)
    except SignposeError as exc:
        print(f"signpose {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_INPUT
    except Terminated:
        print(f"signpose {args.command}: terminated (SIGTERM)", file=sys.stderr)
        return EXIT_TERMINATED
    except KeyboardInterrupt:
        print(f"signpose {args.command}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # stdout's reader left (| head): what it read is what it wanted
        _stdout_to_devnull()
        return EXIT_OK
    except Exception as exc:  # noqa: BLE001 - the CLI's last line of defence
        if args.debug:
            raise
        print(
            f"signpose {args.command}: internal error: {type(exc).__name__}: {one_line(exc)} "
            "(rerun with --debug for the traceback)",
            file=sys.stderr,
        )
        return EXIT_INTERNAL
    return EXIT_OK if code is None else int(code)


def quiet_opencv() -> None:
    """OpenCV's own warnings off stderr (``[ WARN:0@4.0] global grfmt_png.cpp ... incomplete``).

    signpose says the same in its own words (``000020.png: cannot read image;
    skipped``); OpenCV's line beside it broke the one-line error. The variable
    reaches the processes that observe chunks (they import cv2 afresh);
    ``--verbose`` and ``--debug`` keep OpenCV's messages.
    """
    os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)


def _stdout_to_devnull() -> None:
    """Point stdout at /dev/null, so that Python's flush at exit does not fail on the pipe."""
    # No file descriptor behind stdout (a test's capture): nothing to do.
    with contextlib.suppress(OSError, ValueError):
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def add_quiet(parser: argparse.ArgumentParser) -> None:
    # SUPPRESS: not given here keeps what was given before the command (``signpose -q run``).
    flags, help_text = GLOBAL_OPTIONS[0]
    parser.add_argument(*flags, action="store_true", default=argparse.SUPPRESS, help=help_text)


def add_cascade(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--cascade",
        type=Path,
        help="detector cascade XML, e.g. from 'signpose train-detector' (default: the bundled one)",
    )


def add_gt_offset(parser: argparse.ArgumentParser) -> None:
    """--gt-offset SECONDS: the ground truth on a shifted clock (compare, run)."""
    parser.add_argument(
        "--gt-offset",
        type=finite_float,
        default=0.0,
        metavar="SECONDS",
        help="added to the ground truth's stamps (a known shift between the two clocks)",
    )


def add_search(parser: argparse.ArgumentParser) -> None:
    """How the frontend searches a flight's frames (observe, run)."""
    parser.add_argument("--no-tracking", action="store_true", help="search every full frame")
    parser.add_argument(
        "--workers",
        type=count_arg,
        default=0,
        help="processes observing the flight's chunks of 100 frames at once (default: 2 if "
        ">1 core; 1: inline); the output does not depend on it",
    )


def observe_settings(args: argparse.Namespace) -> ObserveSettings:
    """The frontend's settings from --codes, ``add_search``'s options and --cascade."""
    return ObserveSettings(
        codes=args.codes,
        tracking=not args.no_tracking,
        workers=args.workers,
        cascade_path=str(args.cascade or ""),
    )


def count_arg(text: str) -> int:
    """argparse type for a whole number >= 0 (``--workers``, ``--seed``)."""
    try:
        n = int(text)
    except ValueError:
        n = -1
    if n < 0:
        raise argparse.ArgumentTypeError(f"give a whole number >= 0, got {text!r}")
    return n


def finite_float(text: str) -> float:
    """argparse type for a finite number (``--gt-offset``): nan or inf would match no stamp."""
    try:
        x = float(text)
    except ValueError:
        x = float("nan")
    if not math.isfinite(x):
        raise argparse.ArgumentTypeError(f"give a finite number, got {text!r}")
    return x


def out_folder_arg(text: str) -> Path:
    """argparse type for an output folder: a file of that name is refused before any work."""
    p = Path(text)
    if p.exists() and not p.is_dir():
        raise argparse.ArgumentTypeError(
            f"{text} is a file; --out names a folder (a new or an existing one)"
        )
    return p


def check_fps_input(input_path: Path, fps: float | None) -> None:
    """InputError for --fps with a file input: only an image folder takes its times from it.

    A video's or a log's frame times come from the file (``--start-time`` sets a
    video's start); --fps was ignored there without a word.
    """
    if fps is not None and input_path.is_file():
        raise InputError(
            f"{input_path}: --fps is for an image folder; a video or log file gives its own "
            "frame times (a video's start: --start-time)"
        )


def codes_arg(text: str) -> tuple[str, ...]:
    """argparse type for ``--codes 0001,0010``."""
    codes = tuple(c.strip() for c in text.split(",") if c.strip())
    bad = [c for c in codes if c not in ALL_CODES]
    if bad or not codes:
        raise argparse.ArgumentTypeError(f"unknown code {bad[0] if bad else text!r}")
    return codes


if __name__ == "__main__":
    sys.exit(main())
