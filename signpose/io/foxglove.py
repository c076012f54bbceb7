"""Foxglove messages: signpose's jsonschemas and the builders of each message.

Messages are plain dicts in Foxglove's JSON encoding, checked against the
jsonschema definitions shipped in ``signpose/io/schemas/<Name>.json``:
timestamps are ``{"sec", "nsec"}``, bytes are base64 strings, enums are
integers. Poses are ``world_T_cam`` in the map's world frame (z up), the
camera frame being OpenCV's (x right, y down, z forward). The MCAP container
around them is ``signpose.io.mcap_write``.
"""

from __future__ import annotations

import base64
import json
from collections.abc import Iterable
from functools import cache
from importlib import resources

import cv2
import numpy as np

from signpose.estimator.camera import EQUIDISTANT, CameraModel
from signpose.estimator.trajectory import Trajectory, quat_xyzw_from_rotation
from signpose.frontend.observations import FrameObservations
from signpose.maps.loader import SignMap

SCHEMA_NAMES = (
    "CameraCalibration",
    "CompressedImage",
    "FrameTransforms",
    "ImageAnnotations",
    "LocationFix",
    "PoseInFrame",
    "RawImage",
    "SceneUpdate",
)

# The camera frame id of signpose's own logs.
CAMERA_FRAME = "camera"

# RGBA in [0, 1] per method; others cycle through the extra colours.
_METHOD_COLORS = {
    "groundtruth": (0.2, 0.2, 0.2, 1.0),
    "baseline": (0.85, 0.33, 0.1, 1.0),
    "smoothed": (0.0, 0.45, 0.74, 1.0),
}
_EXTRA_COLORS = ((0.47, 0.67, 0.19, 1.0), (0.49, 0.18, 0.56, 1.0), (0.93, 0.69, 0.13, 1.0))


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


def location_fix(
    stamp_ns: int,
    frame_id: str,
    lat_deg: float,
    lon_deg: float,
    height_m: float,
    sigma_enu_m=None,
    rgba: Iterable[float] | None = None,
) -> dict:
    """foxglove.LocationFix of a WGS84 position (ellipsoidal height [m]).

    Args:
        sigma_enu_m: (3,) standard deviation along east, north, up [m], or
            None / non-finite: covariance unknown (type 0).
        rgba: the fix's colour in Foxglove's map panel, or None.
    """
    cov, kind = [0.0] * 9, 0
    if sigma_enu_m is not None:
        s = np.asarray(sigma_enu_m, dtype=float).reshape(3)
        if np.all(np.isfinite(s)):
            cov = np.diag(s**2).ravel().tolist()
            kind = 2  # DIAGONAL_KNOWN
    msg = {
        "timestamp": stamp_dict(stamp_ns),
        "frame_id": frame_id,
        "latitude": float(lat_deg),
        "longitude": float(lon_deg),
        "altitude": float(height_m),
        "position_covariance": cov,
        "position_covariance_type": kind,
    }
    if rgba is not None:
        msg["color"] = _color(rgba)
    return msg
