"""Frame sources: a video file, a folder of images or an MCAP log, read lazily.

Every source yields ``Frame`` objects in order. A source that stops early
(truncated or corrupt file) ends the iteration and records where and why in
``problems``; it does not raise. Unusable inputs (missing, empty, unknown
format, ambiguous topic) raise InputError when the source is opened.
"""

from __future__ import annotations

import bisect
import logging
import math
import os
import queue
import re
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from signpose.core.errors import InputError
from signpose.estimator.camera import CameraModel, check_image_size
from signpose.io.clock import mp4_creation_time_ns
from signpose.io.frames_csv import read_frames_csv
from signpose.io.mcap_read import McapLog
from signpose.io.messages import (
    LogChannel,
    LogMessage,
    MessageLog,
    camera_from_message,
    image_from_message,
    is_cut_jpeg,
    message_frame_id,
    message_stamp_ns,
)
from signpose.io.rosbag import METADATA_NAME, is_bag_file, is_bag_folder, open_bag

log = logging.getLogger(__name__)

# FFmpeg prints decoder complaints straight to stderr; signpose reports them itself.
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")

VIDEO_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".webm", ".mpg", ".mpeg", ".ts")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm", ".webp")
MCAP_SUFFIXES = (".mcap",)
TIMES_CSV_NAMES = ("frames.csv", "times.csv")
# Consecutive failed reads after which a video is taken to end: OpenCV's decoders
# resynchronise after a damaged region within a few reads (7 in a damaged H.264 file).
MAX_FAILED_READS = 50


@dataclass(frozen=True)
class Frame:
    """One image of a flight.

    Attributes:
        index: frame index in the source, from 0 (counting frames yielded).
        stamp_ns: capture time [ns] (container/log time, CSV or index / fps).
        image: (H, W) gray or (H, W, 3) BGR uint8 image.
    """

    index: int
    stamp_ns: int
    image: np.ndarray

    @property
    def image_size(self) -> tuple[int, int]:
        """(width, height) [px]."""
        return (int(self.image.shape[1]), int(self.image.shape[0]))

    def gray(self) -> np.ndarray:
        """(H, W) uint8 gray image."""
        if self.image.ndim == 2:
            return self.image
        return cv2.cvtColor(self.image, cv2.COLOR_BGR2GRAY)


