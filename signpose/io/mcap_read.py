"""MCAP logs in: channels and decoded messages, streamed record by record.

Messages are JSON (Foxglove) or ROS 2 CDR, decoded by the ``rosbags``
typestore from the message definition the log carries (``ros2msg`` or
``ros2idl`` schema, as ``ros2 bag record`` writes it); what they mean is
``signpose.io.messages``. A
truncated or corrupt log yields what is readable and then says where it stopped.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore

from signpose.core.errors import InputError
from signpose.io.messages import LogChannel, LogMessage

JSON_ENCODING = "json"
CDR_ENCODING = "cdr"
ROS2_SCHEMA_ENCODINGS = ("ros2msg", "ros2idl")
MAX_RECORD_BYTES = 1 << 30  # one record larger than this is taken for corrupt data


# The names this module had before the channel and message types became shared.
McapChannel = LogChannel
McapMessage = LogMessage


class McapLog:
    """A streamed MCAP log.

    ``channels`` comes from the summary section, or, for a log without one (e.g.
    truncated), from a scan of the data. ``messages()`` streams in file order
    and, when the data stops early, sets ``problem`` to where and why.
    """

    def __init__(
        self,
        path: str | os.PathLike,
        *,
        name: str | os.PathLike | None = None,
        decompress: Callable[[bytes], bytes] | None = None,
    ):
        """Args:
        path: the ``.mcap`` file.
        name: the path to name in messages (the user's file when ``path`` is a
            decompressed temporary copy); ``path`` when None.
        decompress: applied to every message payload before decoding (rosbag2's
            per-message compression), or None.
        """
        self._file = Path(path)
        self.path = Path(name) if name is not None else self._file
        if not self._file.is_file():
            raise InputError(f"{self.path}: file not found")
        self._decompress = decompress
        self.problem: str | None = None
        self.channels = self._read_channels()

    # ------------------------------------------------------------------ channels
    def _read_channels(self) -> tuple[LogChannel, ...]:
        try:
            with open(self._file, "rb") as f:
                summary = make_reader(f).get_summary()
        except Exception:  # noqa: BLE001 - any failure: fall back to scanning the data
            summary = None
        if summary is not None and summary.channels:
            counts = summary.statistics.channel_message_counts if summary.statistics else {}
            return tuple(
                LogChannel(
                    c.topic,
                    summary.schemas[c.schema_id].name if c.schema_id in summary.schemas else "",
                    c.message_encoding,
                    counts.get(c.id) if summary.statistics else None,
                )
                for c in sorted(summary.channels.values(), key=lambda c: c.id)
            )
        counts: dict[int, int] = {}
        channels: dict[int, Any] = {}
        schemas: dict[int, Any] = {}
        for record in self._records(count_into=counts):
            kind = type(record).__name__
            if kind == "Schema":
                schemas[record.id] = record
            elif kind == "Channel":
                channels[record.id] = record
        scan_problem = self.problem
        self.problem = None
        if not channels and scan_problem:
            raise InputError(f"{self.path}: not a readable MCAP log ({scan_problem})")
        return tuple(
            LogChannel(
                c.topic,
                schemas[c.schema_id].name if c.schema_id in schemas else "",
                c.message_encoding,
                counts.get(c.id, 0) if scan_problem is None else None,
            )
            for c in sorted(channels.values(), key=lambda c: c.id)
        )

    def channel(self, topic: str) -> McapChannel | None:
        for c in self.channels:
            if c.topic == topic:
                return c
        return None

    def image_channels(self) -> list[McapChannel]:
        return [c for c in self.channels if c.is_image]

    # ------------------------------------------------------------------ records
    def _records(self, count_into: dict[int, int] | None = None) -> Iterator[Any]:
        with open(self._file, "rb") as f:
            reader = StreamReader(f, record_size_limit=MAX_RECORD_BYTES)
            n_messages = 0
            try:
                for record in reader.records:
                    kind = type(record).__name__
                    if kind == "Message":
                        n_messages += 1
                        if count_into is not None:
                            count_into[record.channel_id] = count_into.get(record.channel_id, 0) + 1
                    yield record
                    if kind == "Footer":
                        return
            except Exception as exc:  # noqa: BLE001 - corrupt data: stop and say where
                size = self._file.stat().st_size
                at = min(f.tell(), size)
                reason = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
                reason = f"{type(exc).__name__}: {reason}" if reason else type(exc).__name__
                self.problem = (
                    f"log stopped after {n_messages} messages, near byte {at} of {size} "
                    f"({reason}); the file is truncated or corrupt"
                )

    def messages(self, topics: Iterable[str]) -> Iterator[LogMessage]:
        """Decoded messages of ``topics`` in file order (log order for signpose's logs).

        A message that cannot be decoded is yielded with ``error`` set; damaged
        data ends the stream and sets ``problem``.
        """
        wanted = set(topics)
        schemas: dict[int, Any] = {}
        channels: dict[int, Any] = {}
        decoders: dict[int, Callable[[bytes], Any]] = {}
        self.problem = None
        for record in self._records():
            kind = type(record).__name__
            if kind == "Schema":
                schemas[record.id] = record
            elif kind == "Channel":
                channels[record.id] = record
            elif kind == "Message":
                ch = channels.get(record.channel_id)
                if ch is None or ch.topic not in wanted:
                    continue
                sch = schemas.get(ch.schema_id)
                name = sch.name if sch is not None else ""
                decoder = decoders.get(ch.id)
                if decoder is None:
                    decoder = _decoder_for(ch, sch, self.path)
                    decoders[ch.id] = decoder
                yield self._decoded(ch.topic, name, int(record.log_time), record.data, decoder)

    def _decoded(
        self, topic: str, schema_name: str, log_time_ns: int, data: bytes, decoder
    ) -> LogMessage:
        try:
            if self._decompress is not None:
                data = self._decompress(data)
            return LogMessage(topic, schema_name, log_time_ns, decoder(data))
        except Exception as exc:  # noqa: BLE001 - one bad message is a value
            text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            return LogMessage(topic, schema_name, log_time_ns, None, f"cannot decode ({text})")


def _decoder_for(channel, schema_record, path: Path) -> Callable[[bytes], Any]:
    if channel.message_encoding == JSON_ENCODING:
        return _json_message
    if channel.message_encoding != CDR_ENCODING:
        raise InputError(
            f"{path}: topic {channel.topic}: cannot decode message encoding "
            f"'{channel.message_encoding}' (supported: json, ROS 2 cdr)"
        )
    return _cdr_decoder(channel.topic, schema_record, path)


def _cdr_decoder(topic: str, schema_record, path: Path) -> Callable[[bytes], Any]:
    """A decoder of one ROS 2 type built from the definition in the log's schema."""
    encoding = schema_record.encoding if schema_record is not None else ""
    if encoding not in ROS2_SCHEMA_ENCODINGS:
        raise InputError(
            f"{path}: topic {topic}: a cdr channel needs a ros2msg or ros2idl schema, "
            f"has {encoding or 'none'}"
        )
    name = schema_record.name
    store = get_typestore(Stores.EMPTY)
    try:
        text = bytes(schema_record.data).decode("utf-8")
        if encoding == "ros2msg":
            store.register(get_types_from_msg(text, name))
        else:
            store.register(get_types_from_idl(text))
    except Exception as exc:  # noqa: BLE001 - any parse failure of the user's schema
        raise InputError(
            f"{path}: topic {topic}: cannot read the message definition of {name} "
            f"({type(exc).__name__})"
        ) from None
    if name not in store.types:
        raise InputError(f"{path}: topic {topic}: the schema does not define {name}")
    return lambda data: store.deserialize_cdr(data, name)


def _json_message(data: bytes) -> Any:
    """One JSON message; bytes that are not UTF-8 JSON raise ValueError."""
    return json.loads(data.decode("utf-8"))


def read_json_messages(path: str | os.PathLike, topic: str) -> list[dict]:
    """All JSON messages of ``topic`` (for tests and tools)."""
    return [m.decoded for m in McapLog(path).messages([topic]) if not m.error]
