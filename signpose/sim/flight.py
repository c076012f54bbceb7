"""Flight simulator: a sign map + a trajectory -> frames with ground truth.

The 3D side lives here (scene geometry, projection through the camera model
with its lens distortion); ``frontend.render`` draws the projected polygons.

World frame: the map's (z up, metres). Camera poses are ``world_T_cam`` with
OpenCV axes (x right, y down, z forward). Time: frame ``i`` is at
``i / fps`` seconds, ``stamp_ns = round(i * 1e9 / fps)``; the exposure is
centred on the stamp.

Output folder (``simulate``):
    video.mp4 or frames/NNNNNN.png   the frames
    camera.yaml                      ROS camera_info (estimator.camera)
    groundtruth.tum                  world_T_cam per frame (signpose.io.tum)
    boxes.jsonl                      per-frame truth of every visible sign (this module)
    map.yaml                         copy of the map (maps.loader)

``boxes.jsonl``: one line per frame, in frame order::

    {"frame": 0, "stamp_ns": 0, "signs": [{"code": "0101", "bbox_px": [x, y, w, h],
     "center_px": [u, v], "diameter_px": d, "keypoints_px": {"center": [u, v], ...},
     "occluded": false, "truncated": false, "distance_m": 27.1}]}

Pixels are raw (distorted) image pixels, centres at integers. ``bbox_px`` is
the projected disc's bounding box clipped to the image; ``diameter_px`` the
longest projected diameter of the disc; ``keypoints_px`` the keypoints of
``frontend.sign.sign_keypoints`` (white parts only); ``occluded`` is true when
an occluder or a conductor in front covers part of the face; ``truncated``
when part of the disc is outside the image.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import os
import shutil
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

import cv2
import numpy as np
from tqdm import tqdm

from signpose.core.errors import InputError, OutputError
from signpose.core.fileio import atomic_path, atomic_write, ensure_dir, umask_mode
from signpose.estimator.camera import (
    CameraModel,
    pinhole_camera,
    pixel_from_cam_point,
    pixel_from_world_point,
)
from signpose.estimator.trajectory import Trajectory
from signpose.frontend.sign import sign_keypoints, sign_shape
from signpose.io.camera_file import write_camera_info
from signpose.io.tum import write_tum
from signpose.maps.loader import SignMap, write_map
from signpose.sim.render import (
    Backdrop,
    ProjectedLine,
    ProjectedSign,
    RenderOptions,
    compose_frame,
)
from signpose.sim.trajectories import TRAJECTORIES, make_trajectory

log = logging.getLogger(__name__)

FORMATS = ("mp4", "png", "mcap")
LATTICE_BGR = (105.0, 110.0, 112.0)
CONDUCTOR_BGR = (38.0, 40.0, 44.0)


# --------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class SimSettings:
    """What to simulate (defaults: the paper's simulated set, 1080p at 25-30 m).

    Attributes:
        frames: number of frames.
        fps: frame rate [Hz].
        trajectory: one of ``signpose.sim.trajectories.TRAJECTORIES``.
        seed: seeds the trajectory wobble, the scene textures, dirt, occluders,
            lighting and noise. Same seed, same outputs.
        width, height: image size [px].
        hfov_deg: horizontal field of view [deg].
        distortion_k1: plumb_bob k1 of the simulated lens (0 = ideal pinhole).
        distance_m: nominal distance from the signs [m].
        format: ``"mp4"`` (video.mp4, mp4v), ``"png"`` (frames/NNNNNN.png) or ``"mcap"``
            (flight.mcap: images, ground truth and camera; ``signpose.mcap_io``).
        dirt: stains on some sign faces.
        occlusion: opaque bars in front of some sign faces.
        blur: motion blur from the real motion during the exposure.
        exposure_fraction: exposure time as a fraction of the frame period.
        noise_sigma: sensor noise [DN], 0 = off.
        jpeg_quality: JPEG round-trip quality, None = off.
        background: sky, ground, lattice and conductors (False: flat grey).
        lighting: slowly varying global gain/offset.
        supersample: sub-samples per pixel side for the sign faces.
    """

    frames: int = 210
    fps: float = 30.0
    trajectory: str = "climb-hover-depart"
    seed: int = 0
    width: int = 1920
    height: int = 1080
    hfov_deg: float = 60.0
    distortion_k1: float = -0.05
    distance_m: float = 27.0
    format: str = "mp4"
    dirt: bool = False
    occlusion: bool = False
    blur: bool = True
    exposure_fraction: float = 0.5
    noise_sigma: float = 2.5
    jpeg_quality: int | None = 90
    background: bool = True
    lighting: bool = True
    supersample: int = 4

    def render_options(self) -> RenderOptions:
        return RenderOptions(
            supersample=self.supersample,
            blur=self.blur,
            noise_sigma=self.noise_sigma,
            jpeg_quality=self.jpeg_quality,
            background=self.background,
            lighting=self.lighting,
        )

    def validate(self) -> SimSettings:
        """Return self, or raise InputError naming the bad setting."""
        if self.frames < 1:
            raise InputError(f"--frames must be >= 1, got {self.frames}")
        if not (self.fps > 0 and math.isfinite(self.fps)):
            raise InputError(f"--fps must be > 0, got {self.fps}")
        if self.trajectory not in TRAJECTORIES:
            raise InputError(
                f"unknown trajectory {self.trajectory!r}; choose from {', '.join(TRAJECTORIES)}"
            )
        if self.format not in FORMATS:
            raise InputError(f"unknown format {self.format!r}; choose from {', '.join(FORMATS)}")
        if self.width < 16 or self.height < 16:
            raise InputError(f"image size {self.width}x{self.height} is too small")
        if not 1.0 < self.hfov_deg < 170.0:
            raise InputError(f"hfov_deg must be in (1, 170), got {self.hfov_deg}")
        if self.jpeg_quality is not None and not 1 <= self.jpeg_quality <= 100:
            raise InputError(f"jpeg_quality must be in 1..100, got {self.jpeg_quality}")
        if not 0.0 <= self.exposure_fraction <= 1.0:
            raise InputError(f"exposure_fraction must be in [0, 1], got {self.exposure_fraction}")
        if not (self.noise_sigma >= 0 and math.isfinite(self.noise_sigma)):
            raise InputError(f"noise_sigma must be >= 0, got {self.noise_sigma}")
        if not self.distance_m > 0:
            raise InputError(f"distance_m must be > 0, got {self.distance_m}")
        if not 1 <= self.supersample <= 16:
            raise InputError(f"supersample must be in 1..16, got {self.supersample}")
        return self


@dataclass(frozen=True)
class SimResult:
    """What ``simulate`` wrote.

    Attributes:
        out_dir: the output folder.
        frames_path: ``video.mp4`` or the ``frames`` folder.
        camera_path: ``camera.yaml`` (ROS camera_info).
        groundtruth_path: ``groundtruth.tum`` (world_T_cam, t in seconds).
        boxes_path: ``boxes.jsonl`` (per-frame sign truth).
        map_path: ``map.yaml`` (copy of the map).
        n_frames: number of frames written.
        camera: the simulated camera.
        trajectory: the ground truth trajectory.
    """

    out_dir: Path
    frames_path: Path
    camera_path: Path
    groundtruth_path: Path
    boxes_path: Path
    map_path: Path
    n_frames: int
    camera: CameraModel
    trajectory: Trajectory

    def paths(self) -> tuple[Path, ...]:
        return (
            self.frames_path,
            self.camera_path,
            self.groundtruth_path,
            self.boxes_path,
            self.map_path,
        )


@dataclass(frozen=True)
class SignTruth:
    """Ground truth of one visible sign in one frame (raw pixels, centres at integers).

    Attributes:
        code: the sign's code.
        bbox_px: (x, y, w, h) bounding box of the projected disc, clipped to the image.
        center_px: (u, v) projection of the map centre.
        diameter_px: longest projected diameter of the disc [px].
        keypoints_px: keypoint name -> (u, v), white parts only.
        occluded: an occluder or a conductor in front covers part of the face.
        truncated: part of the disc is outside the image.
        distance_m: distance from the camera centre to the sign centre [m].
    """

    code: str
    bbox_px: tuple[float, float, float, float]
    center_px: tuple[float, float]
    diameter_px: float
    keypoints_px: dict[str, tuple[float, float]]
    occluded: bool
    truncated: bool
    distance_m: float

    def to_json(self) -> dict:
        return {
            "code": self.code,
            "bbox_px": [round(v, 3) for v in self.bbox_px],
            "center_px": [round(v, 4) for v in self.center_px],
            "diameter_px": round(self.diameter_px, 3),
            "keypoints_px": {
                k: [round(v[0], 4), round(v[1], 4)] for k, v in self.keypoints_px.items()
            },
            "occluded": self.occluded,
            "truncated": self.truncated,
            "distance_m": round(self.distance_m, 4),
        }


# --------------------------------------------------------------------------- scene


@dataclass(frozen=True)
class SignModel:
    """One sign's drawable geometry in the world frame (built once per flight).

    Attributes:
        code: the sign's code.
        center_m: (3,) disc centre [m], world.
        normal: (3,) unit face normal, world (assumed for centre-only map signs).
        diameter_m: disc diameter [m].
        disc_m: (N, 3) disc outline [m], world.
        white_m: (M_k, 3) white rectangle outlines (edges densified) [m], world.
        keypoints_m: keypoint name -> (3,) [m], world.
        dirt_m: (polygon (P, 3) [m] world, intensity, opacity) stains.
        occluders_m: (polygon (P, 3) [m] world, intensity) bars in front of the face.
        shade: reflectance/illumination factor of the face (1 = nominal paint).
    """

    code: str
    center_m: np.ndarray
    normal: np.ndarray
    diameter_m: float
    disc_m: np.ndarray
    white_m: tuple[np.ndarray, ...]
    keypoints_m: dict[str, np.ndarray]
    dirt_m: tuple[tuple[np.ndarray, float, float], ...]
    occluders_m: tuple[tuple[np.ndarray, float], ...]
    shade: float = 1.0


@dataclass(frozen=True)
class Line3D:
    """A thin 3D structure: (N, 3) polyline [m], world; width [m]; colour BGR."""

    points_m: np.ndarray
    width_m: float
    bgr: tuple[float, float, float]


@dataclass(frozen=True)
class Scene:
    """Everything static in a simulated flight.

    Attributes:
        sign_map: the map.
        camera: the simulated camera (with its distortion).
        signs: drawable sign geometry, map order.
        lines_behind: lattice members and far conductors (drawn behind signs).
        lines_front: conductors between the pylon and the camera.
        center_m: (3,) mean sign centre [m], used for the background motion.
        backdrop: sky/ground textures and noise bank (frontend.render).
    """

    sign_map: SignMap
    camera: CameraModel
    signs: tuple[SignModel, ...]
    lines_behind: tuple[Line3D, ...]
    lines_front: tuple[Line3D, ...]
    center_m: np.ndarray
    backdrop: Backdrop


def simulated_camera(settings: SimSettings = SimSettings()) -> CameraModel:
    """The simulated camera: pinhole of ``hfov_deg`` with plumb_bob k1 distortion."""
    cam = pinhole_camera(settings.width, settings.height, settings.hfov_deg, name="sim")
    dist = np.array([settings.distortion_k1, 0.0, 0.0, 0.0, 0.0])
    return replace(cam, dist=dist)


def _site_axes(sign_map: SignMap) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean sign centre, horizontal facing direction, horizontal lateral axis."""
    centers = sign_map.centers_m()
    center = centers.mean(axis=0)
    normals = [s.normal for s in sign_map.signs if s.normal is not None]
    if normals:
        facing = np.mean(normals, axis=0)
    else:
        _, _, vt = np.linalg.svd(centers - center)
        facing = vt[-1].copy()
    facing[2] = 0.0
    if np.linalg.norm(facing) < 1e-6:
        facing = np.array([0.0, 1.0, 0.0])
    facing = facing / np.linalg.norm(facing)
    lateral = np.cross(np.array([0.0, 0.0, 1.0]), facing)
    return center, facing, lateral / np.linalg.norm(lateral)


def _densify(poly: np.ndarray, pieces: int) -> np.ndarray:
    """Split every edge of closed polygon ``poly`` (N, D) into ``pieces`` parts."""
    nxt = np.roll(poly, -1, axis=0)
    t = np.arange(pieces)[None, :, None] / pieces
    return (poly[:, None, :] * (1 - t) + nxt[:, None, :] * t).reshape(-1, poly.shape[1])


def _ellipse(center: np.ndarray, a: float, b: float, angle: float, n: int = 24) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    c, s = math.cos(angle), math.sin(angle)
    x, y = a * np.cos(t), b * np.sin(t)
    return np.stack([center[0] + c * x - s * y, center[1] + s * x + c * y], axis=1)


def _sign_model(
    s, facing: np.ndarray, rng: np.random.Generator, dirt: bool, occlusion: bool
) -> SignModel:
    if s.oriented:
        R = s.world_R_sign()
    else:
        # Centre-only landmark: drawn facing the site's viewers, directional rectangle up.
        up = np.array([0.0, 0.0, 1.0])
        R = np.stack([np.cross(up, facing), up, facing], axis=1)
    shape = sign_shape(s.code, s.diameter_m)
    r = s.diameter_m / 2.0

    def world(xy: np.ndarray, z: float = 0.0) -> np.ndarray:
        p = np.column_stack([xy, np.full(len(xy), z)])
        return s.center_m + p @ R.T

    stains: list[tuple[np.ndarray, float, float]] = []
    if dirt and rng.random() < 0.7:
        for _ in range(int(rng.integers(2, 6))):
            c = rng.uniform(-0.8, 0.8, 2) * r
            poly = _ellipse(
                c, rng.uniform(0.05, 0.22) * r, rng.uniform(0.04, 0.12) * r, rng.uniform(0, np.pi)
            )
            # Dark grime or pale deposits (bird droppings, lichen).
            value = rng.uniform(60, 110) if rng.random() < 0.5 else rng.uniform(160, 210)
            stains.append((world(poly, 0.001), float(value), float(rng.uniform(0.25, 0.7))))
    bars: list[tuple[np.ndarray, float]] = []
    if occlusion and rng.random() < 0.4:
        # An opaque bar (a bracket, a bird diverter) across the face, missing the
        # location square so the sign stays locatable though maybe not decodable.
        angle = rng.uniform(0, np.pi)
        normal2d = np.array([-math.sin(angle), math.cos(angle)])
        along = np.array([math.cos(angle), math.sin(angle)])
        off = rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 0.85) * r
        half_w = rng.uniform(0.06, 0.14) * r
        mid = off * normal2d
        corners = np.array(
            [
                mid + sa * 1.3 * r * along + sw * half_w * normal2d
                for sa, sw in ((-1, -1), (1, -1), (1, 1), (-1, 1))
            ]
        )
        bars.append((world(_densify(corners, 8), 0.08), float(rng.uniform(45, 90))))
    kps = sign_keypoints(s.code, s.diameter_m)
    return SignModel(
        code=s.code,
        center_m=np.asarray(s.center_m, float),
        normal=R[:, 2].copy(),
        diameter_m=float(s.diameter_m),
        disc_m=world(shape.disc),
        white_m=tuple(world(_densify(c, 6)) for c in shape.white_parts.values()),
        keypoints_m={k: s.center_m + R @ p for k, p in kps.items()},
        dirt_m=tuple(stains),
        occluders_m=tuple(bars),
    )