class FrameSource:
    """Base of the frame sources: iterate for frames; ``len()`` may be unknown.

    Attributes:
        path: the input.
        length: number of frames expected, or None when unknown.
        camera: a calibration carried by the input itself (MCAP), or None.
        problems: what stopped the reading early, one line each (after iteration).
        clock: where the frame times come from: ``log`` (header stamps), ``csv``
            (frames.csv), ``creation_time`` (a video's own), ``start_time`` (given),
            or ``zero`` (counted from 0).
        frame_id: the images' camera frame id where the input names it (logs,
            once read), else None.
    """

    kind = "input"

    def __init__(self, path: Path):
        self.path = path
        self.length: int | None = None
        self.camera: CameraModel | None = None
        self.problems: list[str] = []
        self.clock = "log"
        self.frame_id: str | None = None
        self._notes: list[str] = []  # problems found on opening, repeated in every pass
        # open_source's arguments, to open the same input in another process.
        self.spec: SourceSpec | None = None

    def __iter__(self) -> Iterator[Frame]:
        """The frames in order; frames of another size than the first are skipped and counted."""
        self.problems = list(self._notes)
        size: tuple[int, int] | None = None
        n_odd = 0
        first_odd = ""  # "frame i, WxH" of the first frame skipped
        index = 0
        for frame in self._read():
            if size is None:
                size = frame.image_size
            elif frame.image_size != size:
                if not n_odd:
                    w, h = frame.image_size
                    first_odd = f"frame {frame.index}, {w}x{h}"
                n_odd += 1
                continue
            yield frame if frame.index == index else replace(frame, index=index)
            index += 1
        if n_odd:
            self._problem(
                f"{n_odd} frame(s) of another size than the first frame's {size[0]}x{size[1]} "
                f"skipped (first: {first_odd})"
            )

    def _read(self) -> Iterator[Frame]:
        """The frames as the input holds them (indices from 0 in reading order)."""
        raise NotImplementedError

    @property
    def range_length(self) -> int | None:
        """Positions a chunk can start at (``read_range``); None: read in order only."""
        return None

    def _read_positions(self, start: int, stop: int | None, read: RangeRead) -> Iterator[Frame]:
        """The frames at positions [start, stop), ``Frame.index`` = position; what went
        wrong goes into ``read``."""
        raise NotImplementedError

    def range_problems(self, reads: list[RangeRead], to_end: bool = True) -> list[str]:
        """The problem lines of the chunks ``reads`` (in order), as one pass in order gives them.

        ``to_end``: the chunk that reads to the end of the input is among ``reads``.

        Raises:
            InputError: no chunk read a frame.
        """
        good = sorted(p for r in reads for p in r.good)
        odd = sorted(o for r in reads for o in r.odd)
        lines = list(self._notes) + [n for r in reads for n in r.notes]
        lines += self._range_tail(reads, sorted(good + [o[0] for o in odd]), to_end)
        if odd:
            position, w, h = odd[0]
            size = next(r.size for r in reads if r.size is not None)
            lines.append(
                f"{self.path}: {len(odd)} frame(s) of another size than the first frame's "
                f"{size[0]}x{size[1]} skipped (first: frame {bisect.bisect_left(good, position)}, "
                f"{w}x{h})"
            )
        for line in lines[len(self._notes) :]:
            log.info("%s", line)
        return lines

    def _range_tail(self, reads: list[RangeRead], readable: list[int], to_end: bool) -> list[str]:
        """What ends a pass (damaged regions, a log cut short); ``readable``: positions read."""
        return []

    def describe(self) -> str:
        n = "?" if self.length is None else str(self.length)
        return f"{self.kind} {self.path} ({n} frames)"

    def _problem(self, text: str) -> None:
        line = f"{self.path}: {text}"
        self.problems.append(line)
        log.info("%s", line)  # the caller reports problems to the user

    def _note(self, text: str) -> None:
        """A problem found on opening: reported with every pass over the frames."""
        self._notes.append(f"{self.path}: {text}")
        self._problem(text)


# --------------------------------------------------------------------------- video


