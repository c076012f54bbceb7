"""Camera calibration files: the one module that reads and writes them.

Formats read (detected from content):
    * ROS ``camera_info`` YAML (``image_width``, ``camera_matrix``,
      ``distortion_model``, ``distortion_coefficients``), as written by
      camera_calibration / camera_info_manager;
    * OpenCV FileStorage YAML (``%YAML:1.0`` with ``camera_matrix`` /
      ``distortion_coefficients`` opencv-matrix nodes, ``image_width``,
      ``image_height``; optional ``distortion_model`` or ``fisheye``);
    * Kalibr camchain YAML (``cam0`` with ``intrinsics`` [fu, fv, pu, pv],
      ``distortion_model`` radtan | equidistant, ``distortion_coeffs``,
      ``resolution``).
Format written: ROS ``camera_info`` YAML. The camera model itself (axes, pixel
convention, projection) is ``signpose.estimator.camera``.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml

from signpose.core.errors import InputError
from signpose.core.fileio import atomic_write
from signpose.estimator.camera import EQUIDISTANT, PLUMB_BOB, CameraModel

_MODEL_ALIASES = {
    "plumb_bob": PLUMB_BOB,
    "rational_polynomial": PLUMB_BOB,
    "radtan": PLUMB_BOB,
    "pinhole-radtan": PLUMB_BOB,
    "equidistant": EQUIDISTANT,
    "fisheye": EQUIDISTANT,
    "kannala_brandt": EQUIDISTANT,
    "pinhole-equi": EQUIDISTANT,
}


def _fail(path: Path, what: str) -> InputError:
    return InputError(f"{path}: {what}")


def _matrix(node, path: Path, field: str, rows: int | None = None, cols: int | None = None):
    """A ROS/OpenCV matrix node ({rows, cols, data}) or a flat list, as an array."""
    data = node.get("data") if isinstance(node, dict) else node
    if not isinstance(data, list):
        raise _fail(path, f"field '{field}' must be a matrix with 'data'")
    try:
        arr = np.array([float(x) for x in data])
    except (TypeError, ValueError):
        raise _fail(path, f"field '{field}' must hold numbers") from None
    if not np.all(np.isfinite(arr)):
        raise _fail(path, f"field '{field}' has a non-finite number")
    if rows is not None and cols is not None:
        if arr.size != rows * cols:
            raise _fail(path, f"field '{field}' must have {rows * cols} numbers, has {arr.size}")
        arr = arr.reshape(rows, cols)
    return arr


def _model(name, path: Path) -> str:
    key = str(name).strip().lower()
    if key not in _MODEL_ALIASES:
        raise _fail(
            path, f"unsupported distortion model {name!r}: use plumb_bob/radtan or equidistant"
        )
    return _MODEL_ALIASES[key]


def _checked(cam: CameraModel, path: Path) -> CameraModel:
    if cam.width <= 0 or cam.height <= 0:
        raise _fail(path, "image size must be positive (image_width, image_height)")
    if cam.fx <= 0 or cam.fy <= 0:
        raise _fail(path, "focal lengths must be positive (camera_matrix)")
    if cam.model == EQUIDISTANT and cam.dist.size < 4:
        raise _fail(path, "equidistant distortion needs 4 coefficients k1..k4")
    if cam.model == PLUMB_BOB and cam.dist.size not in (0, 4, 5, 8, 12, 14):
        raise _fail(path, f"plumb_bob distortion needs 4, 5 or 8 coefficients, has {cam.dist.size}")
    return cam


def _from_ros(d: dict, path: Path) -> CameraModel:
    for field in ("image_width", "image_height", "camera_matrix"):
        if field not in d:
            raise _fail(path, f"missing field '{field}' (ROS camera_info YAML)")
    K = _matrix(d["camera_matrix"], path, "camera_matrix", 3, 3)
    dist = _matrix(d.get("distortion_coefficients", {"data": []}), path, "distortion_coefficients")
    model = _model(d.get("distortion_model", PLUMB_BOB), path)
    try:
        w, h = int(d["image_width"]), int(d["image_height"])
    except (TypeError, ValueError):
        raise _fail(path, "image_width and image_height must be integers") from None
    return CameraModel(w, h, K, dist, model, str(d.get("camera_name", "camera")))


def _from_kalibr(d: dict, path: Path) -> CameraModel:
    cam = d.get("cam0")
    if not isinstance(cam, dict):
        raise _fail(path, "Kalibr camchain has no 'cam0'")
    for field in ("intrinsics", "resolution"):
        if field not in cam:
            raise _fail(path, f"cam0: missing field '{field}'")
    intr = _matrix(cam["intrinsics"], path, "cam0.intrinsics")
    if intr.size != 4:
        raise _fail(path, "cam0.intrinsics must be [fu, fv, pu, pv]")
    res = _matrix(cam["resolution"], path, "cam0.resolution")
    if res.size != 2:
        raise _fail(path, "cam0.resolution must be [width, height]")
    K = np.array([[intr[0], 0, intr[2]], [0, intr[1], intr[3]], [0, 0, 1.0]])
    model = _model(cam.get("distortion_model", "radtan"), path)
    dist = _matrix(cam.get("distortion_coeffs", []), path, "cam0.distortion_coeffs")
    if model == PLUMB_BOB and dist.size == 4:
        dist = np.append(dist, 0.0)
    return CameraModel(int(res[0]), int(res[1]), K, dist, model, "cam0")


def _from_opencv(path: Path) -> CameraModel:
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        if not fs.isOpened():
            raise _fail(path, "not a readable OpenCV FileStorage file")
        K = fs.getNode("camera_matrix").mat()
        if K is None:
            K = fs.getNode("K").mat()
        if K is None or K.shape != (3, 3):
            raise _fail(path, "missing 3x3 'camera_matrix' (OpenCV FileStorage)")
        D = fs.getNode("distortion_coefficients").mat()
        if D is None:
            D = fs.getNode("D").mat()
        dist = np.zeros(5) if D is None else D.reshape(-1).astype(float)
        w_node, h_node = fs.getNode("image_width"), fs.getNode("image_height")
        if w_node.empty() or h_node.empty():
            raise _fail(path, "missing 'image_width' / 'image_height' (OpenCV FileStorage)")
        w, h = int(w_node.real()), int(h_node.real())
        model_node = fs.getNode("distortion_model")
        fisheye_node = fs.getNode("fisheye")
        if not model_node.empty():
            model = _model(model_node.string(), path)
        elif not fisheye_node.empty() and int(fisheye_node.real()):
            model = EQUIDISTANT
        else:
            model = PLUMB_BOB
    finally:
        fs.release()
    if not np.all(np.isfinite(K)) or not np.all(np.isfinite(dist)):
        raise _fail(path, "camera_matrix or distortion has a non-finite number")
    return CameraModel(w, h, K.astype(float), dist, model, path.stem)


def load_camera(path: str | Path) -> CameraModel:
    """Read a camera file in any supported format; InputError names the file on failure."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise _fail(p, "camera file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise _fail(p, f"cannot read camera file ({exc})") from None
    if text.lstrip().startswith("%YAML"):
        try:
            cam = _from_opencv(p)
        except cv2.error:
            raise _fail(p, "not a valid OpenCV FileStorage YAML") from None
        return _checked(cam, p)
    try:
        d = yaml.safe_load(text)
    except yaml.YAMLError:
        raise _fail(p, "not valid YAML; expected ROS camera_info, OpenCV or Kalibr YAML") from None
    if not isinstance(d, dict):
        raise _fail(p, "not a camera file; expected ROS camera_info, OpenCV or Kalibr YAML")
    if "cam0" in d:
        return _checked(_from_kalibr(d, p), p)
    if "camera_matrix" in d:
        return _checked(_from_ros(d, p), p)
    raise _fail(p, "unknown camera format; expected ROS camera_info, OpenCV or Kalibr YAML")


def camera_info_dict(camera: CameraModel) -> dict:
    """The ROS camera_info YAML content for ``camera``."""
    K = [float(x) for x in camera.K.reshape(-1)]
    P = [K[0], K[1], K[2], 0.0, K[3], K[4], K[5], 0.0, K[6], K[7], K[8], 0.0]
    dist = [float(x) for x in camera.dist.reshape(-1)]
    return {
        "image_width": int(camera.width),
        "image_height": int(camera.height),
        "camera_name": camera.name,
        "camera_matrix": {"rows": 3, "cols": 3, "data": K},
        "distortion_model": camera.model,
        "distortion_coefficients": {"rows": 1, "cols": len(dist), "data": dist},
        "rectification_matrix": {
            "rows": 3,
            "cols": 3,
            "data": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        },
        "projection_matrix": {"rows": 3, "cols": 4, "data": P},
    }


def write_camera_info(path: str | Path, camera: CameraModel) -> None:
    """Write ``camera`` as ROS camera_info YAML (atomically)."""
    with atomic_write(path) as f:
        yaml.safe_dump(camera_info_dict(camera), f, sort_keys=False, default_flow_style=None)