def _catenary(a: np.ndarray, b: np.ndarray, sag_m: float, n: int) -> np.ndarray:
    """(n, 3) points from ``a`` to ``b`` hanging ``sag_m`` at mid span (parabola)."""
    t = np.linspace(0.0, 1.0, n)[:, None]
    p = a * (1 - t) + b * t
    p[:, 2] -= 4.0 * sag_m * (t[:, 0] * (1 - t[:, 0]))
    return p


def _pylon_lines(sign_map: SignMap) -> tuple[list[Line3D], list[Line3D], list[Line3D]]:
    """Lattice members, far conductors and near conductors of a pylon behind the signs."""
    center, f, a = _site_axes(sign_map)
    rel = sign_map.centers_m() - center
    face = float((rel @ f).min()) - 0.15  # lattice face just behind the signs
    radius = max(s.diameter_m for s in sign_map.signs) / 2.0
    half_top = max(float(np.abs(rel @ a).max()) + radius + 0.6, 1.5)
    z_top = float(sign_map.centers_m()[:, 2].max()) + 3.0
    ground_z = 0.0
    half_bottom = half_top + 0.12 * (z_top - ground_z)
    base = center - (center @ np.array([0, 0, 1.0])) * np.array([0, 0, 1.0])  # on z = 0

    def hw(z: float) -> float:
        return half_bottom + (half_top - half_bottom) * (z - ground_z) / (z_top - ground_z)

    def point(lat: float, depth: float, z: float) -> np.ndarray:
        return base + lat * a + (face - depth) * f + np.array([0, 0, z])

    def seg(p: np.ndarray, q: np.ndarray, width: float, n: int = 8) -> Line3D:
        t = np.linspace(0, 1, n)[:, None]
        return Line3D(p * (1 - t) + q * t, width, LATTICE_BGR)

    lattice: list[Line3D] = []
    levels = np.linspace(ground_z, z_top, max(int((z_top - ground_z) / 3.0), 2) + 1)
    # The tower is square: depth of a level equals its width.
    for side_lat in (-1, 1):
        for side_d in (0, 1):
            corners = [point(side_lat * hw(z), side_d * 2 * hw(z), z) for z in (ground_z, z_top)]
            lattice.append(seg(corners[0], corners[1], 0.16, 16))
    for z0, z1 in zip(levels[:-1], levels[1:], strict=True):
        for d in (0, 1):  # front and back faces
            p00, p01 = point(-hw(z0), d * 2 * hw(z0), z0), point(hw(z0), d * 2 * hw(z0), z0)
            p10, p11 = point(-hw(z1), d * 2 * hw(z1), z1), point(hw(z1), d * 2 * hw(z1), z1)
            lattice += [seg(p00, p11, 0.08), seg(p01, p10, 0.08), seg(p10, p11, 0.09)]
        for lat in (-1, 1):  # side faces
            q00, q01 = point(lat * hw(z0), 0, z0), point(lat * hw(z0), 2 * hw(z0), z0)
            q10, q11 = point(lat * hw(z1), 0, z1), point(lat * hw(z1), 2 * hw(z1), z1)
            lattice += [seg(q00, q11, 0.08), seg(q01, q10, 0.08), seg(q10, q11, 0.09)]
    # Two crossarms and an earth-wire peak.
    arm_half = half_top + 7.0
    tips = []
    for z_arm in (z_top, z_top - 5.0):
        for d in (0.0, 2 * hw(z_arm)):
            lattice.append(seg(point(-arm_half, d, z_arm), point(arm_half, d, z_arm), 0.12, 24))
            for lat in (-1, 1):
                lattice.append(
                    seg(
                        point(lat * arm_half, d, z_arm),
                        point(lat * hw(z_arm - 2.5), d, z_arm - 2.5),
                        0.08,
                    )
                )
        for lat in (-1, 1):
            tips.append(point(lat * (arm_half - 0.3), hw(z_arm), z_arm - 2.2))
            # Insulator string.
            lattice.append(seg(point(lat * (arm_half - 0.3), hw(z_arm), z_arm), tips[-1], 0.18, 4))
    peak = point(0.0, hw(z_top), z_top + 3.5)
    for lat in (-1, 1):
        for d in (0.0, 2 * hw(z_top)):
            lattice.append(seg(point(lat * half_top, d, z_top), peak, 0.1))
    # Conductors run perpendicular to the crossarms, through the UAV's side and away.
    span = 300.0
    near: list[Line3D] = []
    far: list[Line3D] = []
    for tip in tips:
        near.append(Line3D(_catenary(tip, tip + span * f, 9.0, 240), 0.03, CONDUCTOR_BGR))
        far.append(Line3D(_catenary(tip, tip - span * f, 9.0, 120), 0.03, CONDUCTOR_BGR))
    # A low-voltage line along the face, between the pylon and the UAV: it crosses signs.
    for dz in (2.6, 3.4):
        z_att = center[2] + dz
        p = center + 7.0 * f + np.array([0, 0, z_att - center[2]])
        near.append(Line3D(_catenary(p - 60.0 * a, p + 60.0 * a, 2.6, 240), 0.025, CONDUCTOR_BGR))
    return lattice, far, near


