"""rosbag2's sqlite3 storage (``.db3``, the default of ROS 2 Humble), read as a ``MessageLog``.

Tables read: ``topics`` (id, name, type, serialization_format) and ``messages``
(topic_id, timestamp, data), in row order, which is recording order. The CDR
payloads are decoded by the ``rosbags`` typestore, which knows every standard
ROS 2 message type (a Humble .db3 carries no message definitions). A file
shorter than its header says (a recording cut off) is read up to the break
through a repaired temporary copy: the user's file is never written.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import struct
import tempfile
from collections.abc import Callable, Iterable, Iterator
from functools import cache
from pathlib import Path
from typing import Any

from rosbags.typesys import Stores, get_typestore

from signpose.core.errors import InputError
from signpose.io.messages import LogChannel, LogMessage

SQLITE_MAGIC = b"SQLite format 3\x00"
_SQLITE_HEADER_BYTES = 100
_COPY_CHUNK_BYTES = 1 << 20
# What sqlite3 raises for a damaged file (its messages may hold the damaged bytes).
_SQLITE_ERRORS = (sqlite3.Error, UnicodeDecodeError)


@cache
def _typestore():
    """The rosbags typestore that decodes standard ROS 2 CDR messages."""
    return get_typestore(Stores.ROS2_HUMBLE)


def _cdr_decoder(msgtype: str) -> Callable[[bytes], Any]:
    store = _typestore()
    if msgtype not in store.types:
        raise KeyError(msgtype)
    return lambda data: store.deserialize_cdr(data, msgtype)


def _sqlite_truncation(path: Path) -> tuple[int, int] | None:
    """(page size, whole pages in the file) when a .db3 is shorter than its header says.

    Raises:
        ValueError: the file does not start with the SQLite header.
    """
    with open(path, "rb") as f:
        head = f.read(_SQLITE_HEADER_BYTES)
    if len(head) < _SQLITE_HEADER_BYTES or not head.startswith(SQLITE_MAGIC):
        raise ValueError("no SQLite header")
    page_size = struct.unpack(">H", head[16:18])[0]
    page_size = 65536 if page_size == 1 else page_size
    header_pages = struct.unpack(">I", head[28:32])[0]
    size = path.stat().st_size
    if page_size == 0 or header_pages * page_size <= size:
        return None
    return page_size, size // page_size


def _repaired_copy(path: Path, page_size: int, pages: int, folder: Path) -> Path:
    """A copy of a truncated .db3 cut to whole pages, its header's page count made true."""
    copy = folder / path.name
    with open(path, "rb") as fin, open(copy, "wb") as fout:
        shutil.copyfileobj(fin, fout, _COPY_CHUNK_BYTES)
        fout.truncate(page_size * pages)
        fout.seek(28)
        fout.write(struct.pack(">I", pages))
    return copy


