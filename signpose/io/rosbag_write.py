"""rosbag2 out: a run's results as a bag folder that ROS 2 tools open (MCAP storage).

Written with the ``rosbags`` writer (rosbag2 metadata version 8, storage
``mcap`` with the ``ros2`` profile, CDR messages with their ROS 2 message
definitions in the file). The tests read it back with rosbags (which evo's bag
mode uses); ``ros2 bag`` of Iron and later reads metadata version 8, Humble's
may refuse it. Topics:

    /signpose/<method>/pose   geometry_msgs/msg/PoseStamped  world_T_cam per frame
    /signpose/<method>/path   nav_msgs/msg/Path              the whole trajectory, once
    /tf                       tf2_msgs/msg/TFMessage          world -> camera frame per frame
    /signpose/signs           visualization_msgs/msg/MarkerArray  a disc and a label per sign
    /camera/camera_info       sensor_msgs/msg/CameraInfo      once, when the camera is known

Poses are ``world_T_cam`` in the map's world frame; the camera frame is
OpenCV's (x right, y down, z forward), named by the input's own frame id.
Stamps are the frames' stamps; the once-only messages carry the first frame's.
The folder appears complete or not at all (written beside it, then renamed).
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from signpose.core.errors import OutputError
from signpose.core.fileio import temp_dir_beside
from signpose.estimator.camera import EQUIDISTANT, CameraModel
from signpose.estimator.trajectory import Trajectory, quat_xyzw_from_rotation
from signpose.frontend.observations import FrameObservations
from signpose.io.foxglove import CAMERA_FRAME
from signpose.io.tracks import pose_tracks
from signpose.maps.loader import SignMap

BAG_VERSION = 8  # rosbag2 metadata version (Iron and later read it; rosbags writes 8 or 9)
TF_TOPIC = "/tf"
SIGNS_TOPIC = "/signpose/signs"
CAMERA_INFO_TOPIC = "/camera/camera_info"
POSE = "geometry_msgs/msg/PoseStamped"
PATH = "nav_msgs/msg/Path"
TF = "tf2_msgs/msg/TFMessage"
MARKERS = "visualization_msgs/msg/MarkerArray"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
SIGN_DISC_THICKNESS_M = 0.02


def pose_topic(method: str) -> str:
    return f"/signpose/{method}/pose"


def path_topic(method: str) -> str:
    return f"/signpose/{method}/path"


@cache
def _store():
    return get_typestore(Stores.ROS2_HUMBLE)


def _t(name: str):
    return _store().types[name]


# --------------------------------------------------------------------------- messages


def _header(stamp_ns: int, frame_id: str):
    ns = max(0, int(stamp_ns))
    time = _t("builtin_interfaces/msg/Time")(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    return _t("std_msgs/msg/Header")(stamp=time, frame_id=frame_id)


def _pose(world_T_x: np.ndarray):
    T = np.asarray(world_T_x, dtype=float)
    qx, qy, qz, qw = (float(v) for v in quat_xyzw_from_rotation(T[:3, :3])[0])
    x, y, z = (float(v) for v in T[:3, 3])
    return _t("geometry_msgs/msg/Pose")(
        position=_t("geometry_msgs/msg/Point")(x=x, y=y, z=z),
        orientation=_t("geometry_msgs/msg/Quaternion")(x=qx, y=qy, z=qz, w=qw),
    )


def pose_stamped(stamp_ns: int, world: str, world_T_cam: np.ndarray):
    """geometry_msgs/msg/PoseStamped of one camera pose (4, 4) in frame ``world``."""
    return _t(POSE)(header=_header(stamp_ns, world), pose=_pose(world_T_cam))


def transform(stamp_ns: int, parent: str, child: str, parent_T_child: np.ndarray):
    """tf2_msgs/msg/TFMessage with the one transform ``parent_T_child`` (4, 4)."""
    pose = _pose(parent_T_child)
    p = pose.position
    stamped = _t("geometry_msgs/msg/TransformStamped")(
        header=_header(stamp_ns, parent),
        child_frame_id=child,
        transform=_t("geometry_msgs/msg/Transform")(
            translation=_t("geometry_msgs/msg/Vector3")(x=p.x, y=p.y, z=p.z),
            rotation=pose.orientation,
        ),
    )
    return _t(TF)(transforms=[stamped])


def camera_info(stamp_ns: int, camera: CameraModel, frame_id: str):
    """sensor_msgs/msg/CameraInfo of ``camera`` (K, D, R = I, P = [K|0])."""
    K = np.asarray(camera.K, dtype=float).reshape(-1)
    P = np.array([K[0], K[1], K[2], 0.0, K[3], K[4], K[5], 0.0, K[6], K[7], K[8], 0.0])
    model = "equidistant" if camera.model == EQUIDISTANT else "plumb_bob"
    if camera.model != EQUIDISTANT and camera.dist.size > 5:
        model = "rational_polynomial"
    roi = _t("sensor_msgs/msg/RegionOfInterest")(
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    return _t(CAMERA_INFO)(
        header=_header(stamp_ns, frame_id),
        height=int(camera.height),
        width=int(camera.width),
        distortion_model=model,
        d=np.asarray(camera.dist, dtype=float).reshape(-1),
        k=K,
        r=np.eye(3).reshape(-1),
        p=P,
        binning_x=0,
        binning_y=0,
        roi=roi,
    )


def _marker(stamp_ns: int, world: str, marker_id: int, kind: int, world_T_x, scale, rgba, text=""):
    Marker = _t("visualization_msgs/msg/Marker")
    r, g, b, a = (float(v) for v in rgba)
    return Marker(
        header=_header(stamp_ns, world),
        ns="signs",
        id=marker_id,
        type=kind,
        action=Marker.ADD,
        pose=_pose(world_T_x),
        scale=_t("geometry_msgs/msg/Vector3")(x=scale[0], y=scale[1], z=scale[2]),
        color=_t("std_msgs/msg/ColorRGBA")(r=r, g=g, b=b, a=a),
        lifetime=_t("builtin_interfaces/msg/Duration")(sec=0, nanosec=0),
        frame_locked=False,
        points=[],
        colors=[],
        texture_resource="",
        texture=_t("sensor_msgs/msg/CompressedImage")(
            header=_header(0, ""), format="", data=np.zeros(0, np.uint8)
        ),
        uv_coordinates=[],
        text=text,
        mesh_resource="",
        mesh_file=_t("visualization_msgs/msg/MeshFile")(filename="", data=np.zeros(0, np.uint8)),
        mesh_use_embedded_materials=False,
    )


def sign_markers(stamp_ns: int, sign_map: SignMap):
    """visualization_msgs/msg/MarkerArray: a thin disc (cylinder) and the code of every sign."""
    Marker = _t("visualization_msgs/msg/Marker")
    markers = []
    for i, sign in enumerate(sign_map.signs):
        world_T_sign = sign.world_T_sign() if sign.oriented else np.eye(4)
        world_T_sign[:3, 3] = sign.center_m
        d = float(sign.diameter_m)
        label = np.eye(4)
        label[:3, 3] = sign.center_m + np.array([0.0, 0.0, 0.65 * d])
        disc_scale = (d, d, SIGN_DISC_THICKNESS_M)
        markers.append(
            _marker(stamp_ns, sign_map.frame, 2 * i, Marker.CYLINDER, world_T_sign, disc_scale,
                    (0.95, 0.95, 0.95, 1.0))
        )  # fmt: skip
        markers.append(
            _marker(stamp_ns, sign_map.frame, 2 * i + 1, Marker.TEXT_VIEW_FACING, label,
                    (0.0, 0.0, 0.3 * d), (1.0, 1.0, 0.2, 1.0), sign.code)
        )  # fmt: skip
    return _t(MARKERS)(markers=markers)


def path_message(world: str, stamps_ns: np.ndarray, world_T_cams: np.ndarray, stamp_ns: int):
    """nav_msgs/msg/Path of a whole trajectory: (N,) stamps [ns], (N, 4, 4) poses."""
    poses = [pose_stamped(int(t), world, T) for t, T in zip(stamps_ns, world_T_cams, strict=True)]
    return _t(PATH)(header=_header(stamp_ns, world), poses=poses)


# --------------------------------------------------------------------------- writing


class _BagOut:
    """A rosbags writer that serialises messages and registers topics on first use."""

    def __init__(self, writer: Writer):
        self._writer = writer
        self._connections: dict[str, object] = {}

    def write(self, topic: str, msgtype: str, message, stamp_ns: int) -> None:
        conn = self._connections.get(topic)
        if conn is None:
            conn = self._writer.add_connection(topic, msgtype, typestore=_store())
            self._connections[topic] = conn
        self._writer.write(conn, max(0, int(stamp_ns)), _store().serialize_cdr(message, msgtype))


@dataclass(frozen=True)
class ResultBag:
    """What ``write_result_bag`` writes (everything but the path has a default).

    Attributes:
        sign_map: the signs (markers) and the world frame name.
        frames: the observations per frame: their stamps drive poses and /tf.
        trajectories: method name -> estimated world_T_cam per stamp; the one
            named ``smoothed`` (else the first) drives /tf.
        camera: written once as CameraInfo when given.
        camera_frame: the input's camera frame id (tf child, CameraInfo frame).
    """

    sign_map: SignMap
    frames: tuple[FrameObservations, ...]
    trajectories: dict[str, Trajectory]
    camera: CameraModel | None = None
    camera_frame: str = CAMERA_FRAME


def _write_messages(out: _BagOut, bag: ResultBag) -> None:
    world = bag.sign_map.frame
    t0 = bag.frames[0].stamp_ns if bag.frames else 0
    tracks = pose_tracks(bag.trajectories)
    tf_name = "smoothed" if "smoothed" in tracks else next(iter(tracks), None)
    out.write(SIGNS_TOPIC, MARKERS, sign_markers(t0, bag.sign_map), t0)
    if bag.camera is not None:
        out.write(CAMERA_INFO_TOPIC, CAMERA_INFO, camera_info(t0, bag.camera, bag.camera_frame), t0)
    for name, track in tracks.items():
        msg = path_message(world, track.stamps_ns, track.world_T_cams, t0)
        out.write(path_topic(name), PATH, msg, t0)
    for obs in bag.frames:
        t = int(obs.stamp_ns)
        for name, track in tracks.items():
            T = track.at(t)
            if T is None:
                continue
            out.write(pose_topic(name), POSE, pose_stamped(t, world, T), t)
            if name == tf_name:
                out.write(TF_TOPIC, TF, transform(t, world, bag.camera_frame, T), t)


def write_result_bag(path: str | os.PathLike, bag: ResultBag) -> Path:
    """Write ``bag`` as a rosbag2 folder at ``path`` (replacing an older one), atomically.

    Raises:
        OutputError: the folder cannot be written (named with its final path).
    """
    target = Path(path)
    if target.exists() and not target.is_dir():
        raise OutputError(f"{target}: exists and is not a folder; remove it or choose another")
    work = temp_dir_beside(target)  # with this process's id: a killed write's is removed later
    staged = work / target.name
    try:
        with Writer(staged, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP) as writer:
            _write_messages(_BagOut(writer), bag)
        _swap_in(staged, target)
    except OSError as exc:
        raise OutputError(f"{target}: cannot write ({exc.strerror or exc})") from None
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return target


def _swap_in(staged: Path, target: Path) -> None:
    """Move the finished folder to ``target``; an older bag there goes only once it is."""
    old = None
    if target.exists():
        old = target.with_name(f".{target.name}.old")
        shutil.rmtree(old, ignore_errors=True)
        target.rename(old)
    staged.rename(target)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