def build_scene(
    sign_map: SignMap,
    camera: CameraModel,
    seed: int = 0,
    *,
    dirt: bool = False,
    occlusion: bool = False,
    background: bool = True,
) -> Scene:
    """The static part of a flight: sign geometry, pylon, conductors, textures.

    Args:
        sign_map: the signs.
        camera: the simulated camera.
        seed: seeds dirt, occluders and the textures.
        dirt: stain some sign faces.
        occlusion: put opaque bars in front of some sign faces.
        background: build the pylon, conductors and textures (False: signs only).
    """
    rng = np.random.default_rng([seed, 7919])
    center, facing, _ = _site_axes(sign_map)
    signs = tuple(_sign_model(s, facing, rng, dirt, occlusion) for s in sign_map.signs)
    if occlusion and not any(s.occluders_m for s in signs):
        # At least one occluded sign when occlusion is asked for.
        k = int(rng.integers(len(signs)))
        bar_rng = np.random.default_rng([seed, 2])
        bars: tuple = ()
        while not bars:
            bars = _sign_model(sign_map.signs[k], facing, bar_rng, False, True).occluders_m
        signs = signs[:k] + (replace(signs[k], occluders_m=bars),) + signs[k + 1 :]
    # Faces weather and catch the sun differently (own stream: other draws stay put).
    shades = np.random.default_rng([seed, 4242]).uniform(0.85, 1.08, len(signs))
    signs = tuple(replace(s, shade=float(f)) for s, f in zip(signs, shades, strict=True))
    if background:
        lattice, far, near = _pylon_lines(sign_map)
    else:
        lattice, far, near = [], [], []
    backdrop = Backdrop(camera.width, camera.height, seed=seed)
    return Scene(
        sign_map=sign_map,
        camera=camera,
        signs=signs,
        lines_behind=tuple(lattice + far),
        lines_front=tuple(near),
        center_m=center,
        backdrop=backdrop,
    )


