"""MCAP logs out: signpose's writer, the simulator's flight log and result.mcap.

Files hold JSON-encoded Foxglove messages (``signpose.io.foxglove`` builds
them and ships their schemas) and appear atomically on close.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from mcap.writer import Writer
from tqdm import tqdm

from signpose.core.closing import PublishOnExit
from signpose.core.errors import OutputError
from signpose.core.fileio import atomic_path
from signpose.core.units import stamp_ns_from_s
from signpose.estimator.camera import CameraModel
from signpose.estimator.trajectory import Trajectory
from signpose.frontend.observations import FrameObservations
from signpose.io.foxglove import (
    CAMERA_FRAME,
    camera_calibration,
    compressed_image,
    frame_transforms,
    image_annotations,
    location_fix,
    method_color,
    pose_in_frame,
    scene_update,
    schema_text,
)
from signpose.io.geo_out import GNSS_NAME, GeoTrack
from signpose.io.tracks import pose_tracks
from signpose.maps.loader import SignMap

JSON_ENCODING = "json"

# Topics of signpose's own logs.
IMAGE_TOPIC = "/camera/image/compressed"
CALIBRATION_TOPIC = "/camera/calibration"
GROUNDTRUTH_TOPIC = "/groundtruth/pose"
ANNOTATIONS_TOPIC = "/signpose/detections"
SCENE_TOPIC = "/signpose/scene"
TF_TOPIC = "/tf"
GNSS_FIX_TOPIC = "/gnss/fix"
GNSS_FRAME = "gnss"
# foxglove.LocationFix of a georeferenced track (the GNSS fixes: GNSS_FIX_TOPIC).
LOCATION_TOPIC = "/signpose/{name}/fix"
_GNSS_RGBA = (0.94, 0.61, 0.24, 1.0)


class McapJsonWriter(PublishOnExit):
    """Writes JSON-encoded Foxglove messages to an MCAP file, atomically.

    The file appears at ``path`` only on ``close()``; ``abort()`` (or an
    exception inside ``with``) removes the partial file.
    """

    def __init__(self, path: str | os.PathLike, chunk_size: int = 256 * 1024):
        self.path = Path(path)
        self._stack = contextlib.ExitStack()
        self._tmp = self._stack.enter_context(atomic_path(self.path))
        try:
            self._file = open(self._tmp, "wb")  # noqa: SIM115 - closed in close()/abort()
        except OSError as exc:
            self._stack.__exit__(type(exc), exc, None)
            raise OutputError(f"{self.path}: cannot write ({exc.strerror})") from None
        self._writer = Writer(self._file, chunk_size=chunk_size)
        self._writer.start(profile="", library="signpose")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._sequence = 0
        self._open = True

    def _channel(self, topic: str, schema_name: str) -> int:
        channel_id = self._channels.get(topic)
        if channel_id is None:
            schema_id = self._schemas.get(schema_name)
            if schema_id is None:
                schema_id = self._writer.register_schema(
                    f"foxglove.{schema_name}", "jsonschema", schema_text(schema_name).encode()
                )
                self._schemas[schema_name] = schema_id
            channel_id = self._writer.register_channel(topic, JSON_ENCODING, schema_id)
            self._channels[topic] = channel_id
        return channel_id

    def write(self, topic: str, schema_name: str, message: dict, log_time_ns: int) -> None:
        """Append one message; ``schema_name`` without the ``foxglove.`` prefix."""
        channel_id = self._channel(topic, schema_name)
        data = json.dumps(message, separators=(",", ":")).encode()
        t = max(0, int(log_time_ns))
        try:
            self._writer.add_message(channel_id, t, data, t, self._sequence)
        except OSError as exc:  # a full disk: the partial file goes, the message names ours
            self.abort()
            raise OutputError(f"{self.path}: cannot write ({exc.strerror or exc})") from None
        self._sequence += 1

    def close(self) -> None:
        """Finish the file and move it into place."""
        if not self._open:
            return
        self._open = False
        try:
            self._writer.finish()
            self._file.close()
        except BaseException as exc:
            self._file.close()
            self._stack.__exit__(type(exc), exc, exc.__traceback__)
            if isinstance(exc, OSError):
                raise OutputError(f"{self.path}: cannot write ({exc.strerror or exc})") from None
            raise
        self._stack.close()

    def abort(self) -> None:
        """Drop the partial file."""
        if not self._open:
            return
        self._open = False
        self._file.close()
        self._stack.__exit__(KeyboardInterrupt, KeyboardInterrupt(), None)


class McapFrameWriter(PublishOnExit):
    """The simulator's ``--format mcap`` output: images, ground truth and the camera.

    Implements ``signpose.sim.flight.FrameWriter``. Topics: ``/camera/image/compressed``
    (foxglove.CompressedImage, JPEG), ``/camera/calibration`` (foxglove.CameraCalibration,
    once, before the first image), and, when the true poses are given,
    ``/groundtruth/pose`` (foxglove.PoseInFrame, world_T_cam) and ``/tf``
    (foxglove.FrameTransforms world -> camera).
    """

    def __init__(
        self,
        path: str | os.PathLike,
        camera: CameraModel,
        world_frame: str = "world",
        world_T_cams: np.ndarray | None = None,
        jpeg_quality: int = 90,
        chunk_size: int = 256 * 1024,
    ):
        """Args:
        path: the ``.mcap`` to write (appears on ``close()``).
        camera: the camera of the images.
        world_frame: name of the world frame (the map's ``frame``).
        world_T_cams: (N, 4, 4) true camera pose of frame i, or None.
        jpeg_quality: JPEG quality of the images.
        chunk_size: MCAP chunk size [bytes]; small chunks lose less to truncation.
        """
        self._writer = McapJsonWriter(path, chunk_size=chunk_size)
        self.path = self._writer.path
        self.camera = camera
        self.world_frame = world_frame
        self.world_T_cams = None if world_T_cams is None else np.asarray(world_T_cams, float)
        self.jpeg_quality = jpeg_quality
        self._calibrated = False
        self.frames_written = 0

    def write(self, frame_index: int, stamp_ns: int, bgr: np.ndarray) -> None:
        """One frame: (H, W, 3) BGR or (H, W) gray image at ``stamp_ns``."""
        if not self._calibrated:
            self._writer.write(
                CALIBRATION_TOPIC,
                "CameraCalibration",
                camera_calibration(stamp_ns, self.camera),
                stamp_ns,
            )
            self._calibrated = True
        msg = compressed_image(stamp_ns, bgr, quality=self.jpeg_quality)
        self._writer.write(IMAGE_TOPIC, "CompressedImage", msg, stamp_ns)
        poses = self.world_T_cams
        if poses is not None and 0 <= frame_index < len(poses):
            T = poses[frame_index]
            self._writer.write(
                GROUNDTRUTH_TOPIC,
                "PoseInFrame",
                pose_in_frame(stamp_ns, self.world_frame, T),
                stamp_ns,
            )
            self._writer.write(
                TF_TOPIC,
                "FrameTransforms",
                frame_transforms(stamp_ns, self.world_frame, CAMERA_FRAME, T),
                stamp_ns,
            )
        self.frames_written += 1

    def close(self) -> Path:
        self._writer.close()
        return self.path

    def abort(self) -> None:
        self._writer.abort()


def write_result_mcap(
    path: str | os.PathLike,
    sign_map: SignMap,
    frames: list[FrameObservations],
    trajectories: dict[str, Trajectory],
    camera: CameraModel | None = None,
    images: Iterable[tuple[int, np.ndarray]] | None = None,
    jpeg_quality: int = 85,
    progress: bool = False,
    camera_frame: str = CAMERA_FRAME,
    geo_tracks: tuple[GeoTrack, ...] = (),
) -> None:
    """The result log for Foxglove, written atomically.

    Args:
        path: output ``.mcap``.
        sign_map: the signs (scene) and the world frame name.
        frames: the observations per frame (image annotations).
        trajectories: method name -> estimated world_T_cam per stamp; each gets
            ``/signpose/<method>/pose``; the first one named ``smoothed`` (else
            the first) drives ``/tf`` world -> camera. NaN positions are skipped.
        camera: written once as foxglove.CameraCalibration when given.
        images: (stamp_ns, image) pairs, written as JPEG foxglove.CompressedImage.
        jpeg_quality: JPEG quality of the images.
        progress: show a tqdm bar over frames.
        camera_frame: the input's camera frame id (the /tf child and the images' frame).
        geo_tracks: WGS84 tracks written as foxglove.LocationFix (Foxglove's map
            panel): an estimated one on ``/signpose/<name>/fix`` at its frames,
            the GNSS fixes (name ``gnss``) on ``/gnss/fix`` at their own times.
    """

    world = sign_map.frame
    t0 = frames[0].stamp_ns if frames else 0
    tf_name = "smoothed" if "smoothed" in trajectories else next(iter(trajectories), None)
    tracks = pose_tracks(trajectories)
    image_iter = iter(images) if images is not None else None
    fixes = _LocationFixes(geo_tracks, camera_frame)
    with McapJsonWriter(path) as writer:
        writer.write(SCENE_TOPIC, "SceneUpdate", scene_update(t0, sign_map, trajectories), t0)
        if camera is not None:
            calibration = camera_calibration(t0, camera, camera_frame)
            writer.write(CALIBRATION_TOPIC, "CameraCalibration", calibration, t0)
        for obs in tqdm(frames, desc="result.mcap", unit="frame", disable=not progress):
            t = obs.stamp_ns
            if image_iter is not None:
                item = next(image_iter, None)
                if item is not None:
                    msg = compressed_image(item[0], item[1], camera_frame, jpeg_quality)
                    writer.write(IMAGE_TOPIC, "CompressedImage", msg, item[0])
            writer.write(ANNOTATIONS_TOPIC, "ImageAnnotations", image_annotations(obs), t)
            fixes.write_until(writer, t)
            for name, track in tracks.items():
                T = track.at(t)
                if T is None:
                    continue
                writer.write(f"/signpose/{name}/pose", "PoseInFrame", pose_in_frame(t, world, T), t)
                if name == tf_name:
                    writer.write(
                        TF_TOPIC, "FrameTransforms", frame_transforms(t, world, camera_frame, T), t
                    )
        fixes.write_until(writer, None)


class _LocationFixes:
    """foxglove.LocationFix messages of WGS84 tracks, written in time order with the frames."""

    def __init__(self, tracks: tuple[GeoTrack, ...], camera_frame: str):
        self._messages: list[tuple[int, str, dict]] = []
        for i, track in enumerate(tracks):
            gnss = track.name == GNSS_NAME
            topic = GNSS_FIX_TOPIC if gnss else LOCATION_TOPIC.format(name=track.name)
            rgba = _GNSS_RGBA if gnss else method_color(track.name, i)
            frame = GNSS_FRAME if gnss else camera_frame
            for k in range(len(track)):
                t_ns = stamp_ns_from_s(track.stamps_s[k])
                msg = location_fix(
                    t_ns,
                    frame,
                    track.lat_deg[k],
                    track.lon_deg[k],
                    track.height_m[k],
                    track.sigma_enu_m[k],
                    rgba,
                )
                self._messages.append((t_ns, topic, msg))
        self._messages.sort(key=lambda m: m[0])
        self._next = 0

    def write_until(self, writer: McapJsonWriter, t_ns: int | None) -> None:
        """Write the fixes stamped up to ``t_ns`` (+1 us, float stamps), or all with None."""
        while self._next < len(self._messages):
            stamp, topic, msg = self._messages[self._next]
            if t_ns is not None and stamp > t_ns + 1000:
                return
            writer.write(topic, "LocationFix", msg, stamp)
            self._next += 1