class VideoSource(FrameSource):
    """A video file read with ``cv2.VideoCapture``; stamps from the container."""

    kind = "video"

    def __init__(self, path: Path, start_ns: int | None = None):
        """Args:
        path: the video.
        start_ns: time of the first frame [ns since 1970]; None: the container's
            creation_time where it has one, else 0.
        """
        super().__init__(path)
        created = mp4_creation_time_ns(path) if start_ns is None else None
        self.start_ns = start_ns if start_ns is not None else (created or 0)
        self.clock = (
            "start_time" if start_ns is not None else ("creation_time" if created else "zero")
        )
        cap = cv2.VideoCapture(str(path))
        try:
            if not cap.isOpened():
                raise InputError(f"{path}: {_unopenable_reason(path)}")
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
            self.fps = float(cap.get(cv2.CAP_PROP_FPS)) or 0.0
        finally:
            cap.release()
        self.length = n if n > 0 else None

    def _read(self) -> Iterator[Frame]:
        cap = cv2.VideoCapture(str(self.path))
        index = 0
        damaged = _DamagedReads()
        try:
            last_ns = -1
            while damaged.run <= MAX_FAILED_READS:
                ok, image = cap.read()
                if not ok or image is None:  # damage, or the end: read on a little to tell
                    damaged.failed(index)
                    continue
                damaged.recovered()
                stamp_ns = self._stamp_ns(cap, index + damaged.skipped, last_ns)
                last_ns = stamp_ns
                yield Frame(index, self.start_ns + stamp_ns, image)
                index += 1
        finally:
            cap.release()
        if index == 0:
            raise InputError(f"{self.path}: video has no readable frames")
        if damaged.skipped:
            self._problem(
                f"{damaged.skipped} unreadable frame(s) skipped in {damaged.regions} damaged "
                f"region(s), the first after frame {damaged.first_after}; read on past them"
            )
        if self.length is not None and index + damaged.skipped < self.length:
            self._problem(
                f"video stopped at frame {index + damaged.skipped} of {self.length} "
                f"(the decoder could not read further; truncated or corrupt file)"
            )

    @property
    def range_length(self) -> int | None:
        return self.length

    def _read_positions(self, start: int, stop: int | None, read: RangeRead) -> Iterator[Frame]:
        """From a seek to ``start`` (the same frames as reading in order for the simulator's
        mp4v: tests/test_chunks.py); where the container does not land on ``start``, the
        frames before it are decoded and dropped."""
        cap = cv2.VideoCapture(str(self.path))
        try:
            if start > 0 and not _seek(cap, start):
                cap.release()
                cap = cv2.VideoCapture(str(self.path))
                for _ in range(start):
                    cap.grab()
            position, run, last_ns = start, 0, -1
            while (stop is None or position < stop) and run <= MAX_FAILED_READS:
                ok, image = cap.read()
                if not ok or image is None:
                    read.failed.append(position)
                    run += 1
                else:
                    run = 0
                    last_ns = self._stamp_ns(cap, position, last_ns)
                    yield Frame(position, self.start_ns + last_ns, image)
                position += 1
        finally:
            cap.release()

    def _range_tail(self, reads: list[RangeRead], readable: list[int], to_end: bool) -> list[str]:
        if not readable:
            raise InputError(f"{self.path}: video has no readable frames")
        last = readable[-1]
        failed = sorted(p for r in reads for p in r.failed if p < last)
        lines = []
        if failed:
            regions = 1 + sum(b != a + 1 for a, b in zip(failed, failed[1:], strict=False))
            lines.append(
                f"{self.path}: {len(failed)} unreadable frame(s) skipped in {regions} damaged "
                f"region(s), the first after frame {bisect.bisect_left(readable, failed[0])}; "
                "read on past them"
            )
        if to_end and self.length is not None and last + 1 < self.length:
            lines.append(
                f"{self.path}: video stopped at frame {last + 1} of {self.length} "
                f"(the decoder could not read further; truncated or corrupt file)"
            )
        return lines

    def _stamp_ns(self, cap: cv2.VideoCapture, position: int, last_ns: int) -> int:
        """The container's time of the frame just read; position / fps where it has none."""
        ms = cap.get(cv2.CAP_PROP_POS_MSEC)
        if math.isfinite(ms) and ms >= 0:
            stamp_ns = int(round(ms * 1e6))
        elif self.fps > 0:
            stamp_ns = int(round(position / self.fps * 1e9))
        else:
            stamp_ns = last_ns + 1
        if stamp_ns <= last_ns:  # containers without times: keep stamps increasing
            stamp_ns = int(round(position / self.fps * 1e9)) if self.fps > 0 else last_ns + 1
            stamp_ns = max(stamp_ns, last_ns + 1)
        return stamp_ns


def _seek(cap: cv2.VideoCapture, position: int) -> bool:
    """Seek to frame ``position``; False where the decoder does not say it is there."""
    return bool(cap.set(cv2.CAP_PROP_POS_FRAMES, position)) and (
        int(cap.get(cv2.CAP_PROP_POS_FRAMES)) == position
    )


