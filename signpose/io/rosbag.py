"""rosbag2 bags in: a bag folder (``metadata.yaml``) or one of its storage files.

What ``ros2 bag record`` writes, read without ROS:

* storage ``mcap`` (``.mcap``, streamed by ``signpose.io.mcap_read``) or
  ``sqlite3`` (``.db3``, the default of ROS 2 Humble, read by
  ``signpose.io.rosbag_db3`` with Python's ``sqlite3`` and the ``rosbags``
  typestore);
* compression ``none``, ``file`` (each storage file zstd-compressed as
  ``<name>.mcap.zstd`` / ``.db3.zstd``, decompressed here into a temporary
  folder) or ``message`` (each payload zstd-compressed);
* a bag split into several files (read in the order ``metadata.yaml`` lists them).

A folder without ``metadata.yaml`` (a recording killed before it was closed)
is read from its storage files. Damage never raises once a bag is open: a
truncated ``.db3`` is read up to the break through a repaired temporary copy
(the user's file is never written), and ``problem`` says where it stopped.
What a message means (image, camera, stamps) is ``signpose.io.messages``.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import yaml
import zstandard

from signpose.core.errors import InputError
from signpose.core.nesting import check_nesting
from signpose.io.mcap_read import McapLog
from signpose.io.messages import LogChannel, LogMessage, MessageLog
from signpose.io.rosbag_db3 import Db3Log

METADATA_NAME = "metadata.yaml"
STORAGE_SUFFIXES = {".mcap": "mcap", ".db3": "sqlite3"}
ZSTD_SUFFIX = ".zstd"
COMPRESSION_MODES = ("none", "file", "message")
CDR_ENCODING = "cdr"
_COPY_CHUNK_BYTES = 1 << 20
# metadata.yaml lists topics and files: a few kB, a few MB for a bag of thousands of files.
MAX_METADATA_BYTES = 16 << 20


@dataclass(frozen=True)
class BagInfo:
    """What a bag holds, from its ``metadata.yaml`` (or its files when that is missing).

    Attributes:
        folder: the bag folder.
        storage: ``mcap`` or ``sqlite3``.
        files: the storage files, in the order they are read.
        compression: ``none``, ``file`` or ``message`` (zstd).
        topics: the topics with their types and message counts (None when unknown).
        note: what was assumed (e.g. no metadata.yaml), "" when nothing.
    """

    folder: Path
    storage: str
    files: tuple[Path, ...]
    compression: str
    topics: tuple[LogChannel, ...]
    note: str = ""


# --------------------------------------------------------------------------- metadata


def is_bag_folder(path: Path) -> bool:
    """True for a folder with ``metadata.yaml`` or with rosbag2 storage files and no images."""
    if not path.is_dir():
        return False
    return (path / METADATA_NAME).is_file() or bool(_storage_files(path))


def _storage_files(folder: Path) -> list[Path]:
    files = []
    for p in sorted(folder.iterdir()):
        name = p.name.removesuffix(ZSTD_SUFFIX)
        if p.is_file() and Path(name).suffix in STORAGE_SUFFIXES:
            files.append(p)
    return files


def _metadata_fail(path: Path, what: str) -> InputError:
    return InputError(
        f"{path}: {what}; rewrite it with `ros2 bag reindex` or remove it to read the "
        "storage files directly"
    )


def _field(d: dict, key: str, kind: type, path: Path):
    value = d.get(key)
    if not isinstance(value, kind) or isinstance(value, bool):
        raise _metadata_fail(path, f"'{key}' is missing or not a {kind.__name__}")
    return value


def _topics_from_metadata(info: dict, path: Path) -> tuple[LogChannel, ...]:
    topics = []
    for entry in info.get("topics_with_message_count") or []:
        meta = entry.get("topic_metadata") if isinstance(entry, dict) else None
        if not isinstance(meta, dict):
            raise _metadata_fail(path, "a 'topics_with_message_count' entry has no topic_metadata")
        count = entry.get("message_count")
        topics.append(
            LogChannel(
                str(_field(meta, "name", str, path)),
                str(_field(meta, "type", str, path)),
                str(meta.get("serialization_format", CDR_ENCODING)),
                count if isinstance(count, int) and not isinstance(count, bool) else None,
            )
        )
    return tuple(topics)


def read_bag_info(folder: str | os.PathLike) -> BagInfo:
    """Read a bag folder's ``metadata.yaml``; InputError names the file and what is wrong."""
    folder = Path(folder)
    path = folder / METADATA_NAME
    if not path.is_file():
        return _info_from_files(folder)
    size = path.stat().st_size
    if size > MAX_METADATA_BYTES:
        raise _metadata_fail(
            path, f"{size} bytes; a bag's metadata is at most {MAX_METADATA_BYTES}"
        )
    try:
        text = path.read_bytes().decode("utf-8")
        check_nesting(text, path)
        doc = yaml.safe_load(text)
    except yaml.MarkedYAMLError as exc:
        line = exc.problem_mark.line + 1 if exc.problem_mark is not None else "?"
        raise _metadata_fail(path, f"not readable YAML (line {line}: {exc.problem})") from None
    except (OSError, UnicodeDecodeError, yaml.YAMLError, ValueError, RecursionError) as exc:
        raise _metadata_fail(path, f"not readable YAML ({type(exc).__name__})") from None
    info = doc.get("rosbag2_bagfile_information") if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        raise _metadata_fail(path, "no 'rosbag2_bagfile_information' mapping")
    storage = _field(info, "storage_identifier", str, path)
    if storage not in STORAGE_SUFFIXES.values():
        raise InputError(
            f"{path}: storage '{storage}' is not supported (supported: mcap, sqlite3); "
            "convert the bag with `ros2 bag convert`"
        )
    names = _field(info, "relative_file_paths", list, path)
    files = tuple(folder / Path(str(name)).name for name in names)
    if not files:
        raise _metadata_fail(path, "'relative_file_paths' lists no file")
    missing = [p.name for p in files if not p.is_file()]
    if missing:
        raise InputError(f"{path}: lists files that are not in the folder: {', '.join(missing)}")
    mode = str(info.get("compression_mode") or "none").lower()
    fmt = str(info.get("compression_format") or "").lower()
    if mode not in COMPRESSION_MODES:
        raise _metadata_fail(path, f"unknown compression_mode '{mode}' (none, file, message)")
    if mode != "none" and fmt != "zstd":
        raise InputError(f"{path}: compression format '{fmt}' is not supported (zstd)")
    return BagInfo(folder, storage, files, mode, _topics_from_metadata(info, path))