# --------------------------------------------------------------------------- one frame


def _cam_points(world_T_cam: np.ndarray, world_points: np.ndarray) -> np.ndarray:
    cam_T_world = np.linalg.inv(world_T_cam)
    return (
        np.asarray(world_points, float).reshape(-1, 3) @ cam_T_world[:3, :3].T + cam_T_world[:3, 3]
    )


def _project_lines(
    camera: CameraModel, world_T_cam: np.ndarray, lines: tuple[Line3D, ...]
) -> list[ProjectedLine]:
    """Project polylines, cutting them where they leave the cone where the lens model is valid."""
    if not lines:
        return []
    f = camera.fx
    sizes = [len(ln.points_m) for ln in lines]
    cam = _cam_points(world_T_cam, np.concatenate([ln.points_m for ln in lines]))
    z = cam[:, 2]
    ok = z > 0.3
    rn = np.full(len(cam), np.inf)
    rn[ok] = np.hypot(cam[ok, 0], cam[ok, 1]) / z[ok]
    # Beyond ~1.3 (normalised radius) a barrel polynomial folds back; the image corner is ~0.66.
    ok &= rn < 1.3
    px = np.full((len(cam), 2), np.nan)
    if np.any(ok):
        px[ok] = pixel_from_cam_point(camera, cam[ok])
    out: list[ProjectedLine] = []
    start = 0
    for ln, n in zip(lines, sizes, strict=True):
        sl = slice(start, start + n)
        start += n
        valid = ok[sl]
        p, depth = px[sl], z[sl]
        # Runs of consecutive valid points.
        idx = np.flatnonzero(valid)
        if len(idx) < 2:
            continue
        breaks = np.flatnonzero(np.diff(idx) > 1)
        for run in np.split(idx, breaks + 1):
            if len(run) < 2:
                continue
            d_mid = 0.5 * (depth[run[:-1]] + depth[run[1:]])
            out.append(ProjectedLine(p[run], ln.width_m * f / d_mid, ln.bgr))
    return out