class _DamagedReads:
    """Failed reads of a video: runs of them, and how many were followed by good frames."""

    def __init__(self) -> None:
        self.run = 0  # failed reads since the last good frame
        self.skipped = 0  # failed reads that good frames followed
        self.regions = 0
        self.first_after: int | None = None  # good frames before the first damaged region
        self._run_after = 0  # good frames before the current run of failed reads

    def failed(self, frames_so_far: int) -> None:
        if self.run == 0:
            self._run_after = frames_so_far
        self.run += 1

    def recovered(self) -> None:
        if self.run:
            self.skipped += self.run
            self.regions += 1
            if self.first_after is None:
                self.first_after = self._run_after
        self.run = 0


def _unopenable_reason(path: Path) -> str:
    if path.suffix.lower() in (".mp4", ".mov", ".m4v"):
        with open(path, "rb") as f:
            head = f.read(64)
            f.seek(0)
            has_index = b"moov" in f.read()
        if b"ftyp" in head and not has_index:
            return (
                "cannot read the video: its index (MP4 'moov' atom) is missing, so the "
                "recording was cut off before it was finalised; no frame can be located "
                "(recover it with a tool such as untrunc, or record to .mkv/.avi)"
            )
    return "cannot open as a video (unknown format or corrupt file)"


# --------------------------------------------------------------------------- folder


def _natural_key(name: str):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


class FolderSource(FrameSource):
    """A folder of images, sorted by name; stamps from frames.csv/times.csv or fps."""

    kind = "folder"

    def __init__(self, path: Path, fps: float | None = None, start_ns: int | None = None):
        """Args:
        path: the folder.
        fps: frame rate: frame i is at ``start_ns + i / fps`` (frames.csv is ignored).
        start_ns: time of the first frame with ``fps`` [ns since 1970]; None: 0.
        """
        super().__init__(path)
        files = sorted(
            (p for p in path.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES),
            key=lambda p: _natural_key(p.name),
        )
        if not files:
            raise InputError(
                f"{path}: folder has no images ({', '.join(IMAGE_SUFFIXES)}); nothing to process"
            )
        csv_path = next((path / n for n in TIMES_CSV_NAMES if (path / n).is_file()), None)
        if fps is not None:
            if not (math.isfinite(fps) and fps > 0):
                raise InputError(f"--fps must be a number > 0, got {fps}")
            t0 = start_ns or 0
            self.items = [(p, t0 + int(round(i / fps * 1e9))) for i, p in enumerate(files)]
            self.clock = "zero" if start_ns is None else "start_time"
        elif start_ns is not None and csv_path is not None:
            raise InputError(
                f"{path}: --start-time is for videos and --fps folders; "
                f"{csv_path.name} gives this folder's times"
            )
        elif csv_path is not None:
            self.clock = "csv"
            self.items = _read_times_csv(csv_path, {p.name: p for p in files})
            unlisted = sorted(set(files) - {p for p, _ in self.items}, key=files.index)
            if unlisted:
                self._note(
                    f"{len(unlisted)} image(s) not listed in {csv_path.name} are left out "
                    f"(first: {unlisted[0].name})"
                )
        else:
            raise InputError(
                f"{path}: no frame times; add frames.csv (columns filename,stamp_ns) or pass --fps"
            )
        self.length = len(self.items)

    def _read(self) -> Iterator[Frame]:
        index = 0
        for p, stamp_ns in self.items:
            image, reason = _read_image(p)
            if image is None:
                self._problem(f"{p.name}: {reason}; skipped")
                continue
            yield Frame(index, stamp_ns, _as_bgr8(image))
            index += 1
        if index == 0:
            raise InputError(f"{self.path}: none of the images could be read")

    @property
    def range_length(self) -> int | None:
        return len(self.items)

    def _read_positions(self, start: int, stop: int | None, read: RangeRead) -> Iterator[Frame]:
        end = len(self.items) if stop is None else min(stop, len(self.items))
        for position in range(start, end):
            p, stamp_ns = self.items[position]
            image, reason = _read_image(p)
            if image is None:
                read.notes.append(f"{self.path}: {p.name}: {reason}; skipped")
                continue
            yield Frame(position, stamp_ns, _as_bgr8(image))

    def _range_tail(self, reads: list[RangeRead], readable: list[int], to_end: bool) -> list[str]:
        if not readable:
            raise InputError(f"{self.path}: none of the images could be read")
        return []