class Db3Log:
    """One rosbag2 sqlite3 storage file (``.db3``), read as a ``MessageLog``.

    Messages come in the order they were recorded (row id). A file shorter than
    its header says is read through a repaired temporary copy up to the break.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        name: str | os.PathLike | None = None,
        decompress: Callable[[bytes], bytes] | None = None,
    ):
        """Args:
        path: the ``.db3`` file.
        name: the path to name in messages (``path`` when None).
        decompress: applied to every payload before decoding (per-message compression).
        """
        self._file = Path(path)
        self.path = Path(name) if name is not None else self._file
        self._decompress = decompress
        self.problem: str | None = None
        self._cut_note: str | None = None
        self._tmp: tempfile.TemporaryDirectory | None = None
        try:
            cut = _sqlite_truncation(self._file)
        except OSError as exc:
            raise InputError(f"{self.path}: cannot read ({exc.strerror})") from None
        except ValueError:
            raise InputError(
                f"{self.path}: not an SQLite database (a .db3 bag file starts 'SQLite format 3')"
            ) from None
        if cut is not None:
            page_size, pages = cut
            self._tmp = tempfile.TemporaryDirectory(prefix="signpose-db3-")
            self._file = _repaired_copy(self._file, page_size, pages, Path(self._tmp.name))
            self._cut_note = f"the file is cut short after {page_size * pages} bytes"
        self._topics = self._read_topics()
        self.channels = self._read_channels()

    def _connect(self) -> sqlite3.Connection:
        con = sqlite3.connect(f"file:{self._file}?mode=ro", uri=True)
        con.text_factory = _text  # damaged text is read, not raised
        return con

    def _read_topics(self) -> dict[int, tuple[str, str, str]]:
        try:
            with self._connect() as con:
                rows = con.execute(
                    "SELECT id, name, type, serialization_format FROM topics ORDER BY id"
                ).fetchall()
        except _SQLITE_ERRORS as exc:
            if self._cut_note is not None:
                raise InputError(
                    f"{self.path}: {self._cut_note}, before its first message; nothing to read"
                ) from None
            raise InputError(
                f"{self.path}: not a readable rosbag2 sqlite3 file ({exc}); "
                "check the file or record the bag again"
            ) from None
        return {
            i: (str(name), str(kind), str(fmt))
            for i, name, kind, fmt in rows
            if isinstance(i, int)  # a damaged row has no id: its topic cannot be read
        }

    def _read_channels(self) -> tuple[LogChannel, ...]:
        counts: dict[int, int] | None
        try:
            with self._connect() as con:
                rows = con.execute(
                    "SELECT topic_id, COUNT(*) FROM messages GROUP BY topic_id"
                ).fetchall()
            counts = {tid: n for tid, n in rows if isinstance(tid, int)}
        except _SQLITE_ERRORS:
            counts = None  # damaged: counted while reading
        if self._cut_note is not None:
            counts = None
        return tuple(
            LogChannel(name, kind, fmt, None if counts is None else counts.get(tid, 0))
            for tid, (name, kind, fmt) in self._topics.items()
        )

    def messages(self, topics: Iterable[str]) -> Iterator[LogMessage]:
        """Decoded messages of ``topics`` in recording order."""
        wanted = {tid: t for tid, t in self._topics.items() if t[0] in set(topics)}
        self.problem = None
        decoders: dict[int, Callable[[bytes], Any] | None] = {}
        read = 0
        con = self._connect()
        try:
            marks = ",".join("?" * len(wanted))
            rows = con.execute(
                f"SELECT topic_id, timestamp, data FROM messages WHERE topic_id IN ({marks}) "
                "ORDER BY id",
                tuple(wanted),
            )
            for tid, log_time_ns, data in rows:
                read += 1
                name, kind, _ = wanted[tid]
                if tid not in decoders:
                    decoders[tid] = _decoder_or_none(kind)
                if not isinstance(log_time_ns, int) or not isinstance(data, bytes):
                    yield LogMessage(name, kind, 0, None, "damaged row (no time or no data)")
                    continue
                yield self._decoded(name, kind, log_time_ns, data, decoders[tid])
        except _SQLITE_ERRORS as exc:
            where = self._cut_note or "the file is damaged"
            self.problem = f"log stopped after {read} messages ({where}: {exc})"
        finally:
            con.close()
        if self.problem is None and self._cut_note is not None:
            self.problem = f"log stopped after {read} messages ({self._cut_note})"

    def _decoded(self, topic: str, kind: str, log_time_ns: int, data: bytes, decoder):
        if decoder is None:
            return LogMessage(topic, kind, log_time_ns, None, f"unknown message type {kind}")
        try:
            if self._decompress is not None:
                data = self._decompress(data)
            return LogMessage(topic, kind, log_time_ns, decoder(data))
        except Exception as exc:  # noqa: BLE001 - one bad message is a value
            text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            return LogMessage(topic, kind, log_time_ns, None, f"cannot decode ({text})")


def _text(raw: bytes) -> str:
    return raw.decode("utf-8", errors="replace")


def _decoder_or_none(msgtype: str) -> Callable[[bytes], Any] | None:
    try:
        return _cdr_decoder(msgtype)
    except KeyError:
        return None
