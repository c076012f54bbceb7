"""Any telemetry file in -> ``Telemetry``: the format told by extension, else by content.

=================================  ===========================================
input                              reader
=================================  ===========================================
``.srt`` (DJI sidecar)             ``signpose.io.telemetry_srt.read_srt``
``.ulg`` (PX4 ULog)                ``signpose.io.telemetry_ulog.read_ulog``
``.csv`` (columns: docs/telemetry.md)  ``signpose.io.telemetry_csv``
``.mcap``, rosbag2 folder/``.db3``  ``signpose.io.telemetry_ros`` (NavSatFix, Imu)
=================================  ===========================================

``check_overlap`` refuses telemetry whose time span misses the video's frames.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from signpose.core.errors import InputError
from signpose.estimator.telemetry import Telemetry
from signpose.io.mcap_read import McapLog
from signpose.io.rosbag import is_bag_file, is_bag_folder, open_bag
from signpose.io.telemetry_build import reasons
from signpose.io.telemetry_csv import TIME_COLUMN, read_telemetry_csv
from signpose.io.telemetry_ros import read_log_telemetry
from signpose.io.telemetry_srt import read_srt
from signpose.io.telemetry_ulog import read_ulog

ULOG_MAGIC = b"ULog\x01\x12\x35"
MCAP_MAGIC = b"\x89MCAP"
# With the clock offset left to the fusion to find, the telemetry may be this
# far from the video and still count as overlapping [s].
MAX_UNKNOWN_OFFSET_S = 2.0
_SNIFF_BYTES = 4096


def _kind(p: Path) -> str:
    """``srt``, ``ulog``, ``csv`` or ``log`` (MCAP / rosbag2) for a telemetry path."""
    if p.is_dir():
        if is_bag_folder(p):
            return "log"
        raise InputError(f"{p}: a folder that is not a rosbag2 bag; pass a telemetry file")
    suffix = p.suffix.lower()
    by_suffix = {".srt": "srt", ".ulg": "ulog", ".csv": "csv", ".mcap": "log", ".db3": "log"}
    if suffix in by_suffix:
        return by_suffix[suffix]
    if is_bag_file(p):
        return "log"
    try:
        with open(p, "rb") as f:
            head = f.read(_SNIFF_BYTES)
    except OSError as exc:
        raise InputError(f"{p}: cannot read telemetry file ({exc.strerror})") from None
    if head.startswith(ULOG_MAGIC):
        return "ulog"
    if head.startswith(MCAP_MAGIC):
        return "log"
    text = head.decode("utf-8", errors="replace")
    if "-->" in text:
        return "srt"
    first = next((ln for ln in text.splitlines() if ln.strip() and not ln.startswith("#")), "")
    if TIME_COLUMN in [c.strip() for c in first.split(",")]:
        return "csv"
    raise InputError(
        f"{p}: not a telemetry file signpose reads (DJI .SRT, PX4 .ulg, telemetry CSV, "
        "MCAP or rosbag2 with NavSatFix / Imu)"
    )


@dataclass(frozen=True)
class TelemetryRequest:
    """What the user asked for with ``--telemetry`` (``signpose run`` / ``estimate``).

    Attributes:
        path: the telemetry file; None: the run's input log itself (MCAP /
            rosbag2 with NavSatFix / Imu topics).
        topic: ``--telemetry-topic``: the log's telemetry topic(s), comma-separated.
        clock_offset_s: ``--telemetry-offset``: telemetry time minus video time
            [s]; None: the fusion estimates it.
    """

    path: Path | None = None
    topic: str | None = None
    clock_offset_s: float | None = None


def read_requested(
    request: TelemetryRequest, input_path: str | os.PathLike, video_start_s: float = 0.0
) -> Telemetry:
    """The telemetry a request names (the input log itself when its path is None)."""
    p = request.path
    if p is None:
        p = Path(input_path)
        try:
            kind = _kind(p) if p.exists() else None
        except InputError:  # a video, an image folder
            kind = None
        if kind != "log":
            raise InputError(
                f"{p}: --telemetry-topic without --telemetry reads the input log, and this is "
                "not an MCAP / rosbag2 log; pass --telemetry FILE"
            )
    return read_telemetry(p, request.topic, video_start_s=video_start_s)


def describe(telemetry: Telemetry) -> str:
    """One line for the user: what was read and what was skipped."""
    parts = []
    if telemetry.gnss is not None:
        parts.append(f"{len(telemetry.gnss)} GNSS fixes")
    if telemetry.imu is not None:
        parts.append(f"{len(telemetry.imu)} IMU samples")
    if telemetry.gimbal is not None:
        parts.append(f"{len(telemetry.gimbal)} gimbal angles")
    line = f"telemetry {telemetry.source}: {', '.join(parts) or 'nothing'}"
    if telemetry.skipped:
        line += f"; skipped {reasons(telemetry.skipped)}"
    return line


def read_telemetry(
    path: str | os.PathLike, topic: str | None = None, *, video_start_s: float = 0.0
) -> Telemetry:
    """Read a telemetry file of any supported format.

    Args:
        path: the file (or rosbag2 folder).
        topic: for MCAP / rosbag2 only: the NavSatFix (and Imu) topic(s),
            comma-separated; None picks the log's only ones.
        video_start_s: the video's first frame time [s]; an SRT's subtitle
            times are relative to it (ignored by the other formats).

    Raises:
        InputError: missing or unreadable file, unknown format, no usable sample.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: telemetry file not found")
    kind = _kind(p)
    if topic and kind != "log":
        raise InputError(
            f"{p}: --telemetry-topic applies to MCAP / rosbag2 logs, not to a {kind} file"
        )
    if kind == "srt":
        return read_srt(p, video_start_s)
    if kind == "ulog":
        return read_ulog(p)
    if kind == "csv":
        return read_telemetry_csv(p)
    log = open_bag(p) if (p.is_dir() or is_bag_file(p)) else McapLog(p)
    topics = [t.strip() for t in topic.split(",") if t.strip()] if topic else None
    return read_log_telemetry(log, topics)


def check_overlap(
    telemetry: Telemetry, frame_stamps_s, clock_offset_s: float | None = None
) -> None:
    """Refuse telemetry whose time span does not overlap the video's frames.

    Args:
        frame_stamps_s: (N,) the frames' times on the video's clock [s].
        clock_offset_s: telemetry time minus video time [s] when given;
            None: unknown (to be estimated), up to ``MAX_UNKNOWN_OFFSET_S``.

    Raises:
        InputError: no overlap; the message names the telemetry file and both spans.
    """
    span = telemetry.span_s()
    if span is None or len(frame_stamps_s) == 0:
        return
    offset = clock_offset_s or 0.0
    slack = MAX_UNKNOWN_OFFSET_S if clock_offset_s is None else 0.0
    first, last = float(min(frame_stamps_s)) + offset, float(max(frame_stamps_s)) + offset
    if last + slack >= span[0] and first - slack <= span[1]:
        return
    raise InputError(
        f"{telemetry.source}: telemetry spans {span[0]:.3f}..{span[1]:.3f} s but the video's "
        f"frames are at {first:.3f}..{last:.3f} s: no overlap; pass this flight's telemetry "
        "or --telemetry-offset S (telemetry time minus video time)"
    )