def _as_bgr8(image: np.ndarray) -> np.ndarray:
    """A read image as gray or BGR uint8 (alpha dropped, 16 bits scaled)."""
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if image.dtype != np.uint8:
        image = (image / 257).astype(np.uint8)
    return image


def _read_image(p: Path) -> tuple[np.ndarray | None, str]:
    """The image at ``p``, or (None, why not); a JPEG cut short is refused, not half-read."""
    try:
        data = np.frombuffer(p.read_bytes(), dtype=np.uint8)
    except OSError as exc:
        return None, f"cannot read image ({exc.strerror})"
    if data.size == 0:
        return None, "empty image file"
    if is_cut_jpeg(data):
        return None, "JPEG ends without its end-of-image marker (cut short)"
    image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    return (image, "") if image is not None else (None, "cannot read image")


def _read_times_csv(csv_path: Path, files: dict[str, Path]) -> list[tuple[Path, int]]:
    """(image, stamp_ns) in time order; a name or a stamp listed twice is refused."""
    items = []
    line_of_name: dict[str, int] = {}
    line_of_stamp: dict[int, int] = {}
    for row in read_frames_csv(csv_path):
        name = Path(row.filename).name
        p = files.get(name)
        where = f"{csv_path}: line {row.line}"
        if p is None:
            raise InputError(f"{where}: image {row.filename!r} is not in the folder")
        if name in line_of_name:
            raise InputError(
                f"{where}: image {name!r} is listed again (first on line {line_of_name[name]})"
            )
        if row.stamp_ns in line_of_stamp:
            raise InputError(
                f"{where}: stamp_ns {row.stamp_ns} repeats line {line_of_stamp[row.stamp_ns]}'s; "
                "every frame needs its own time"
            )
        line_of_name[name] = row.line
        line_of_stamp[row.stamp_ns] = row.line
        items.append((p, row.stamp_ns))
    items.sort(key=lambda item: item[1])
    return items


# --------------------------------------------------------------------------- logs


