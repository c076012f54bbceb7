"""Where a simulated flight's frames go: mp4 video, a PNG folder or an MCAP log.

Every writer publishes its output atomically: a temporary name beside the
target while frames are written, renamed into place on ``close``, removed on
``abort`` (a context manager does either).

Outputs:
    video.mp4                      mp4v video (``Mp4Writer``)
    frames/NNNNNN.png + frames.csv one PNG per frame and their stamps
                                   (``PngWriter``; ``signpose.io.frames_csv``)
    flight.mcap                    images, ground truth and camera
                                   (``signpose.io.mcap.McapFrameWriter``)
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np

from signpose.core.closing import PublishOnExit
from signpose.core.errors import InputError, OutputError
from signpose.core.fileio import atomic_path, umask_mode
from signpose.estimator.camera import CameraModel
from signpose.io.frames_csv import FrameStamp, write_frames_csv
from signpose.io.mcap import McapFrameWriter

FORMATS = ("mp4", "png", "mcap")


class FrameWriter(Protocol):
    """Where rendered frames go. Use as a context manager: on an exception the
    partial output is removed; on success ``close`` publishes it atomically.

    Implement ``write``, ``close``, ``abort`` and the context-manager pair for
    another container (``signpose.io.mcap.McapFrameWriter`` does, for MCAP with
    foxglove.CompressedImage), then return it from ``make_frame_writer`` and add
    its name to ``FORMATS``.
    """

    path: Path

    def write(self, frame_index: int, stamp_ns: int, bgr: np.ndarray) -> None:
        """Add frame ``frame_index`` ((H, W, 3) uint8 BGR) taken at ``stamp_ns``."""
        ...

    def close(self) -> Path:
        """Finish and publish the output; return its path."""
        ...

    def abort(self) -> None:
        """Remove the partial output."""
        ...

    def __enter__(self) -> FrameWriter: ...

    def __exit__(self, exc_type, exc, tb) -> None: ...


class Mp4Writer(PublishOnExit):
    """``video.mp4`` (fourcc mp4v), written to a temporary name and renamed on close."""

    def __init__(self, path: Path, fps: float, size: tuple[int, int]):
        self.path = Path(path)
        self._stack = contextlib.ExitStack()
        self._tmp = self._stack.enter_context(atomic_path(self.path))
        self._vw = cv2.VideoWriter(
            str(self._tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), size
        )
        if not self._vw.isOpened():
            self._vw.release()
            self.abort()
            raise OutputError(f"{self.path}: cannot open an mp4v video writer")
        self._size = size

    def write(self, frame_index: int, stamp_ns: int, bgr: np.ndarray) -> None:
        self._vw.write(bgr)

    def close(self) -> Path:
        self._vw.release()
        self._stack.close()
        return self.path

    def abort(self) -> None:
        with contextlib.suppress(Exception):
            self._vw.release()
        self._stack.__exit__(OutputError, OutputError("aborted"), None)


class PngWriter(PublishOnExit):
    """``frames/NNNNNN.png`` plus ``frames/frames.csv`` (filename,stamp_ns), so the folder
    is a ready input for ``signpose run`` without ``--fps``; written into a temporary
    folder that replaces ``frames`` on close."""

    def __init__(self, path: Path):
        self.path = Path(path)
        try:
            self._tmp = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent))
        except OSError as exc:
            raise OutputError(f"{self.path}: cannot write here ({exc.strerror})") from None
        # mkdtemp makes a private folder; give it the usual permissions.
        os.chmod(self._tmp, umask_mode(directory=True))
        self._stamps: list[FrameStamp] = []

    def write(self, frame_index: int, stamp_ns: int, bgr: np.ndarray) -> None:
        target = self._tmp / f"{frame_index:06d}.png"
        if not cv2.imwrite(str(target), bgr):
            raise OutputError(f"{self.path}: could not write {target.name}")
        self._stamps.append(FrameStamp(target.name, int(stamp_ns)))

    def close(self) -> Path:
        write_frames_csv(self._tmp / "frames.csv", self._stamps)
        old = None
        if self.path.exists():
            old = self.path.parent / f".{self.path.name}.old.{os.getpid()}"
            os.replace(self.path, old)
        os.replace(self._tmp, self.path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        return self.path

    def abort(self) -> None:
        shutil.rmtree(self._tmp, ignore_errors=True)


def make_frame_writer(
    fmt: str,
    out_dir: Path,
    fps: float,
    camera: CameraModel,
    world_T_cams: np.ndarray | None = None,
    world_frame: str = "world",
) -> FrameWriter:
    """The frame writer for ``fmt`` ("mp4", "png" or "mcap") in ``out_dir``.

    Args:
        fmt: one of ``FORMATS``.
        out_dir: the output folder.
        fps: frame rate [Hz].
        camera: the camera of the frames (image size; containers that store
            the calibration use all of it).
        world_T_cams: (N, 4, 4) true pose of frame i, for containers that store
            ground truth next to the images (unused by mp4/png).
        world_frame: name of the world frame (the map's ``frame``).
    """
    size = (camera.width, camera.height)
    if fmt == "mp4":
        return Mp4Writer(Path(out_dir) / "video.mp4", fps, size)
    if fmt == "png":
        return PngWriter(Path(out_dir) / "frames")
    if fmt == "mcap":
        return McapFrameWriter(Path(out_dir) / "flight.mcap", camera, world_frame, world_T_cams)
    raise InputError(f"unknown format {fmt!r}; choose from {', '.join(FORMATS)}")
