"""MCAP logs: the one entry point for reading and writing them.

The format is split by direction so each part can be read on its own:

    signpose.io.foxglove   Foxglove message builders and signpose's jsonschemas
    signpose.io.messages   image/camera messages (Foxglove JSON or ROS 2) -> arrays, cameras
    signpose.io.mcap_read  McapLog: channels and decoded messages, streamed
    signpose.io.mcap_write McapJsonWriter, the simulator's McapFrameWriter, write_result_mcap

Callers import this module (``from signpose.io import mcap as mcap_io``); the
names below are its public surface.
"""

from __future__ import annotations

from signpose.io.foxglove import (
    CAMERA_FRAME,
    SCHEMA_NAMES,
    camera_calibration,
    compressed_image,
    frame_transforms,
    image_annotations,
    method_color,
    pose_in_frame,
    scene_update,
    schema,
    schema_text,
    stamp_dict,
)
from signpose.io.mcap_read import (
    JSON_ENCODING,
    McapChannel,
    McapLog,
    McapMessage,
    read_json_messages,
)
from signpose.io.mcap_write import (
    ANNOTATIONS_TOPIC,
    CALIBRATION_TOPIC,
    GROUNDTRUTH_TOPIC,
    IMAGE_TOPIC,
    SCENE_TOPIC,
    TF_TOPIC,
    McapFrameWriter,
    McapJsonWriter,
    write_result_mcap,
)
from signpose.io.messages import (
    CAMERA_SCHEMAS,
    IMAGE_SCHEMAS,
    camera_from_message,
    image_from_message,
    message_stamp_ns,
)

__all__ = [
    "ANNOTATIONS_TOPIC",
    "CALIBRATION_TOPIC",
    "CAMERA_FRAME",
    "CAMERA_SCHEMAS",
    "GROUNDTRUTH_TOPIC",
    "IMAGE_SCHEMAS",
    "IMAGE_TOPIC",
    "JSON_ENCODING",
    "SCENE_TOPIC",
    "SCHEMA_NAMES",
    "TF_TOPIC",
    "McapChannel",
    "McapFrameWriter",
    "McapJsonWriter",
    "McapLog",
    "McapMessage",
    "camera_calibration",
    "camera_from_message",
    "compressed_image",
    "frame_transforms",
    "image_annotations",
    "image_from_message",
    "message_stamp_ns",
    "method_color",
    "pose_in_frame",
    "read_json_messages",
    "scene_update",
    "schema",
    "schema_text",
    "stamp_dict",
    "write_result_mcap",
]