def _segment_distance(point: np.ndarray, polyline: np.ndarray) -> float:
    a, b = polyline[:-1], polyline[1:]
    ab = b - a
    t = np.clip(
        np.einsum("ij,ij->i", point - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab), 1e-12),
        0,
        1,
    )
    d = a + t[:, None] * ab - point
    return float(np.sqrt(np.einsum("ij,ij->i", d, d).min()))


def render_frame(
    scene: Scene,
    world_T_cam: np.ndarray,
    rng: np.random.Generator,
    *,
    options: RenderOptions | None = None,
    exposure_poses: tuple[np.ndarray, np.ndarray] | None = None,
    gain: float = 1.0,
    offset: float = 0.0,
) -> tuple[np.ndarray, list[SignTruth]]:
    """Render the scene from one pose.

    Args:
        scene: from ``build_scene``.
        world_T_cam: (4, 4) camera pose at the frame's stamp (mid-exposure).
        rng: per-frame randomness (sensor noise).
        options: rendering switches (noise, blur, JPEG, background...).
        exposure_poses: (4, 4) poses at the start and end of the exposure; the
            motion blur follows the image motion between them. None: no blur.
        gain, offset: global lighting (``out = gain * in + offset``).

    Returns:
        ((H, W, 3) uint8 BGR image, truth of every sign whose disc is in the image).
    """
    options = options if options is not None else RenderOptions()
    cam = scene.camera
    w, h = cam.width, cam.height
    cam_pos = world_T_cam[:3, 3]
    projected: list[ProjectedSign] = []
    truths: list[SignTruth] = []
    front = _project_lines(cam, world_T_cam, scene.lines_front) if options.background else []
    behind = _project_lines(cam, world_T_cam, scene.lines_behind) if options.background else []

    def motion_of(point: np.ndarray) -> np.ndarray | None:
        if exposure_poses is None:
            return None
        p0, _ = pixel_from_world_point(cam, exposure_poses[0], point[None])
        p1, _ = pixel_from_world_point(cam, exposure_poses[1], point[None])
        m = (p1 - p0)[0]
        return m if np.all(np.isfinite(m)) else None

    for s in scene.signs:
        view = cam_pos - s.center_m
        dist = float(np.linalg.norm(view))
        if float(s.normal @ view) <= 0.05 * dist:
            continue  # seen from behind or edge-on
        cam_disc = _cam_points(world_T_cam, s.disc_m)
        if np.any(cam_disc[:, 2] < 0.3):
            continue
        rn = np.hypot(cam_disc[:, 0], cam_disc[:, 1]) / cam_disc[:, 2]
        if np.any(rn > 1.3):
            continue
        disc_px = pixel_from_cam_point(cam, cam_disc)  # every depth > 0.3 m: all finite
        lo, hi = disc_px.min(axis=0), disc_px.max(axis=0)
        if hi[0] < -0.5 or hi[1] < -0.5 or lo[0] > w - 0.5 or lo[1] > h - 0.5:
            continue
        names = list(s.keypoints_m)
        kp_px, _ = pixel_from_world_point(
            cam, world_T_cam, np.array([s.keypoints_m[k] for k in names])
        )
        center_px, _ = pixel_from_world_point(cam, world_T_cam, s.center_m[None])
        white_px = tuple(pixel_from_world_point(cam, world_T_cam, poly)[0] for poly in s.white_m)
        dirt_px = tuple(
            (pixel_from_world_point(cam, world_T_cam, poly)[0], v, o) for poly, v, o in s.dirt_m
        )
        occ_px = tuple(
            (pixel_from_world_point(cam, world_T_cam, poly)[0], v) for poly, v in s.occluders_m
        )
        motion = motion_of(s.center_m)
        projected.append(
            ProjectedSign(
                s.code,
                disc_px,
                white_px,
                dirt_px,
                occ_px,
                motion if motion is not None else np.zeros(2),
                s.shade,
            )
        )
        half = len(disc_px) // 2
        diameter = float(np.linalg.norm(disc_px[:half] - disc_px[half : 2 * half], axis=1).max())
        c = center_px[0]
        occluded = bool(occ_px) or any(
            _segment_distance(c, ln.points_px) < 0.5 * diameter + 0.5 * float(ln.widths_px.max())
            for ln in front
        )
        x0, y0 = max(lo[0], -0.5), max(lo[1], -0.5)
        x1, y1 = min(hi[0], w - 0.5), min(hi[1], h - 0.5)
        truths.append(
            SignTruth(
                code=s.code,
                bbox_px=(float(x0), float(y0), float(x1 - x0), float(y1 - y0)),
                center_px=(float(c[0]), float(c[1])),
                diameter_px=diameter,
                keypoints_px={
                    k: (float(p[0]), float(p[1])) for k, p in zip(names, kp_px, strict=True)
                },
                occluded=occluded,
                truncated=bool(lo[0] < -0.5 or lo[1] < -0.5 or hi[0] > w - 0.5 or hi[1] > h - 0.5),
                distance_m=dist,
            )
        )
    # Far signs first so nearer ones cover them.
    order = np.argsort([-t.distance_m for t in truths])
    projected = [projected[i] for i in order]
    image = compose_frame(
        scene.backdrop,
        cam.K,
        world_T_cam,
        projected,
        rng,
        lines_behind=behind,
        lines_front=front,
        background_motion_px=motion_of(scene.center_m),
        gain=gain,
        offset=offset,
        options=options,
        size=(w, h),
    )
    return image, truths


