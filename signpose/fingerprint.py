"""What a flight's outputs were made from, as one digest: a rerun redoes the flight when it changes.

A batch stores the fingerprint in each flight's done marker. It covers the
input (for a file its name, size and modification time; for a folder, every
file's relative name, size and modification time: videos are not read
again, so a rerun over unchanged flights costs a ``stat`` per file), the
map, camera and ground-truth files (their bytes: they are small), the
settings that change the results (as given by the caller, e.g. topic, fps,
cascade) and the signpose version.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path

from signpose import __version__

FINGERPRINT_KEY = "fingerprint"  # its key in a done marker (JSON)
_CHUNK_BYTES = 1 << 20


def _file_digest(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(_CHUNK_BYTES):
            digest.update(chunk)
    return digest.hexdigest()


def _stat(path: Path) -> list:
    st = path.stat()
    return [st.st_size, st.st_mtime_ns]


def input_identity(path: str | os.PathLike) -> list:
    """A file's [name, size, mtime_ns]; a folder's sorted [relative name, size, mtime_ns] rows."""
    p = Path(path)
    if p.is_dir():
        files = sorted(f for f in p.rglob("*") if f.is_file())
        return [[str(f.relative_to(p)), *_stat(f)] for f in files]
    if p.is_file():
        return [p.name, *_stat(p)]
    return [p.name, "missing"]


def content_digest(path: str | os.PathLike | None) -> str:
    """sha256 of a small file's bytes; "" for no file, "missing" when it is not there."""
    if not path:
        return ""
    p = Path(path)
    return _file_digest(p) if p.is_file() else "missing"


def flight_fingerprint(
    input_path: str | os.PathLike,
    map_path: str | os.PathLike,
    camera_path: str | os.PathLike | None,
    gt_path: str | os.PathLike | None,
    settings: Mapping[str, object],
) -> str:
    """The digest of one flight's input, map, camera, ground truth, settings and version.

    Args:
        input_path: video, image folder, MCAP log or rosbag2 folder.
        map_path: the sign map.
        camera_path: the camera file the flight uses, or None (the log's calibration).
        gt_path: the ground truth compared with, or None.
        settings: JSON-able settings that change the outputs.
    """
    record = {
        "version": __version__,
        "input": input_identity(input_path),
        "map": content_digest(map_path),
        "camera": content_digest(camera_path),
        "groundtruth": content_digest(gt_path),
        "settings": dict(settings),
    }
    text = json.dumps(record, sort_keys=True, default=str)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def stored_fingerprint(marker: str | os.PathLike) -> str:
    """The fingerprint kept in a done marker, or "" (none, or an unreadable marker)."""
    try:
        value = json.loads(Path(marker).read_text(encoding="utf-8")).get(FINGERPRINT_KEY, "")
    except (OSError, ValueError, AttributeError):
        return ""
    return value if isinstance(value, str) else ""