def _info_from_files(folder: Path) -> BagInfo:
    files = _storage_files(folder)
    if not files:
        raise InputError(f"{folder}: no {METADATA_NAME} and no .mcap or .db3 file; not a bag")
    kinds = {STORAGE_SUFFIXES[Path(p.name.removesuffix(ZSTD_SUFFIX)).suffix] for p in files}
    if len(kinds) > 1:
        raise InputError(f"{folder}: holds both .mcap and .db3 files and no {METADATA_NAME}")
    compression = "file" if all(p.name.endswith(ZSTD_SUFFIX) for p in files) else "none"
    note = f"no {METADATA_NAME} (recording not closed?); read {len(files)} storage file(s)"
    return BagInfo(folder, kinds.pop(), tuple(files), compression, (), note)


# --------------------------------------------------------------------------- zstd


def zstd_decompress(data: bytes) -> bytes:
    """One zstd frame (rosbag2's per-message compression), size in the frame or not."""
    return zstandard.ZstdDecompressor().decompressobj().decompress(bytes(data))


def decompress_file(src: Path, dst: Path) -> str | None:
    """Decompress a ``.zstd`` file (one or more frames) into ``dst``; what was readable is kept.

    Returns:
        None, or the reason it stopped early (the compressed file is cut or damaged).
    """
    written = 0
    try:
        with open(src, "rb") as fin, open(dst, "wb") as fout:
            dobj, fed = zstandard.ZstdDecompressor().decompressobj(), False
            pending = b""
            while chunk := pending or fin.read(_COPY_CHUNK_BYTES):
                out = dobj.decompress(chunk)
                fed, pending = True, b""
                fout.write(out)
                written += len(out)
                if dobj.eof:  # one frame done; the rest of the chunk starts the next one
                    pending = dobj.unused_data
                    dobj, fed = zstandard.ZstdDecompressor().decompressobj(), False
            if fed:
                return f"compressed file ends inside a frame after {written} decompressed bytes"
    except zstandard.ZstdError as exc:
        return f"compressed file is damaged after {written} decompressed bytes ({exc})"
    except OSError as exc:
        raise InputError(f"{src}: cannot decompress ({exc.strerror})") from None
    return None


