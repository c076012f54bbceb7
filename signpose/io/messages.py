"""Image and camera messages, Foxglove JSON or ROS 2, decoded into images and cameras.

Independent of the container: MCAP logs (``signpose.io.mcap_read``) and
rosbag2 bags hand their decoded messages here. A decoded message is a dict
(JSON) or a ROS 2 message object (attributes); both are read with ``_get``.
Schemas read: ``foxglove.CompressedImage`` / ``foxglove.RawImage`` and
``sensor_msgs/msg/CompressedImage`` / ``sensor_msgs/msg/Image`` for images,
``foxglove.CameraCalibration`` and ``sensor_msgs/msg/CameraInfo`` for the camera.
"""

from __future__ import annotations

import base64
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from signpose.core.errors import InputError
from signpose.estimator.camera import EQUIDISTANT, PLUMB_BOB, CameraModel

IMAGE_SCHEMAS = (
    "foxglove.CompressedImage",
    "foxglove.RawImage",
    "sensor_msgs/msg/CompressedImage",
    "sensor_msgs/msg/Image",
)
CAMERA_SCHEMAS = ("foxglove.CameraCalibration", "sensor_msgs/msg/CameraInfo")


@dataclass(frozen=True)
class LogChannel:
    """One channel (topic) of a log: an MCAP channel or a rosbag2 topic.

    Attributes:
        topic: channel topic.
        schema_name: e.g. ``foxglove.CompressedImage``, ``sensor_msgs/msg/Image``.
        message_encoding: ``json``, ``cdr``, ...
        message_count: number of messages, or None when the log does not say.
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
class LogMessage:
    """One message of a log, decoded.

    Attributes:
        topic: its topic.
        schema_name: its type, as ``LogChannel.schema_name``.
        log_time_ns: the time the recorder received it [ns].
        decoded: a dict (JSON) or a ROS 2 message object; None when ``error`` is set.
        error: why the message could not be decoded ("" when it was).
    """

    topic: str
    schema_name: str
    log_time_ns: int
    decoded: Any
    error: str = ""


class MessageLog(Protocol):
    """A recorded log of messages: an MCAP file, a rosbag2 bag or one of its files.

    ``messages()`` streams in file order and never raises for damaged data: it
    stops, and ``problem`` then says where and why (None when it read to the end).
    """

    path: Path
    channels: tuple[LogChannel, ...]
    problem: str | None

    def messages(self, topics: Iterable[str]) -> Iterator[LogMessage]: ...


def _get(msg: Any, key: str, default=None):
    if isinstance(msg, dict):
        return msg.get(key, default)
    return getattr(msg, key, default)


def _as_bytes(data: Any) -> bytes:
    if isinstance(data, str):
        return base64.b64decode(data)
    if isinstance(data, bytes | bytearray | memoryview):
        return bytes(data)
    if isinstance(data, np.ndarray):  # rosbags decodes uint8[] as an array
        return data.astype(np.uint8, copy=False).tobytes()
    return bytes(bytearray(data))  # ROS 2 uint8[] may decode as a list


def _whole_number(value: Any) -> int:
    """An integer field of a message; ValueError when it is not a finite whole number."""
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise ValueError(f"{value!r} is not a number")
    if not math.isfinite(value) or value != int(value):
        raise ValueError(f"{value!r} is not a whole number")
    return int(value)


def message_stamp_ns(schema_name: str, msg: Any) -> int | None:
    """The header / timestamp of an image or camera message [ns], or None when it has none.

    Raises:
        ValueError: the stamp is there but is not made of whole numbers.
    """
    if schema_name.startswith("foxglove."):
        stamp, nsec_key = _get(msg, "timestamp"), "nsec"
    else:
        header = _get(msg, "header")
        stamp, nsec_key = (_get(header, "stamp") if header is not None else None), "nanosec"
    if stamp is None:
        return None
    return _whole_number(_get(stamp, "sec", 0)) * 1_000_000_000 + _whole_number(
        _get(stamp, nsec_key, 0)
    )


def message_frame_id(msg: Any) -> str | None:
    """The frame id of an image or camera message (Foxglove or ROS 2 header), or None."""
    frame_id = _get(msg, "frame_id")
    if frame_id is None:
        header = _get(msg, "header")
        frame_id = _get(header, "frame_id") if header is not None else None
    return frame_id if isinstance(frame_id, str) and frame_id else None


_JPEG_START = b"\xff\xd8"
_JPEG_END = b"\xff\xd9"


def is_cut_jpeg(buf: np.ndarray) -> bool:
    """A JPEG whose end-of-image marker is missing (libjpeg would decode it with gray rows)."""
    data = buf.tobytes()
    return data[:2] == _JPEG_START and not data.rstrip(b"\x00").endswith(_JPEG_END)


# Raw encodings (ROS 2 sensor_msgs/Image, foxglove.RawImage): name -> (bytes per pixel
# and channel layout in the buffer, conversion to BGR or None). Bayer patterns by their
# standard names (OpenCV >= 4.5 spells them so; cv_bridge maps bayer_rggb8 the same way).
_RAW_ENCODINGS: dict[str, tuple[int, int | None]] = {
    "mono8": (1, None),
    "8uc1": (1, None),
    "bgr8": (3, None),
    "8uc3": (3, None),
    "rgb8": (3, cv2.COLOR_RGB2BGR),
    "bgra8": (4, cv2.COLOR_BGRA2BGR),
    "8uc4": (4, cv2.COLOR_BGRA2BGR),
    "rgba8": (4, cv2.COLOR_RGBA2BGR),
    "bayer_rggb8": (1, cv2.COLOR_BayerRGGB2BGR),
    "bayer_bggr8": (1, cv2.COLOR_BayerBGGR2BGR),
    "bayer_gbrg8": (1, cv2.COLOR_BayerGBRG2BGR),
    "bayer_grbg8": (1, cv2.COLOR_BayerGRBG2BGR),
    "yuv422": (2, cv2.COLOR_YUV2BGR_UYVY),
    "uyvy": (2, cv2.COLOR_YUV2BGR_UYVY),
    "yuv422_yuy2": (2, cv2.COLOR_YUV2BGR_YUY2),
    "yuyv": (2, cv2.COLOR_YUV2BGR_YUY2),
}
_MONO16 = ("mono16", "16uc1")
MAX_RAW_SIDE_PX = 100_000


def image_from_message(schema_name: str, msg: Any) -> tuple[np.ndarray | None, str]:
    """Decode an image message to a gray (H, W) or BGR (H, W, 3) uint8 array.

    Returns:
        (image, "") or (None, reason) when the message cannot be decoded; never raises
        for a message's content.
    """
    if schema_name in ("foxglove.CompressedImage", "sensor_msgs/msg/CompressedImage"):
        return _compressed_image(msg)
    if schema_name in ("foxglove.RawImage", "sensor_msgs/msg/Image"):
        try:
            return _raw_image(msg)
        except (ValueError, TypeError, OverflowError) as exc:
            return None, f"malformed raw image ({exc})"
    return None, f"not an image schema: {schema_name}"


def _compressed_image(msg: Any) -> tuple[np.ndarray | None, str]:
    try:
        buf = np.frombuffer(_as_bytes(_get(msg, "data", b"")), dtype=np.uint8)
    except (ValueError, TypeError) as exc:
        return None, f"bad image data ({exc})"
    if buf.size == 0:
        return None, "empty image data"
    if "compresseddepth" in str(_get(msg, "format", "")).lower():
        return None, "a compressed depth image, not a camera image"
    if is_cut_jpeg(buf):
        return None, "JPEG data ends without its end-of-image marker (cut short)"
    img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    if img is None:
        return None, f"cannot decode {_get(msg, 'format', '?')} image"
    if img.ndim == 3 and img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    if img.dtype != np.uint8:
        img = (img / 257).astype(np.uint8)
    return img, ""


def _raw_image(msg: Any) -> tuple[np.ndarray | None, str]:
    w = _whole_number(_get(msg, "width", 0))
    h = _whole_number(_get(msg, "height", 0))
    step = _whole_number(_get(msg, "step", 0))
    enc = str(_get(msg, "encoding", "")).lower()
    data = _as_bytes(_get(msg, "data", b""))
    if enc in _MONO16:
        big = bool(_whole_number(_get(msg, "is_bigendian", 0)))
        dtype, width_bytes, conversion = np.dtype(">u2" if big else "<u2"), 2, None
    elif enc in _RAW_ENCODINGS:
        width_bytes, conversion = _RAW_ENCODINGS[enc]
        dtype = np.dtype(np.uint8)
    else:
        return None, f"unsupported raw image encoding '{enc}'"
    row = w * width_bytes
    step = step or row
    if not (0 < w <= MAX_RAW_SIDE_PX and 0 < h <= MAX_RAW_SIDE_PX):
        return None, f"raw image size {w}x{h} is not usable"
    if step < row or len(data) < step * (h - 1) + row:
        return None, f"raw image data too short for {w}x{h} {enc}"
    rows = np.frombuffer(data[: step * h].ljust(step * h, b"\0"), dtype=np.uint8)
    pixels = np.ascontiguousarray(rows.reshape(h, step)[:, :row])
    if enc in _MONO16:
        return (pixels.view(dtype).reshape(h, w).astype(np.float32) / 257).astype(np.uint8), ""
    img = pixels.reshape(h, w, width_bytes) if width_bytes > 1 else pixels.reshape(h, w)
    if conversion is not None:
        img = cv2.cvtColor(img, conversion)
    return img, ""


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
        D = np.array([float(v) for v in ([] if D is None else D)], dtype=float)
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