class LogSource(FrameSource):
    """Images of one topic of a recorded log; the camera from a calibration topic if any.

    Frame times are the messages' header stamps; the log time only where a
    header stamp is zero or absent. Attributes beyond ``FrameSource``: ``topic``
    and ``schema_name``.
    """

    kind = "log"

    def __init__(self, path: Path, log: MessageLog, topic: str | None = None):
        super().__init__(path)
        self.log = log
        ch = _image_channel(path, log.channels, topic)
        self.topic = ch.topic
        self.schema_name = ch.schema_name
        self.length = ch.message_count
        if ch.message_count == 0:
            raise InputError(f"{path}: topic {ch.topic} has no messages")
        self.camera = self._find_camera()  # a damaged log is reported by the frames' pass

    def _find_camera(self) -> CameraModel | None:
        cams = [c for c in self.log.channels if c.is_camera]
        if not cams:
            return None
        for msg in self.log.messages([cams[0].topic]):
            if msg.error:
                raise InputError(f"{self.path}: {cams[0].topic}: camera message {msg.error}")
            return camera_from_message(msg.schema_name, msg.decoded, str(self.path))
        return None

    def _frame_of(self, msg: LogMessage) -> tuple[np.ndarray | None, int, str]:
        """(image, stamp_ns, "") of one message, or (None, 0, why it is skipped)."""
        if msg.error:
            return None, 0, msg.error
        image, reason = image_from_message(msg.schema_name, msg.decoded)
        if image is None:
            return None, 0, reason
        try:
            stamp_ns = message_stamp_ns(msg.schema_name, msg.decoded)
        except ValueError as exc:
            return None, 0, f"bad header stamp ({exc})"
        if stamp_ns is None or stamp_ns == 0:
            stamp_ns = msg.log_time_ns
        if self.frame_id is None:
            self.frame_id = message_frame_id(msg.decoded)
        return image, stamp_ns, ""

    def _read(self) -> Iterator[Frame]:
        """Frames in log order; one whose stamp is not after the previous frame's is skipped.

        A repeated or backward header stamp (a driver republishing, a clock
        jump) is never rewritten: such frames are counted and reported once.
        """
        index = 0
        last_ns = -1
        backward: list[int] = []
        for number, msg in enumerate(self.log.messages([self.topic])):
            image, stamp_ns, reason = self._frame_of(msg)
            if image is None:
                self._problem(f"{self.topic}: message {number}: {reason}; skipped")
                continue
            if stamp_ns <= last_ns:
                backward.append(number)
                continue
            last_ns = stamp_ns
            yield Frame(index, stamp_ns, image)
            index += 1
        if backward:
            self._problem(
                f"{self.topic}: {len(backward)} image(s) stamped at or before the previous "
                f"image skipped (first: message {backward[0]}); frame times must increase"
            )
        if self.log.problem:
            self._problem(f"{self.log.problem} (read {index} images of {self.topic})")
        if index == 0:
            raise InputError(f"{self.path}: no readable image on {self.topic}")

    @property
    def range_length(self) -> int | None:
        return self.length

    def _read_positions(self, start: int, stop: int | None, read: RangeRead) -> Iterator[Frame]:
        """Messages before ``start`` are read for their stamps only (no image decoded), so a
        message whose image would not decode counts there for the stamps' order."""
        last_ns = -1
        for number, msg in enumerate(self.log.messages([self.topic])):
            if stop is not None and number >= stop:
                return
            if number < start:
                last_ns = max(last_ns, _stamp_only(msg))
                continue
            image, stamp_ns, reason = self._frame_of(msg)
            if image is None:
                read.notes.append(f"{self.path}: {self.topic}: message {number}: {reason}; skipped")
            elif stamp_ns <= last_ns:
                read.backward.append(number)
            else:
                last_ns = stamp_ns
                yield Frame(number, stamp_ns, image)
        read.log_problem = self.log.problem or ""

    def _range_tail(self, reads: list[RangeRead], readable: list[int], to_end: bool) -> list[str]:
        lines = []
        backward = sorted(p for r in reads for p in r.backward)
        if backward:
            lines.append(
                f"{self.path}: {self.topic}: {len(backward)} image(s) stamped at or before the "
                f"previous image skipped (first: message {backward[0]}); frame times must increase"
            )
        problem = next((r.log_problem for r in reads if r.log_problem), "")
        if problem:
            lines.append(f"{self.path}: {problem} (read {len(readable)} images of {self.topic})")
        if not readable:
            raise InputError(f"{self.path}: no readable image on {self.topic}")
        return lines


def _stamp_only(msg: LogMessage) -> int:
    """A message's frame time without decoding its image; -1 where it has none."""
    if msg.error:
        return -1
    try:
        stamp_ns = message_stamp_ns(msg.schema_name, msg.decoded)
    except ValueError:
        return -1
    return msg.log_time_ns if stamp_ns is None or stamp_ns == 0 else stamp_ns


def _image_channel(path: Path, channels: Iterable[LogChannel], topic: str | None) -> LogChannel:
    """The image topic to read: ``topic``, or the log's only image topic."""
    channels = tuple(channels)
    images = [c for c in channels if c.is_image]
    names = ", ".join(c.topic for c in images) or "none"
    if topic is not None:
        ch = next((c for c in channels if c.topic == topic), None)
        if ch is None:
            raise InputError(f"{path}: no topic '{topic}'; image topics in the log: {names}")
        if not ch.is_image:
            raise InputError(
                f"{path}: topic '{topic}' holds {ch.schema_name or 'unknown messages'}, "
                f"not images; image topics: {names}"
            )
        return ch
    if not images:
        listed = ", ".join(c.describe() for c in channels) or "none"
        raise InputError(
            f"{path}: no image topic (foxglove.CompressedImage/RawImage, "
            f"sensor_msgs/msg/CompressedImage/Image); topics in the log: {listed}"
        )
    if len(images) > 1:
        raise InputError(f"{path}: several image topics ({names}); choose one with --topic")
    return images[0]