# --------------------------------------------------------------------------- time


def pose_at(traj_T: np.ndarray, stamps_s: np.ndarray, t: float) -> np.ndarray:
    """(4, 4) pose at time ``t`` interpolated (or extrapolated at the ends) from samples.

    Translation linearly, rotation along the geodesic (axis-angle of the relative rotation).
    """
    n = len(stamps_s)
    if n == 1:
        return traj_T[0].copy()
    i = int(np.clip(np.searchsorted(stamps_s, t) - 1, 0, n - 2))
    t0, t1 = stamps_s[i], stamps_s[i + 1]
    alpha = (t - t0) / (t1 - t0)
    A, B = traj_T[i], traj_T[i + 1]
    rel, _ = cv2.Rodrigues(A[:3, :3].T @ B[:3, :3])
    R, _ = cv2.Rodrigues(rel * alpha)
    out = np.eye(4)
    out[:3, :3] = A[:3, :3] @ R
    out[:3, 3] = A[:3, 3] * (1 - alpha) + B[:3, 3] * alpha
    return out


def lighting_at(t: float, seed: int) -> tuple[float, float]:
    """Global (gain, offset [DN]) at time ``t`` [s]: slow, smooth drifts (clouds, auto-exposure)."""
    r = np.random.default_rng([seed, 31337])
    ph = r.uniform(0, 2 * np.pi, 3)
    gain = (
        1.0
        + 0.12 * math.sin(2 * np.pi * t / 7.0 + ph[0])
        + 0.05 * math.sin(2 * np.pi * t / 2.3 + ph[1])
    )
    offset = 6.0 * math.sin(2 * np.pi * t / 5.0 + ph[2])
    return gain, offset


