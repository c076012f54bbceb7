"""Where an input's clock starts: a video's own creation time, or one the user gives.

Logs and bags carry their own times (header stamps, epoch ns) and a folder's
``frames.csv`` lists them; a video only counts from 0 inside the container, and
a folder read with ``--fps`` has no clock at all. For those two the first
frame's time is the MP4/MOV movie header's ``creation_time`` where the file has
one, else what ``--start-time`` says, else 0 (the behaviour before).
"""

from __future__ import annotations

import struct
from datetime import datetime
from decimal import Decimal, InvalidOperation
from pathlib import Path

from signpose.core.errors import InputError

QUICKTIME_EPOCH_OFFSET_S = 2_082_844_800  # 1904-01-01 to 1970-01-01, the MP4 clock's origin
MP4_SUFFIXES = (".mp4", ".mov", ".m4v", ".3gp")
_BOX_HEADER = struct.Struct(">I4s")
MAX_EPOCH_S = 9_223_372_036  # int64 nanoseconds end in 2262
_MAX_BOXES = 10_000  # a damaged file is not walked for ever


def parse_start_time(text: str) -> int:
    """``--start-time``: epoch seconds (``1714557600.25``) or ISO 8601 with a zone [ns].

    Raises:
        InputError: neither, a time without a zone, or a time before 1970.
    """
    s = text.strip()
    try:
        seconds = Decimal(s)  # exact: 1714557600.25 is 1714557600250000000 ns
    except InvalidOperation:
        seconds = None
    if seconds is not None:
        if not seconds.is_finite() or not 0 <= seconds < MAX_EPOCH_S:
            raise InputError(f"--start-time {text!r}: epoch seconds must be in 0..{MAX_EPOCH_S}")
        return int(seconds * 1_000_000_000)
    try:
        when = datetime.fromisoformat(s)
    except ValueError:
        raise InputError(
            f"--start-time {text!r}: give epoch seconds or an ISO 8601 time such as "
            "2026-05-01T10:30:00Z"
        ) from None
    if when.tzinfo is None:
        raise InputError(f"--start-time {text!r}: add the time zone (e.g. Z or +02:00)")
    ns = int(round(when.timestamp() * 1e6)) * 1000  # microseconds are exact in a float
    if ns < 0:
        raise InputError(f"--start-time {text!r}: is before 1970")
    return ns


def _boxes(f, start: int, end: int):
    """(type, payload start, payload end) of the ISO-BMFF boxes in [start, end)."""
    pos = start
    for _ in range(_MAX_BOXES):
        if pos + 8 > end:
            return
        f.seek(pos)
        head = f.read(8)
        if len(head) < 8:
            return
        size, kind = _BOX_HEADER.unpack(head)
        payload = pos + 8
        if size == 1:
            large = f.read(8)
            if len(large) < 8:
                return
            size = struct.unpack(">Q", large)[0]
            payload = pos + 16
        elif size == 0:
            size = end - pos
        if size < payload - pos:
            return
        yield kind, payload, min(pos + size, end)
        pos += size


def mp4_creation_time_ns(path: str | Path) -> int | None:
    """The movie header's (``moov/mvhd``) creation time [ns since 1970], or None.

    None when the file is not MP4/MOV, has no movie header, or says 0 (what
    writers that do not know the time, OpenCV's among them, put there).
    """
    p = Path(path)
    if p.suffix.lower() not in MP4_SUFFIXES:
        return None
    try:
        with open(p, "rb") as f:
            size = p.stat().st_size
            moov = next(((a, b) for k, a, b in _boxes(f, 0, size) if k == b"moov"), None)
            if moov is None:
                return None
            mvhd = next((a for k, a, _ in _boxes(f, *moov) if k == b"mvhd"), None)
            if mvhd is None:
                return None
            f.seek(mvhd)
            head = f.read(12)
    except OSError:
        return None
    if len(head) < 8:
        return None
    if head[0] == 1:
        seconds = struct.unpack(">Q", head[4:12])[0] if len(head) == 12 else 0
    else:
        seconds = struct.unpack(">I", head[4:8])[0]
    if seconds <= QUICKTIME_EPOCH_OFFSET_S:
        return None
    return (seconds - QUICKTIME_EPOCH_OFFSET_S) * 1_000_000_000