class McapSource(LogSource):
    """Images of one topic of an MCAP file (Foxglove JSON or ROS 2 CDR messages)."""

    kind = "mcap"

    def __init__(self, path: Path, topic: str | None = None):
        super().__init__(path, McapLog(path), topic)


class BagSource(LogSource):
    """Images of one topic of a rosbag2 bag: its folder, or one of its storage files."""

    kind = "rosbag2"

    def __init__(self, path: Path, topic: str | None = None):
        log = open_bag(path)
        super().__init__(path, log, topic)
        if log.info.note:
            self._note(log.info.note)


# --------------------------------------------------------------------------- entry point


def open_source(
    path: str | Path,
    *,
    topic: str | None = None,
    fps: float | None = None,
    start_ns: int | None = None,
) -> FrameSource:
    """Open a video file, a folder of images, an MCAP log or a rosbag2 bag by what ``path`` is.

    A bag is a folder with ``metadata.yaml`` (or with only .mcap/.db3 files), a
    ``.db3``, a ``.mcap.zstd``/``.db3.zstd``, or a ``.mcap`` its folder's
    ``metadata.yaml`` lists (so the bag's compression applies).

    Args:
        path: the input.
        topic: image topic of a log or bag (needed when it has several).
        fps: frame rate for a folder without a times CSV (overrides the CSV).
        start_ns: the first frame's time [ns since 1970] for a video or an
            ``fps`` folder (``signpose.io.clock.parse_start_time``); logs, bags
            and frames.csv carry their own times and refuse it.

    Raises:
        InputError: missing, empty or unknown input, or an ambiguous topic.
    """
    source = _open(Path(path), topic, fps, start_ns)
    source.spec = SourceSpec(str(path), topic, fps, start_ns)
    return source


def _open(p: Path, topic: str | None, fps: float | None, start_ns: int | None) -> FrameSource:
    if not p.exists():
        raise InputError(f"{p}: input not found")
    if p.is_dir() and not (
        (p / METADATA_NAME).is_file() or (not _has_images(p) and is_bag_folder(p))
    ):
        return FolderSource(p, fps=fps, start_ns=start_ns)
    if p.is_file() and p.stat().st_size == 0:
        raise InputError(f"{p}: input file is empty")
    suffix = p.suffix.lower()
    is_log = p.is_dir() or is_bag_file(p) or suffix in MCAP_SUFFIXES or _has_mcap_magic(p)
    if is_log and start_ns is not None:
        raise InputError(
            f"{p}: --start-time is for videos and --fps folders; a log has its own times"
        )
    if p.is_dir() or is_bag_file(p):
        return BagSource(p, topic=topic)
    if is_log:
        return McapSource(p, topic=topic)
    if suffix in IMAGE_SUFFIXES:
        raise InputError(f"{p}: a single image; pass the folder that holds the frames")
    return VideoSource(p, start_ns=start_ns)


def _has_images(folder: Path) -> bool:
    return any(p.suffix.lower() in IMAGE_SUFFIXES for p in folder.iterdir() if p.is_file())


def _has_mcap_magic(p: Path) -> bool:
    try:
        with open(p, "rb") as f:
            return f.read(8) == b"\x89MCAP0\r\n"
    except OSError:
        return False


def check_source_camera(source_name: str, camera: CameraModel, image_size: tuple[int, int]) -> None:
    """InputError when the images are not the camera's size (estimator.camera.check_image_size)."""
    check_image_size(camera, image_size[0], image_size[1], source_name)


