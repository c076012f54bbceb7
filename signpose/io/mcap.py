"""MCAP logs: the one module that reads and writes them.

Written files use JSON message encoding with signpose's own jsonschema
definitions of the Foxglove messages (``signpose/schemas/<Name>.json``):
timestamps are ``{"sec", "nsec"}``, bytes are base64 strings, enums are
integers. Poses are ``world_T_cam`` in the map's world frame (z up), the
camera frame being OpenCV's (x right, y down, z forward).

Read files may hold images as ``foxglove.CompressedImage`` / ``foxglove.RawImage``
(JSON) or ROS 2 ``sensor_msgs/msg/CompressedImage`` / ``sensor_msgs/msg/Image``
(CDR, via mcap-ros2-support), and the camera as ``foxglove.CameraCalibration``
or ``sensor_msgs/msg/CameraInfo``. Reading is streamed record by record, so a
truncated or corrupt log yields what is readable and then says where it stopped.
"""

from __future__ import annotations

import base64
import contextlib
import json
import logging
import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from signpose.core.errors import InputError, OutputError
from signpose.core.fileio import atomic_path
from signpose.estimator.camera import EQUIDISTANT, PLUMB_BOB, CameraModel
from signpose.estimator.trajectory import Trajectory, quat_xyzw_from_rotation
from signpose.frontend.observations import FrameObservations
from signpose.maps.loader import SignMap

log = logging.getLogger(__name__)

JSON_ENCODING = "json"
SCHEMA_NAMES = (
    "CameraCalibration",
    "CompressedImage",
    "FrameTransforms",
    "ImageAnnotations",
    "PoseInFrame",
    "RawImage",
    "SceneUpdate",
)
IMAGE_SCHEMAS = (
    "foxglove.CompressedImage",
    "foxglove.RawImage",
    "sensor_msgs/msg/CompressedImage",
    "sensor_msgs/msg/Image",
)
CAMERA_SCHEMAS = ("foxglove.CameraCalibration", "sensor_msgs/msg/CameraInfo")

# Topics of signpose's own logs.
CAMERA_FRAME = "camera"
IMAGE_TOPIC = "/camera/image/compressed"
CALIBRATION_TOPIC = "/camera/calibration"
GROUNDTRUTH_TOPIC = "/groundtruth/pose"
ANNOTATIONS_TOPIC = "/signpose/detections"
SCENE_TOPIC = "/signpose/scene"
TF_TOPIC = "/tf"

# RGBA in [0, 1] per method; others cycle through the extra colours.
_METHOD_COLORS = {
    "groundtruth": (0.2, 0.2, 0.2, 1.0),
    "baseline": (0.85, 0.33, 0.1, 1.0),
    "smoothed": (0.0, 0.45, 0.74, 1.0),
}
_EXTRA_COLORS = ((0.47, 0.67, 0.19, 1.0), (0.49, 0.18, 0.56, 1.0), (0.93, 0.69, 0.13, 1.0))


# --------------------------------------------------------------------------- schemas


@cache
def schema_text(name: str) -> str:
    """The jsonschema of ``foxglove.<name>`` as shipped in ``signpose/schemas``."""
    if name not in SCHEMA_NAMES:
        raise KeyError(f"no schema for {name!r}")
    return resources.files("signpose.io").joinpath("schemas", f"{name}.json").read_text("utf-8")


def schema(name: str) -> dict:
    """The jsonschema of ``foxglove.<name>`` as a dict."""
    return json.loads(schema_text(name))


# --------------------------------------------------------------------------- message builders


def stamp_dict(stamp_ns: int) -> dict:
    """A Foxglove timestamp; negative stamps are clamped to 0."""
    ns = max(0, int(stamp_ns))
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _color(rgba: Iterable[float]) -> dict:
    r, g, b, a = (float(v) for v in rgba)
    return {"r": r, "g": g, "b": b, "a": a}


