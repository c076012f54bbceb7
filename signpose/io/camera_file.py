"""Camera calibration files: the one module that reads and writes them.

Formats read (detected from content, never from the file name):
    * ROS ``camera_info`` YAML (``image_width``, ``camera_matrix``,
      ``distortion_model``, ``distortion_coefficients``), as written by
      camera_calibration (ost.yaml) and camera_info_manager;
    * OpenCV FileStorage, YAML (``%YAML:1.0``, ``!!opencv-matrix``) or XML
      (``<opencv_storage>``), read with ``cv2.FileStorage``: the calibration
      sample's keys old (``Camera_Matrix``, ``Distortion_Coefficients``,
      ``image_Width``, ``image_Height``) and new (``camera_matrix``, ...), its
      ``fisheye_model`` flag, or a ``distortion_model`` string;
    * Kalibr camchain YAML (``cam0`` with ``camera_model: pinhole``,
      ``intrinsics`` [fu, fv, pu, pv], ``distortion_model`` radtan |
      equidistant | none, ``distortion_coeffs``, ``resolution``), with or
      without a ``%YAML`` header.
A file is loaded with the lens model it states or refused naming that model:
signpose undistorts with OpenCV's pinhole model (plumb_bob / radtan /
rational_polynomial: 4, 5, 8, 12 or 14 coefficients) and its fisheye model
(equidistant / kannala_brandt: 4 coefficients). Omni, double sphere, EUCM, FOV
... are refused. Formats written: ROS ``camera_info`` YAML, OpenCV FileStorage
YAML, Kalibr camchain YAML. The camera model itself (axes, pixel convention,
projection) is ``signpose.estimator.camera``.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from signpose.core.errors import InputError
from signpose.core.fileio import atomic_path, atomic_write
from signpose.core.nesting import check_nesting, safe_load_unique
from signpose.estimator.camera import EQUIDISTANT, PLUMB_BOB, CameraModel

ROS_CAMERA_INFO = "camera_info"
OPENCV = "opencv"
OPENCV_XML = "opencv_xml"
KALIBR = "kalibr"
SOURCE_FORMATS = (ROS_CAMERA_INFO, OPENCV, OPENCV_XML, KALIBR)

# A calibration file is a few kB; anything far larger is not one (and is not parsed).
MAX_CAMERA_FILE_BYTES = 1 << 20
MAX_IMAGE_SIDE_PX = 100_000
MAX_FOCAL_PX = 1e7  # a 100,000 px wide sensor behind a 0.6 degree lens
MAX_DISTORTION_COEFF = 1e6
OPENCV_COEFF_COUNTS = (4, 5, 8, 12, 14)  # what cv2.undistortPoints takes
SUPPORTED_MODELS = (
    "plumb_bob / radtan / rational_polynomial (OpenCV pinhole, 4, 5, 8, 12 or 14 "
    "coefficients) and equidistant / fisheye / kannala_brandt (4 coefficients)"
)

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
_IDENTITY_3 = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
_YAML_DIRECTIVE = re.compile(r"\A\s*%YAML[: ][^\n]*\n(\s*---[^\n]*\n)?")


@dataclass(frozen=True)
class CameraFile:
    """A camera read from a file, with the format it was read in.

    Attributes:
        camera: the camera.
        source_format: one of ``SOURCE_FORMATS``.
    """

    camera: CameraModel
    source_format: str


def _fail(path: Path, what: str) -> InputError:
    return InputError(f"{path}: {what}")


# --------------------------------------------------------------------------- checks


def _numbers(values, path: Path, field: str) -> np.ndarray:
    try:
        arr = np.array([float(x) for x in values], dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise _fail(path, f"field '{field}' must hold numbers") from None
    if not np.all(np.isfinite(arr)):
        raise _fail(path, f"field '{field}' has a non-finite number")
    return arr


def _matrix(node, path: Path, field: str, rows: int | None = None, cols: int | None = None):
    """A ROS matrix node ({rows, cols, data}) or a flat list, as an array."""
    data = node.get("data") if isinstance(node, dict) else node
    if not isinstance(data, list):
        raise _fail(path, f"field '{field}' must be a matrix with 'data'")
    arr = _numbers(data, path, field)
    if rows is not None and cols is not None:
        if arr.size != rows * cols:
            raise _fail(path, f"field '{field}' must have {rows * cols} numbers, has {arr.size}")
        arr = arr.reshape(rows, cols)
    return arr


def _model(name, path: Path, where: str = "distortion model") -> str:
    key = str(name).strip().lower()
    if key not in _MODEL_ALIASES:
        raise _fail(
            path, f"{where} {name!r} is not supported; signpose supports {SUPPORTED_MODELS}"
        )
    return _MODEL_ALIASES[key]


def _size(value, path: Path, field: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int | float) or value != value:
        raise _fail(path, f"'{field}' must be a whole number of pixels")
    if not math.isfinite(value) or value != int(value) or not 1 <= value <= MAX_IMAGE_SIDE_PX:
        raise _fail(path, f"'{field}' must be a whole number in 1..{MAX_IMAGE_SIDE_PX}")
    return int(value)


def _checked(cam: CameraModel, path: Path) -> CameraModel:
    """The camera when every number is usable; InputError naming the field otherwise."""
    for field, value in (("width", cam.width), ("height", cam.height)):
        _size(value, path, f"image {field}")
    K = cam.K
    if not (0 < cam.fx <= MAX_FOCAL_PX and 0 < cam.fy <= MAX_FOCAL_PX):
        raise _fail(path, f"focal lengths must be in (0, {MAX_FOCAL_PX:g}] px (camera_matrix)")
    if K[1, 0] != 0 or list(K[2]) != [0.0, 0.0, 1.0]:
        raise _fail(path, "camera_matrix must be [fx s cx; 0 fy cy; 0 0 1]")
    if not (-cam.width <= cam.cx <= 2 * cam.width and -cam.height <= cam.cy <= 2 * cam.height):
        raise _fail(path, "principal point (cx, cy) lies far outside the image")
    if np.any(np.abs(cam.dist) > MAX_DISTORTION_COEFF):
        raise _fail(path, f"a distortion coefficient is beyond +-{MAX_DISTORTION_COEFF:g}")
    n = cam.dist.size
    if cam.model == EQUIDISTANT and n != 4:
        raise _fail(path, f"equidistant (fisheye) distortion takes 4 coefficients k1..k4, has {n}")
    if cam.model == PLUMB_BOB and n not in (0, *OPENCV_COEFF_COUNTS):
        raise _fail(
            path,
            f"pinhole distortion with {n} coefficients is not supported: OpenCV's model "
            "takes 4, 5 (plumb_bob), 8 (rational_polynomial), 12 or 14",
        )
    if n == 0:
        cam = CameraModel(cam.width, cam.height, K, np.zeros(5), cam.model, cam.name)
    return cam


# --------------------------------------------------------------------------- ROS camera_info


def _from_ros(d: dict, path: Path) -> CameraModel:
    for field in ("image_width", "image_height", "camera_matrix"):
        if field not in d:
            raise _fail(path, f"missing field '{field}' (ROS camera_info YAML)")
    K = _matrix(d["camera_matrix"], path, "camera_matrix", 3, 3)
    dist = _matrix(d.get("distortion_coefficients", {"data": []}), path, "distortion_coefficients")
    model = _model(d.get("distortion_model", PLUMB_BOB), path)
    w = _size(d["image_width"], path, "image_width")
    h = _size(d["image_height"], path, "image_height")
    return CameraModel(w, h, K, dist, model, str(d.get("camera_name", "camera")))


# --------------------------------------------------------------------------- Kalibr


def _kalibr_camera(cam, key: str, path: Path) -> CameraModel:
    if not isinstance(cam, dict):
        raise _fail(path, f"Kalibr camchain: '{key}' is not a mapping")
    projection = str(cam.get("camera_model", "pinhole")).strip().lower()
    if projection != "pinhole":
        raise _fail(
            path,
            f"{key}: camera_model '{projection}' is not supported; signpose supports pinhole "
            f"cameras with {SUPPORTED_MODELS}",
        )
    for field in ("intrinsics", "resolution"):
        if field not in cam:
            raise _fail(path, f"{key}: missing field '{field}' (Kalibr camchain)")
    intr = _matrix(cam["intrinsics"], path, f"{key}.intrinsics")
    if intr.size != 4:
        raise _fail(path, f"{key}.intrinsics must be [fu, fv, pu, pv], has {intr.size} numbers")
    res = cam["resolution"]
    if not isinstance(res, list) or len(res) != 2:
        raise _fail(path, f"{key}.resolution must be [width, height]")
    K = np.array([[intr[0], 0, intr[2]], [0, intr[1], intr[3]], [0, 0, 1.0]])
    name = str(cam.get("distortion_model", "radtan")).strip().lower()
    dist = _matrix(cam.get("distortion_coeffs", []), path, f"{key}.distortion_coeffs")
    if name == "none":
        model, dist = PLUMB_BOB, np.zeros(5)
    else:
        model = _model(name, path, f"{key}: distortion_model")
        if model == PLUMB_BOB and dist.size != 4:
            raise _fail(path, f"{key}: radtan takes 4 coefficients [k1, k2, p1, p2]")
        if model == PLUMB_BOB:
            dist = np.append(dist, 0.0)
    w = _size(res[0], path, f"{key}.resolution width")
    h = _size(res[1], path, f"{key}.resolution height")
    return CameraModel(w, h, K, dist, model, key)


def _from_kalibr(d: dict, path: Path) -> CameraModel:
    """cam0 of a camchain; every camera of the chain must be one signpose can use."""
    cams = sorted(k for k in d if re.fullmatch(r"cam\d+", str(k)))
    if "cam0" not in cams:
        raise _fail(path, "Kalibr camchain has no 'cam0' (signpose reads cam0)")
    checked = [_kalibr_camera(d[key], key, path) for key in cams]
    return checked[0]


def _looks_like_kalibr(d: dict) -> bool:
    keys = {str(k) for k in d}
    return any(re.fullmatch(r"cam\d+", k) for k in keys) or {"intrinsics", "camera_model"} <= keys


# --------------------------------------------------------------------------- OpenCV FileStorage


def _fs_node(fs: cv2.FileStorage, names: tuple[str, ...]):
    for name in names:
        node = fs.getNode(name)
        if not node.empty():
            return node
    return None


def _fs_matrix(fs: cv2.FileStorage, names: tuple[str, ...]) -> np.ndarray | None:
    node = _fs_node(fs, names)
    if node is None:
        return None
    if node.isSeq():
        return np.array([node.at(i).real() for i in range(node.size())], dtype=float)
    mat = node.mat()
    return None if mat is None else np.asarray(mat, dtype=float)


def _fs_model(fs: cv2.FileStorage, path: Path) -> str:
    """The lens model a FileStorage file states: ``distortion_model``, its fisheye flag, both."""
    model_node = _fs_node(fs, ("distortion_model",))
    named = _model(model_node.string(), path) if model_node is not None else None
    flag = _fs_node(fs, ("fisheye_model", "fisheye", "Fisheye_Model"))
    flagged = None
    if flag is not None:
        if not flag.isInt() or int(flag.real()) not in (0, 1):
            raise _fail(path, f"'{flag.name()}' must be 0 or 1")
        flagged = EQUIDISTANT if int(flag.real()) else PLUMB_BOB
    if named is not None and flagged is not None and named != flagged:
        raise _fail(
            path,
            f"distortion_model says {named} but {flag.name()} says {flagged}; fix one of them",
        )
    return named or flagged or PLUMB_BOB


def _from_filestorage(fs: cv2.FileStorage, path: Path) -> CameraModel:
    if not fs.root().isMap():
        raise _fail(path, "not a camera file: the OpenCV FileStorage top level is not a mapping")
    K = _fs_matrix(fs, ("camera_matrix", "Camera_Matrix", "K"))
    if K is None or K.size != 9:
        raise _fail(path, "missing 3x3 'camera_matrix' (OpenCV FileStorage)")
    K = K.reshape(3, 3)
    D = _fs_matrix(fs, ("distortion_coefficients", "Distortion_Coefficients", "D"))
    dist = np.zeros(5) if D is None else D.reshape(-1)
    sizes = []
    for names in (("image_width", "image_Width"), ("image_height", "image_Height")):
        node = _fs_node(fs, names)
        if node is None or not (node.isInt() or node.isReal()):
            raise _fail(path, f"missing '{names[0]}' (OpenCV FileStorage)")
        sizes.append(_size(node.real(), path, names[0]))
    if not np.all(np.isfinite(K)) or not np.all(np.isfinite(dist)):
        raise _fail(path, "camera_matrix or distortion has a non-finite number")
    return CameraModel(sizes[0], sizes[1], K, dist, _fs_model(fs, path), path.stem)


def _read_filestorage(text: str, path: Path, what: str, source_format: str) -> CameraFile:
    """The camera of an OpenCV FileStorage text, read with ``cv2.FileStorage``.

    cv2 raises ``cv2.error`` (or a SystemError) for damaged files, on opening or
    on reading a node of the wrong kind: either is the file's fault, so one line.
    """
    try:
        fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
        opened = fs.isOpened()
    except Exception:  # noqa: BLE001 - see above
        opened = False
    if not opened:
        raise _fail(path, f"not a readable OpenCV FileStorage {what} file")
    try:
        return CameraFile(_from_filestorage(fs, path), source_format)
    except (cv2.error, SystemError) as exc:
        where = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise _fail(path, f"not a valid OpenCV FileStorage {what} file ({where[:80]})") from None
    finally:
        fs.release()


# --------------------------------------------------------------------------- reading


def _read_text(p: Path) -> str:
    try:
        size = p.stat().st_size
        if size > MAX_CAMERA_FILE_BYTES:
            raise _fail(
                p, f"{size} bytes: not a camera file (the limit is {MAX_CAMERA_FILE_BYTES} bytes)"
            )
        return p.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise _fail(p, "camera file not found") from None
    except IsADirectoryError:
        raise _fail(p, "is a folder; pass the camera file") from None
    except UnicodeDecodeError as exc:
        raise _fail(p, f"not a text file (byte {exc.start} is not UTF-8)") from None
    except OSError as exc:
        raise _fail(p, f"cannot read camera file ({exc.strerror})") from None


def _safe_yaml(text: str, p: Path):
    check_nesting(text, p)
    try:
        return safe_load_unique(text)
    except yaml.MarkedYAMLError as exc:
        line = exc.problem_mark.line + 1 if exc.problem_mark is not None else "?"
        raise _fail(p, f"not valid YAML at line {line} ({exc.problem})") from None
    except (yaml.YAMLError, ValueError, TypeError, OverflowError, RecursionError) as exc:
        raise _fail(p, f"not valid YAML ({type(exc).__name__})") from None


def _read_yaml_directive_file(text: str, p: Path) -> CameraFile:
    """A file starting ``%YAML``: a Kalibr camchain with that header, or OpenCV FileStorage."""
    check_nesting(text, p)
    try:  # plain YAML once the directive is gone (OpenCV's !!opencv-matrix tags are not)
        d = yaml.safe_load(_YAML_DIRECTIVE.sub("", text, count=1))
    except Exception:  # noqa: BLE001 - not plain YAML: OpenCV's reader decides below
        d = None
    if isinstance(d, dict) and _looks_like_kalibr(d):
        return CameraFile(_from_kalibr(d, p), KALIBR)
    return _read_filestorage(text, p, "YAML", OPENCV)


def _read(p: Path, text: str) -> CameraFile:
    head = text.lstrip()
    if head.startswith(("<?xml", "<opencv_storage")):
        return _read_filestorage(text, p, "XML", OPENCV_XML)
    if head.startswith("%YAML"):
        return _read_yaml_directive_file(text, p)
    d = _safe_yaml(text, p)
    if not isinstance(d, dict):
        raise _fail(p, "not a camera file; expected ROS camera_info, OpenCV or Kalibr YAML")
    if _looks_like_kalibr(d):
        return CameraFile(_from_kalibr(d, p), KALIBR)
    if "camera_matrix" in d:
        return CameraFile(_from_ros(d, p), ROS_CAMERA_INFO)
    raise _fail(p, "unknown camera format; expected ROS camera_info, OpenCV or Kalibr YAML")


def read_camera_file(path: str | Path) -> CameraFile:
    """Read a camera file in any supported format, with the format it was in.

    Raises:
        InputError: naming the file and what to fix (unreadable, unknown format,
            a lens model signpose cannot use, a number out of range).
    """
    p = Path(path)
    found = _read(p, _read_text(p))
    return CameraFile(_checked(found.camera, p), found.source_format)


def load_camera(path: str | Path) -> CameraModel:
    """Read a camera file in any supported format; InputError names the file on failure."""
    return read_camera_file(path).camera


# --------------------------------------------------------------------------- writing


def camera_summary(camera: CameraModel, source_format: str | None = None) -> dict:
    """What a camera is, as one JSON-ready object (``signpose camera FILE`` prints it)."""
    out = {
        "model": camera.model,
        "width": int(camera.width),
        "height": int(camera.height),
        "fx": camera.fx,
        "fy": camera.fy,
        "cx": camera.cx,
        "cy": camera.cy,
        "skew": float(camera.K[0, 1]),
        "distortion": [float(x) for x in camera.dist.reshape(-1)],
    }
    if source_format is not None:
        out["source_format"] = source_format
    return out


def camera_info_dict(camera: CameraModel) -> dict:
    """The ROS camera_info YAML content for ``camera``."""
    K = [float(x) for x in camera.K.reshape(-1)]
    P = [K[0], K[1], K[2], 0.0, K[3], K[4], K[5], 0.0, K[6], K[7], K[8], 0.0]
    dist = [float(x) for x in camera.dist.reshape(-1)]
    ros_model = camera.model
    if camera.model == PLUMB_BOB and len(dist) > 5:
        ros_model = "rational_polynomial"
    return {
        "image_width": int(camera.width),
        "image_height": int(camera.height),
        "camera_name": camera.name,
        "camera_matrix": {"rows": 3, "cols": 3, "data": K},
        "distortion_model": ros_model,
        "distortion_coefficients": {"rows": 1, "cols": len(dist), "data": dist},
        "rectification_matrix": {"rows": 3, "cols": 3, "data": list(_IDENTITY_3)},
        "projection_matrix": {"rows": 3, "cols": 4, "data": P},
    }


def write_camera_info(path: str | Path, camera: CameraModel) -> None:
    """Write ``camera`` as ROS camera_info YAML (atomically)."""
    with atomic_write(path) as f:
        yaml.safe_dump(camera_info_dict(camera), f, sort_keys=False, default_flow_style=None)


def write_opencv(path: str | Path, camera: CameraModel) -> None:
    """Write ``camera`` as OpenCV FileStorage YAML (atomically), as cv2 writes it."""
    with atomic_path(path) as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
        try:
            fs.write("image_width", int(camera.width))
            fs.write("image_height", int(camera.height))
            fs.write("camera_matrix", np.asarray(camera.K, dtype=float))
            fs.write("distortion_model", camera.model)
            fs.write("fisheye_model", int(camera.model == EQUIDISTANT))
            fs.write("distortion_coefficients", camera.dist.reshape(1, -1).astype(float))
        finally:
            fs.release()


def kalibr_dict(camera: CameraModel) -> dict:
    """A one-camera Kalibr camchain for ``camera``.

    Raises:
        ValueError: the camera has skew or more than radtan's 4 coefficients +
            k3 = 0, which a Kalibr pinhole camera cannot state.
    """
    dist = [float(x) for x in camera.dist.reshape(-1)]
    if camera.K[0, 1] != 0:
        raise ValueError("a Kalibr pinhole camera has no skew; this camera's is not 0")
    if camera.model == PLUMB_BOB:
        if any(dist[4:]):
            raise ValueError("Kalibr radtan takes k1, k2, p1, p2; this camera has more terms")
        dist, model = dist[:4], "radtan"
    else:
        model = "equidistant"
    return {
        "cam0": {
            "camera_model": "pinhole",
            "intrinsics": [camera.fx, camera.fy, camera.cx, camera.cy],
            "distortion_model": model,
            "distortion_coeffs": dist,
            "resolution": [int(camera.width), int(camera.height)],
        }
    }


def write_kalibr(path: str | Path, camera: CameraModel) -> None:
    """Write ``camera`` as a Kalibr camchain YAML (atomically).

    Raises:
        InputError: naming ``path``, when Kalibr cannot state the camera (``kalibr_dict``).
    """
    try:
        chain = kalibr_dict(camera)
    except ValueError as exc:
        raise _fail(Path(path), str(exc)) from None
    with atomic_write(path) as f:
        yaml.safe_dump(chain, f, sort_keys=False, default_flow_style=None)