# --------------------------------------------------------------------------- prefetch


@dataclass(frozen=True)
class PrefetchedFrame:
    """A frame read ahead by ``prefetch``.

    Attributes:
        frame: the frame.
        gray: (H, W) uint8 gray image of it.
        read_s: time the reader thread spent reading/decoding and converting it [s].
    """

    frame: Frame
    gray: np.ndarray
    read_s: float


def prefetch(source: FrameSource, depth: int = 4) -> Iterator[PrefetchedFrame]:
    """Read and decode ``source`` in a background thread, ``depth`` frames ahead.

    Video decoding and colour conversion release the GIL, so on two cores they
    overlap with the detector. Errors of the source (InputError ...) are
    raised here, in the consumer; closing the generator (or Ctrl-C in the
    consumer) stops the reader.
    """
    q: queue.Queue = queue.Queue(maxsize=max(1, depth))
    stop = threading.Event()
    done = object()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def reader() -> None:
        try:
            it = iter(source)
            while not stop.is_set():
                t0 = time.perf_counter()
                try:
                    frame = next(it)
                except StopIteration:
                    break
                gray = frame.gray()
                if not put(PrefetchedFrame(frame, gray, time.perf_counter() - t0)):
                    return
        except BaseException as exc:  # noqa: BLE001 - handed to the consumer
            put(exc)
            return
        put(done)

    thread = threading.Thread(target=reader, name="signpose-reader", daemon=True)
    thread.start()
    try:
        while True:
            item = q.get()
            if item is done:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        thread.join(timeout=5.0)


# --------------------------------------------------------------------------- chunks
# pipeline.observe reads a flight in chunks of source positions, each on its own
# (in another process), from a seek where the input has one: a position is a
# video's frame number, a folder's image number (in time order) or a log topic's
# message number. A frame's index in the flight is the number of frames of the
# chunks before it plus its place in its chunk (the caller counts them).


@dataclass(frozen=True)
class SourceSpec:
    """What opens the same input again (in another process): ``open_source``'s arguments."""

    path: str
    topic: str | None = None
    fps: float | None = None
    start_ns: int | None = None

    def open(self) -> FrameSource:
        return open_source(self.path, topic=self.topic, fps=self.fps, start_ns=self.start_ns)


@dataclass
class RangeRead:
    """What reading the positions [start, stop) of a source met (``read_range``).

    Attributes:
        start: first position asked for.
        stop: the position after the last one asked for; None: to the end.
        size: (width, height) [px] of the flight's frames, or None: the first read's.
        good: positions read as frames of that size, in order.
        failed: positions a video's decoder could not read.
        notes: problem lines of single positions (an unreadable image, a bad message).
        odd: (position, width, height) of frames of another size, left out.
        backward: message positions stamped at or before the previous image, left out.
        log_problem: the log's own problem where reading stopped, else "".
    """

    start: int
    stop: int | None
    size: tuple[int, int] | None = None
    good: list[int] = field(default_factory=list)
    failed: list[int] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    odd: list[tuple[int, int, int]] = field(default_factory=list)
    backward: list[int] = field(default_factory=list)
    log_problem: str = ""


def read_range(source: FrameSource, read: RangeRead) -> Iterator[Frame]:
    """The frames at positions [read.start, read.stop) of ``source``, ``Frame.index`` = position.

    Needs ``source.range_length`` (not None). Frames of another size than
    ``read.size`` (default: the first frame's) are left out; what went wrong
    is recorded in ``read``, and ``source.range_problems`` turns the reads of
    every chunk into the lines a pass in order gives.
    """
    for frame in source._read_positions(read.start, read.stop, read):
        if read.size is None:
            read.size = frame.image_size
        if frame.image_size != read.size:
            read.odd.append((frame.index, *frame.image_size))
            continue
        read.good.append(frame.index)
        yield frame