def method_color(name: str, index: int = 0) -> tuple[float, float, float, float]:
    """RGBA in [0, 1] used for method ``name`` in plots and scenes."""
    return _METHOD_COLORS.get(name, _EXTRA_COLORS[index % len(_EXTRA_COLORS)])


def _pose(world_T_x: np.ndarray) -> dict:
    T = np.asarray(world_T_x, dtype=float)
    qx, qy, qz, qw = quat_xyzw_from_rotation(T[:3, :3])[0]
    x, y, z = (float(v) for v in T[:3, 3])
    return {
        "position": {"x": x, "y": y, "z": z},
        "orientation": {"x": float(qx), "y": float(qy), "z": float(qz), "w": float(qw)},
    }


_IDENTITY_POSE = _pose(np.eye(4))


def pose_in_frame(stamp_ns: int, frame_id: str, world_T_cam: np.ndarray) -> dict:
    """foxglove.PoseInFrame of a camera pose (4, 4) in world frame ``frame_id``."""
    return {"timestamp": stamp_dict(stamp_ns), "frame_id": frame_id, "pose": _pose(world_T_cam)}


def frame_transforms(stamp_ns: int, parent: str, child: str, parent_T_child: np.ndarray) -> dict:
    """foxglove.FrameTransforms with the one transform ``parent_T_child`` (4, 4)."""
    p = _pose(parent_T_child)
    return {
        "transforms": [
            {
                "timestamp": stamp_dict(stamp_ns),
                "parent_frame_id": parent,
                "child_frame_id": child,
                "translation": p["position"],
                "rotation": p["orientation"],
            }
        ]
    }


def compressed_image(
    stamp_ns: int, image: np.ndarray, frame_id: str = CAMERA_FRAME, quality: int = 90
) -> dict:
    """foxglove.CompressedImage (JPEG) of a gray (H, W) or BGR (H, W, 3) image."""
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return {
        "timestamp": stamp_dict(stamp_ns),
        "frame_id": frame_id,
        "data": base64.b64encode(buf.tobytes()).decode("ascii"),
        "format": "jpeg",
    }


def camera_calibration(stamp_ns: int, camera: CameraModel, frame_id: str = CAMERA_FRAME) -> dict:
    """foxglove.CameraCalibration of ``camera``."""
    K = [float(v) for v in camera.K.reshape(-1)]
    P = [K[0], K[1], K[2], 0.0, K[3], K[4], K[5], 0.0, K[6], K[7], K[8], 0.0]
    model = (
        "kannala_brandt"
        if camera.model == EQUIDISTANT
        else ("rational_polynomial" if camera.dist.size > 5 else "plumb_bob")
    )
    return {
        "timestamp": stamp_dict(stamp_ns),
        "frame_id": frame_id,
        "width": int(camera.width),
        "height": int(camera.height),
        "distortion_model": model,
        "D": [float(v) for v in camera.dist.reshape(-1)],
        "K": K,
        "R": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "P": P,
    }


def _entity(stamp_ns: int, frame_id: str, entity_id: str, **primitives) -> dict:
    entity = {
        "timestamp": stamp_dict(stamp_ns),
        "frame_id": frame_id,
        "id": entity_id,
        "lifetime": {"sec": 0, "nsec": 0},
        "frame_locked": False,
        "metadata": [],
    }
    for key in ("arrows", "cubes", "spheres", "cylinders", "lines", "triangles", "texts", "models"):
        entity[key] = primitives.get(key, [])
    return entity