# --------------------------------------------------------------------------- bags


class BagLog:
    """All storage files of a bag, read in order, as one ``MessageLog``.

    Attributes:
        info: what ``metadata.yaml`` says (or what the files say without it).
        problem: where reading stopped early, in each file that did ("; "-joined).
    """

    def __init__(self, info: BagInfo, *, name: str | os.PathLike | None = None):
        self.info = info
        self.path = Path(name) if name is not None else info.folder
        self.problem: str | None = None
        self._tmp: tempfile.TemporaryDirectory | None = None  # for decompressed files
        self._early: dict[int, str] = {}
        self._logs = [self._open(i, p) for i, p in enumerate(info.files)]
        self.channels = self._merged_channels()

    def _open(self, index: int, path: Path) -> MessageLog:
        decompress = zstd_decompress if self.info.compression == "message" else None
        storage_path = path
        if path.name.endswith(ZSTD_SUFFIX):
            if self._tmp is None:
                self._tmp = tempfile.TemporaryDirectory(prefix="signpose-bag-")
            storage_path = Path(self._tmp.name) / path.name.removesuffix(ZSTD_SUFFIX)
            stopped = decompress_file(path, storage_path)
            if stopped is not None:
                self._early[index] = f"{path.name}: {stopped}"
        if self.info.storage == "sqlite3":
            return Db3Log(storage_path, name=path, decompress=decompress)
        return McapLog(storage_path, name=path, decompress=decompress)

    def _merged_channels(self) -> tuple[LogChannel, ...]:
        listed = {c.topic: c for c in self.info.topics}
        merged: dict[str, LogChannel] = {}
        for log in self._logs:
            for c in log.channels:
                seen = merged.get(c.topic)
                if seen is None:
                    merged[c.topic] = c
                    continue
                both = None
                if seen.message_count is not None and c.message_count is not None:
                    both = seen.message_count + c.message_count
                merged[c.topic] = LogChannel(c.topic, c.schema_name, c.message_encoding, both)
        for topic, c in merged.items():
            if c.message_count is None and topic in listed:
                merged[topic] = LogChannel(
                    topic, c.schema_name, c.message_encoding, listed[topic].message_count
                )
        return tuple(merged.values())

    def messages(self, topics: Iterable[str]) -> Iterator[LogMessage]:
        """Decoded messages of ``topics``, file after file."""
        wanted = tuple(topics)
        problems = []
        self.problem = None
        for index, log in enumerate(self._logs):
            yield from log.messages(wanted)
            if index in self._early:
                problems.append(self._early[index])
            if log.problem:
                problems.append(f"{log.path.name}: {log.problem}")
        self.problem = "; ".join(problems) or None


def _listed_in_bag(path: Path) -> BagInfo | None:
    """The bag a storage file belongs to (its folder's metadata.yaml lists it), or None."""
    if not (path.parent / METADATA_NAME).is_file():
        return None
    info = read_bag_info(path.parent)
    if path.name not in {p.name for p in info.files}:
        return None
    return BagInfo(info.folder, info.storage, (path,), info.compression, info.topics, info.note)


def is_bag_file(path: Path) -> bool:
    """True for a ``.db3``, a ``.mcap.zstd``/``.db3.zstd``, or a ``.mcap`` a bag lists."""
    name = path.name.lower()
    if name.endswith((".db3", ".db3" + ZSTD_SUFFIX, ".mcap" + ZSTD_SUFFIX)):
        return True
    return name.endswith(".mcap") and _listed_in_bag(path) is not None


def open_bag(path: str | os.PathLike) -> BagLog:
    """A bag folder, or one storage file of a bag (with its folder's compression).

    Raises:
        InputError: corrupt ``metadata.yaml``, unsupported storage or
            compression, a file that is not a bag.
    """
    p = Path(path)
    if p.is_dir():
        return BagLog(read_bag_info(p))
    info = _listed_in_bag(p)
    if info is None:
        stem = p.name.removesuffix(ZSTD_SUFFIX)
        storage = STORAGE_SUFFIXES.get(Path(stem).suffix.lower())
        if storage is None:
            raise InputError(f"{p}: not a rosbag2 storage file (.mcap or .db3)")
        compression = "file" if p.name.endswith(ZSTD_SUFFIX) else "none"
        info = BagInfo(p.parent, storage, (p,), compression, ())
    return BagLog(info, name=p)
