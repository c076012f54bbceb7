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
from typing import Any

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