def scene_update(
    stamp_ns: int, sign_map: SignMap, trajectories: dict[str, Trajectory] | None = None
) -> dict:
    """foxglove.SceneUpdate: signs as thin discs with their code, trajectories as line strips."""
    entities = []
    for sign in sign_map.signs:
        if sign.oriented:
            world_T_sign = sign.world_T_sign()
        else:
            world_T_sign = np.eye(4)
            world_T_sign[:3, 3] = sign.center_m
        d = float(sign.diameter_m)
        label_T = np.eye(4)
        label_T[:3, 3] = sign.center_m + np.array([0.0, 0.0, 0.65 * d])
        disc = {
            "pose": _pose(world_T_sign),
            "size": {"x": d, "y": d, "z": 0.02},
            "bottom_scale": 1.0,
            "top_scale": 1.0,
            "color": _color((0.95, 0.95, 0.95, 1.0)),
        }
        text = {
            "pose": _pose(label_T),
            "billboard": True,
            "font_size": 14.0,
            "scale_invariant": True,
            "color": _color((1.0, 1.0, 0.2, 1.0)),
            "text": sign.code,
        }
        entities.append(
            _entity(stamp_ns, sign_map.frame, f"sign/{sign.code}", cylinders=[disc], texts=[text])
        )
    for i, (name, traj) in enumerate((trajectories or {}).items()):
        ok = np.all(np.isfinite(traj.world_t_cam), axis=1)
        points = [
            {"x": float(p[0]), "y": float(p[1]), "z": float(p[2])} for p in traj.world_t_cam[ok]
        ]
        line = {
            "type": 0,  # LINE_STRIP
            "pose": _IDENTITY_POSE,
            "thickness": 3.0,
            "scale_invariant": True,
            "points": points,
            "color": _color(method_color(name, i)),
            "colors": [],
            "indices": [],
        }
        entities.append(_entity(stamp_ns, sign_map.frame, f"trajectory/{name}", lines=[line]))
    return {"deletions": [], "entities": entities}


def image_annotations(frame_obs: FrameObservations, default_diameter_px: float = 24.0) -> dict:
    """foxglove.ImageAnnotations: a circle and the code of every decoded sign of one frame."""
    ts = stamp_dict(frame_obs.stamp_ns)
    circles, texts = [], []
    for s in frame_obs.signs:
        u, v = s.center_px
        diameter = default_diameter_px
        if s.bbox_px is not None:
            diameter = float(max(s.bbox_px[2], s.bbox_px[3]))
        circles.append(
            {
                "timestamp": ts,
                "position": {"x": float(u), "y": float(v)},
                "diameter": float(diameter),
                "thickness": 2.0,
                "fill_color": _color((0.0, 0.0, 0.0, 0.0)),
                "outline_color": _color((0.1, 1.0, 0.1, 1.0)),
            }
        )
        texts.append(
            {
                "timestamp": ts,
                "position": {"x": float(u + 0.5 * diameter), "y": float(v - 0.5 * diameter)},
                "text": s.code,
                "font_size": 18.0,
                "text_color": _color((1.0, 1.0, 0.2, 1.0)),
                "background_color": _color((0.0, 0.0, 0.0, 0.6)),
            }
        )
    return {"circles": circles, "points": [], "texts": texts}


# --------------------------------------------------------------------------- writing