def stamp_ns_of(frame: int, fps: float) -> int:
    return int(round(frame * 1e9 / fps))


# --------------------------------------------------------------------------- frame output


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


class _WriterBase:
    path: Path

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    def close(self) -> Path:  # pragma: no cover - overridden
        raise NotImplementedError

    def abort(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError


class Mp4Writer(_WriterBase):
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


class PngWriter(_WriterBase):
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
        self._stamps: list[tuple[str, int]] = []

    def write(self, frame_index: int, stamp_ns: int, bgr: np.ndarray) -> None:
        target = self._tmp / f"{frame_index:06d}.png"
        if not cv2.imwrite(str(target), bgr):
            raise OutputError(f"{self.path}: could not write {target.name}")
        self._stamps.append((target.name, int(stamp_ns)))

    def close(self) -> Path:
        with open(self._tmp / "frames.csv", "w", encoding="utf-8") as f:
            f.write("filename,stamp_ns\n")
            f.writelines(f"{name},{stamp}\n" for name, stamp in self._stamps)
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
        from signpose.io.mcap import McapFrameWriter

        return McapFrameWriter(Path(out_dir) / "flight.mcap", camera, world_frame, world_T_cams)
    raise InputError(f"unknown format {fmt!r}; choose from {', '.join(FORMATS)}")


def boxes_line(frame: int, stamp_ns: int, truths: list[SignTruth]) -> str:
    """One ``boxes.jsonl`` line."""
    return json.dumps(
        {"frame": frame, "stamp_ns": stamp_ns, "signs": [t.to_json() for t in truths]},
        separators=(",", ":"),
    )


def read_boxes(path: str | Path) -> list[dict]:
    """Read ``boxes.jsonl``: one dict per frame (format in this module's docstring)."""
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise InputError(f"{p}: cannot read boxes file ({exc})") from None
    out = []
    for i, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            raise InputError(f"{p}: line {i}: not valid JSON") from None
    return out


# --------------------------------------------------------------------------- a flight


def simulate(
    sign_map: SignMap,
    out_dir: str | Path,
    settings: SimSettings = SimSettings(),
    progress: bool = True,
) -> SimResult:
    """Render a flight in front of ``sign_map`` and write it with its ground truth to ``out_dir``.

    Args:
        sign_map: the signs (and the site the pylon is built around).
        out_dir: output folder, created if missing.
        settings: what to simulate.
        progress: show a tqdm bar over frames.

    Returns:
        The paths written. Raises OutputError when ``out_dir`` is not writable.
    """
    settings.validate()
    out = ensure_dir(out_dir)
    camera = simulated_camera(settings)
    traj = make_trajectory(
        settings.trajectory,
        sign_map,
        n_frames=settings.frames,
        fps=settings.fps,
        distance_m=settings.distance_m,
        seed=settings.seed,
    )
    poses = traj.world_T_cam()
    stamps = traj.stamps_s
    scene = build_scene(
        sign_map,
        camera,
        settings.seed,
        dirt=settings.dirt,
        occlusion=settings.occlusion,
        background=settings.background,
    )
    options = settings.render_options()
    log.info(
        "simulating %d frames %dx%d (%s, seed %d) of %d signs into %s",
        settings.frames,
        settings.width,
        settings.height,
        settings.trajectory,
        settings.seed,
        len(sign_map.signs),
        out,
    )
    half_exposure = 0.5 * settings.exposure_fraction / settings.fps
    lines: list[str] = []
    writer = make_frame_writer(
        settings.format, out, settings.fps, camera, poses, world_frame=sign_map.frame
    )
    with writer:
        for i in tqdm(range(len(traj)), desc="simulate", unit="frame", disable=not progress):
            t = float(stamps[i])
            exposure = None
            if settings.blur and half_exposure > 0 and len(traj) > 1:
                exposure = (
                    pose_at(poses, stamps, t - half_exposure),
                    pose_at(poses, stamps, t + half_exposure),
                )
            gain, offset = lighting_at(t, settings.seed)
            rng = np.random.default_rng([settings.seed, i])
            image, truths = render_frame(
                scene,
                poses[i],
                rng,
                options=options,
                exposure_poses=exposure,
                gain=gain,
                offset=offset,
            )
            stamp_ns = stamp_ns_of(i, settings.fps)
            writer.write(i, stamp_ns, image)
            lines.append(boxes_line(i, stamp_ns, truths))
        frames_path = writer.path
    boxes_path = out / "boxes.jsonl"
    with atomic_write(boxes_path) as f:
        f.write("\n".join(lines) + "\n")
    camera_path = out / "camera.yaml"
    write_camera_info(camera_path, camera)
    gt_path = out / "groundtruth.tum"
    write_tum(gt_path, traj)
    map_path = out / "map.yaml"
    write_map(map_path, sign_map)
    return SimResult(
        out_dir=out,
        frames_path=frames_path,
        camera_path=camera_path,
        groundtruth_path=gt_path,
        boxes_path=boxes_path,
        map_path=map_path,
        n_frames=len(traj),
        camera=camera,
        trajectory=traj,
    )
