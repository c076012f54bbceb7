"""``frames.csv``: the frame times of a folder of images (the one reader and writer).

Format: UTF-8 CSV with the header ``filename,stamp_ns`` and one row per image::

    filename,stamp_ns
    000000.png,0
    000001.png,33333333

``filename`` is the image's name inside the folder (readers match a path by
its last part); ``stamp_ns`` the frame's time [ns] as an integer. Blank
rows are skipped; extra columns are ignored. The simulator writes it beside
``frames/NNNNNN.png``; ``signpose.io.sources.FolderSource`` reads it (also
under the older name ``times.csv``).
"""

from __future__ import annotations

import csv
import os
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from signpose.core.errors import InputError
from signpose.core.fileio import atomic_write

HEADER = ("filename", "stamp_ns")


@dataclass(frozen=True)
class FrameStamp:
    """One row of ``frames.csv``.

    Attributes:
        filename: image name inside the folder, as written in the file.
        stamp_ns: frame time [ns].
        line: 1-based line of the row in the file (0 when not read from a file),
            for error messages that point at it.
    """

    filename: str
    stamp_ns: int
    line: int = 0


def frames_csv_text(rows: Iterable[FrameStamp]) -> str:
    """The text of a ``frames.csv`` listing ``rows`` in the given order."""
    lines = [",".join(HEADER)]
    lines += [f"{row.filename},{int(row.stamp_ns)}" for row in rows]
    return "\n".join(lines) + "\n"


def write_frames_csv(path: str | os.PathLike, rows: Iterable[FrameStamp]) -> Path:
    """Write ``rows`` to ``path`` atomically; return the path."""
    target = Path(path)
    with atomic_write(target, encoding="utf-8", newline="") as f:
        f.write(frames_csv_text(rows))
    return target


def read_frames_csv(path: str | os.PathLike) -> list[FrameStamp]:
    """Read ``frames.csv`` rows in file order.

    Raises:
        InputError: unreadable file, wrong header, a row without a stamp, a
            stamp that is not an integer, or no rows at all; each message
            names the file (and the line).
    """
    csv_path = Path(path)
    try:
        text = csv_path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{csv_path}: cannot read ({exc})") from None
    reader = csv.reader(text.splitlines())
    header = next(reader, None)
    if header is None or tuple(h.strip() for h in header[:2]) != HEADER:
        raise InputError(f"{csv_path}: first line must be the header 'filename,stamp_ns'")
    rows = []
    for lineno, row in enumerate(reader, start=2):
        if not row or not "".join(row).strip():
            continue
        if len(row) < 2:
            raise InputError(f"{csv_path}: line {lineno}: expected 'filename,stamp_ns'")
        name, stamp = row[0].strip(), row[1].strip()
        try:
            stamp_ns = int(stamp)
        except ValueError:
            raise InputError(
                f"{csv_path}: line {lineno}: stamp_ns {stamp!r} is not an integer"
            ) from None
        rows.append(FrameStamp(name, stamp_ns, lineno))
    if not rows:
        raise InputError(f"{csv_path}: lists no frames")
    return rows