class McapJsonWriter:
    """Writes JSON-encoded Foxglove messages to an MCAP file, atomically.

    The file appears at ``path`` only on ``close()``; ``abort()`` (or an
    exception inside ``with``) removes the partial file.
    """

    def __init__(self, path: str | os.PathLike, chunk_size: int = 256 * 1024):
        from mcap.writer import Writer

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
        self._writer.add_message(channel_id, t, data, t, self._sequence)
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
            raise
        self._stack.close()

    def abort(self) -> None:
        """Drop the partial file."""
        if not self._open:
            return
        self._open = False
        self._file.close()
        self._stack.__exit__(KeyboardInterrupt, KeyboardInterrupt(), None)

    def __enter__(self) -> McapJsonWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class McapFrameWriter:
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

    def __enter__(self) -> McapFrameWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_result_mcap(
    path: str | os.PathLike,
    sign_map: SignMap,
    frames: list[FrameObservations],
    trajectories: dict[str, Trajectory],
    camera: CameraModel | None = None,
    images: Iterable[tuple[int, np.ndarray]] | None = None,
    jpeg_quality: int = 85,
    progress: bool = False,
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
    """
    from tqdm import tqdm

    world = sign_map.frame
    t0 = frames[0].stamp_ns if frames else 0
    tf_name = "smoothed" if "smoothed" in trajectories else next(iter(trajectories), None)
    by_stamp: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, traj in trajectories.items():
        Ts = traj.world_T_cam()
        ok = np.all(np.isfinite(Ts.reshape(len(Ts), -1)), axis=1)
        by_stamp[name] = (np.round(traj.stamps_s[ok] * 1e9).astype(np.int64), Ts[ok])
    image_iter = iter(images) if images is not None else None
    with McapJsonWriter(path) as writer:
        writer.write(SCENE_TOPIC, "SceneUpdate", scene_update(t0, sign_map, trajectories), t0)
        if camera is not None:
            writer.write(CALIBRATION_TOPIC, "CameraCalibration", camera_calibration(t0, camera), t0)
        for obs in tqdm(frames, desc="result.mcap", unit="frame", disable=not progress):
            t = obs.stamp_ns
            if image_iter is not None:
                item = next(image_iter, None)
                if item is not None:
                    msg = compressed_image(item[0], item[1], quality=jpeg_quality)
                    writer.write(IMAGE_TOPIC, "CompressedImage", msg, item[0])
            writer.write(ANNOTATIONS_TOPIC, "ImageAnnotations", image_annotations(obs), t)
            for name, (stamps_ns, poses) in by_stamp.items():
                T = _nearest(stamps_ns, poses, t)
                if T is None:
                    continue
                writer.write(f"/signpose/{name}/pose", "PoseInFrame", pose_in_frame(t, world, T), t)
                if name == tf_name:
                    writer.write(
                        TF_TOPIC, "FrameTransforms", frame_transforms(t, world, CAMERA_FRAME, T), t
                    )


def _nearest(stamps_ns: np.ndarray, poses: np.ndarray, stamp_ns: int, tol_ns: int = 1_000_000):
    """The pose at ``stamp_ns`` (within ``tol_ns``: stamps went through seconds), or None."""
    if len(stamps_ns) == 0:
        return None
    i = int(np.searchsorted(stamps_ns, stamp_ns))
    best = None
    for j in (i - 1, i):
        if 0 <= j < len(stamps_ns):
            dt = abs(int(stamps_ns[j]) - int(stamp_ns))
            if dt <= tol_ns and (best is None or dt < best[0]):
                best = (dt, j)
    return None if best is None else poses[best[1]]


# --------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class McapChannel:
    """One channel of a log.

    Attributes:
        topic: channel topic.
        schema_name: e.g. ``foxglove.CompressedImage``, ``sensor_msgs/msg/Image``.
        message_encoding: ``json``, ``cdr``, ...
        message_count: number of messages, or None when the log has no summary.
    """

    topic: str
    schema_name: str
    message_encoding: str
    message_count: int | None

    @property
    def is_image(self) -> bool:
        return self.schema_name in IMAGE_SCHEMAS

    @property
    def is_camera(self) -> bool:
        return self.schema_name in CAMERA_SCHEMAS

    def describe(self) -> str:
        return f"{self.topic} ({self.schema_name or 'no schema'})"


@dataclass(frozen=True)
class McapMessage:
    """One decoded message: ``decoded`` is a dict (JSON) or a ROS 2 message object."""

    topic: str
    schema_name: str
    log_time_ns: int
    decoded: Any


class McapLog:
    """A streamed MCAP log.

    ``channels`` comes from the summary section, or, for a log without one (e.g.
    truncated), from a scan of the data. ``messages()`` streams in file order
    and, when the data stops early, sets ``problem`` to where and why.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(f"{self.path}: file not found")
        self.problem: str | None = None
        self.channels = self._read_channels()

    # ------------------------------------------------------------------ channels
    def _read_channels(self) -> tuple[McapChannel, ...]:
        from mcap.reader import make_reader

        try:
            with open(self.path, "rb") as f:
                summary = make_reader(f).get_summary()
        except Exception:  # noqa: BLE001 - any failure: fall back to scanning the data
            summary = None
        if summary is not None and summary.channels:
            counts = summary.statistics.channel_message_counts if summary.statistics else {}
            return tuple(
                McapChannel(
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
            McapChannel(
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
        from mcap.stream_reader import StreamReader

        with open(self.path, "rb") as f:
            reader = StreamReader(f, record_size_limit=1 << 30)
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
                size = self.path.stat().st_size
                at = min(f.tell(), size)
                reason = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
                reason = f"{type(exc).__name__}: {reason}" if reason else type(exc).__name__
                self.problem = (
                    f"log stopped after {n_messages} messages, near byte {at} of {size} "
                    f"({reason}); the file is truncated or corrupt"
                )

    def messages(self, topics: Iterable[str]) -> Iterator[McapMessage]:
        """Decoded messages of ``topics`` in file order (log order for signpose's logs)."""
        from mcap_ros2.decoder import DecoderFactory

        wanted = set(topics)
        ros2 = DecoderFactory()
        schemas: dict[int, Any] = {}
        channels: dict[int, Any] = {}
        decoders: dict[int, Any] = {}
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
                    decoder = _decoder_for(ch, sch, ros2, self.path)
                    decoders[ch.id] = decoder
                try:
                    decoded = decoder(record.data)
                except Exception as exc:  # noqa: BLE001 - one bad message is a value
                    log.warning("%s: %s: cannot decode a message (%s)", self.path, ch.topic, exc)
                    continue
                yield McapMessage(ch.topic, name, int(record.log_time), decoded)


def _decoder_for(channel, schema_record, ros2_factory, path: Path):
    if channel.message_encoding == JSON_ENCODING:
        return lambda data: json.loads(data)
    decoder = ros2_factory.decoder_for(channel.message_encoding, schema_record)
    if decoder is None:
        raise InputError(
            f"{path}: topic {channel.topic}: cannot decode message encoding "
            f"'{channel.message_encoding}' (supported: json, ROS 2 cdr)"
        )
    return decoder


def _get(msg: Any, key: str, default=None):
    if isinstance(msg, dict):
        return msg.get(key, default)
    return getattr(msg, key, default)


def _as_bytes(data: Any) -> bytes:
    if isinstance(data, str):
        return base64.b64decode(data)
    if isinstance(data, bytes | bytearray | memoryview):
        return bytes(data)
    return bytes(bytearray(data))  # ROS 2 uint8[] may decode as a list


def message_stamp_ns(schema_name: str, msg: Any) -> int | None:
    """The header / timestamp of an image or camera message [ns], or None."""
    if schema_name.startswith("foxglove."):
        ts = _get(msg, "timestamp")
        if ts is None:
            return None
        return int(_get(ts, "sec", 0)) * 1_000_000_000 + int(_get(ts, "nsec", 0))
    header = _get(msg, "header")
    stamp = _get(header, "stamp") if header is not None else None
    if stamp is None:
        return None
    return int(_get(stamp, "sec", 0)) * 1_000_000_000 + int(_get(stamp, "nanosec", 0))


_RAW_CHANNELS = {"mono8": 1, "8uc1": 1, "bgr8": 3, "rgb8": 3, "8uc3": 3, "bgra8": 4, "rgba8": 4}


def image_from_message(schema_name: str, msg: Any) -> tuple[np.ndarray | None, str]:
    """Decode an image message to a gray (H, W) or BGR (H, W, 3) uint8 array.

    Returns:
        (image, "") or (None, reason) when the message cannot be decoded.
    """
    if schema_name in ("foxglove.CompressedImage", "sensor_msgs/msg/CompressedImage"):
        try:
            buf = np.frombuffer(_as_bytes(_get(msg, "data", b"")), dtype=np.uint8)
        except (ValueError, TypeError) as exc:
            return None, f"bad image data ({exc})"
        if buf.size == 0:
            return None, "empty image data"
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        if img is None:
            return None, f"cannot decode {_get(msg, 'format', '?')} image"
        if img.ndim == 3 and img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        if img.dtype != np.uint8:
            img = (img / 257).astype(np.uint8)
        return img, ""
    if schema_name in ("foxglove.RawImage", "sensor_msgs/msg/Image"):
        w, h = int(_get(msg, "width", 0)), int(_get(msg, "height", 0))
        enc = str(_get(msg, "encoding", "")).lower()
        step = int(_get(msg, "step", 0))
        data = _as_bytes(_get(msg, "data", b""))
        if enc in ("mono16", "16uc1"):
            ch, dtype = 1, np.dtype(">u2" if int(_get(msg, "is_bigendian", 0)) else "<u2")
        elif enc in _RAW_CHANNELS:
            ch, dtype = _RAW_CHANNELS[enc], np.dtype(np.uint8)
        else:
            return None, f"unsupported raw image encoding '{enc}'"
        row = w * ch * dtype.itemsize
        step = step or row
        if w <= 0 or h <= 0 or step < row or len(data) < step * (h - 1) + row:
            return None, f"raw image data too short for {w}x{h} {enc}"
        rows = np.frombuffer(data[: step * h].ljust(step * h, b"\0"), dtype=np.uint8)
        pixels = np.ascontiguousarray(rows.reshape(h, step)[:, :row]).view(dtype)
        if ch == 1:
            img = pixels.reshape(h, w)
            if dtype.itemsize == 2:
                img = (img.astype(np.float32) / 257).astype(np.uint8)
            return img, ""
        img = pixels.reshape(h, w, ch)
        conversion = {
            "rgb8": cv2.COLOR_RGB2BGR,
            "rgba8": cv2.COLOR_RGBA2BGR,
            "bgra8": cv2.COLOR_BGRA2BGR,
        }.get(enc)
        if conversion is not None:
            img = cv2.cvtColor(img, conversion)
        return img, ""
    return None, f"not an image schema: {schema_name}"


def camera_from_message(schema_name: str, msg: Any, source: str) -> CameraModel:
    """A CameraModel from foxglove.CameraCalibration or sensor_msgs/msg/CameraInfo."""
    if schema_name == "foxglove.CameraCalibration":
        K, D, model = _get(msg, "K"), _get(msg, "D"), _get(msg, "distortion_model", "")
    elif schema_name == "sensor_msgs/msg/CameraInfo":
        K, D, model = _get(msg, "k"), _get(msg, "d"), _get(msg, "distortion_model", "")
    else:
        raise InputError(f"{source}: {schema_name} is not a camera message")
    try:
        K = np.array([float(v) for v in K], dtype=float).reshape(3, 3)
        D = np.array([float(v) for v in (D or [])], dtype=float)
        w, h = int(_get(msg, "width")), int(_get(msg, "height"))
    except (TypeError, ValueError):
        raise InputError(f"{source}: camera calibration message is malformed") from None
    name = str(model).strip().lower()
    if name in ("", "plumb_bob", "rational_polynomial", "radtan"):
        cam_model = PLUMB_BOB
    elif name in ("equidistant", "kannala_brandt", "fisheye"):
        cam_model = EQUIDISTANT
    else:
        raise InputError(f"{source}: unsupported distortion model '{model}' in the log")
    if w <= 0 or h <= 0 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(f"{source}: camera calibration in the log has no size or focal length")
    if D.size == 0:
        D = np.zeros(5)
    return CameraModel(w, h, K, D, cam_model, "camera")


def read_json_messages(path: str | os.PathLike, topic: str) -> list[dict]:
    """All JSON messages of ``topic`` (for tests and tools)."""
    return [m.decoded for m in McapLog(path).messages([topic])]
