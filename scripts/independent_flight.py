#!/usr/bin/env python
"""A flight video drawn without signpose's renderer: the harder scene of the throughput benchmarks.

Why: ``signpose.sim`` draws the frames the frontend was tuned on; a speed measured
only there says little about frames it did not shape. This script draws each
frame its own way, as ``scripts/independent_scene.py`` draws its crops (and with
its helpers): a real photograph behind the pylon (scikit-image's data images,
panned over the flight), each sign of the map the PNG ``signpose sign`` writes
warped through the camera (``cv2.warpPerspective`` of the face and of its disc's
coverage), pylon members and conductors as 3D cylinders between the camera and
the signs (some crossing signs), gain drift, motion blur bursts and noise, then
an mp4v video. Only the geometry is the simulator's: its trajectory
(``sim.trajectories.make_trajectory``) and its camera's intrinsics.

Options (``FlightOptions``; the defaults draw the benchmarks' flight, byte for
byte as before) make it a flight for an end-to-end evaluation
(``scripts/eval_flight.py``):

* ``--distortion k1 k2 p1 p2``: a real lens (OpenCV's plumb_bob model). The
  scene is drawn through a pinhole on a larger canvas, then every raw pixel
  samples it (``cv2.remap``) where this script's own inverse of the lens model
  (Newton on the polynomial written out here, not OpenCV's) puts it; blur and
  noise are added after the lens, as a sensor would. camera.yaml carries the
  distortion.
* ``--lens equidistant --distortion k1 k2 k3 k4 --hfov DEG``: a wide-angle /
  fisheye lens instead (the equidistant or Kannala-Brandt model of Kalibr's and
  ROS's ``equidistant`` files: a ray at ``theta`` from the axis lands at
  ``r = f theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``), its
  focal set so that the principal row spans DEG; drawn as above, with this
  script's own inverse (Newton on theta_d(theta)), not ``cv2.fisheye``, and
  camera.yaml a ROS camera_info with ``distortion_model: equidistant``.
* ``--jpeg LO HI``: each frame JPEG-encoded at a quality drawn in [LO, HI]
  before the video.
* ``--vibration DEG``: high-frequency rotation jitter of the camera (6-14 Hz
  sinusoids, DEG RMS per axis); groundtruth.tum follows it.
* ``--pan DEG``: a slow yaw (and pitch) pan that sweeps the signs to the
  image's edges, where the lens bends most; ``--distance M`` from the signs.
* ``--members SHARE``: share of the signs with a member crossing in front.
* ``--map MAP``: the signs drawn (default: the bundled map).
* ``--trajectory NAME``, ``--speed M/S``, ``--wobble-seed N``: the flight path.
* ``--truth``: also ``truth.jsonl``, per frame every sign drawn (code, centre,
  keypoints and box in raw pixels through the lens, diameter, share of its disc that a
  member or conductor hides) and the frame's conditions (JPEG quality, blur
  burst, gain).

Writes ``video.mp4``, ``camera.yaml`` and ``groundtruth.tum`` into OUT:

    .venv/bin/python scripts/independent_flight.py OUT --frames 600 [--width 1920 --height 1080]
        [--distortion -0.3 0.1 0.0005 -0.0003] [--jpeg 70 90] [--vibration 0.3] [--truth]
        [--lens equidistant --distortion -0.006 0.016 -0.024 0.0155 --hfov 120]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from independent_scene import SUPERSAMPLE, _bar_polygon, _face, _motion_kernel, _photo
from signpose.estimator.camera import EQUIDISTANT, PLUMB_BOB, CameraModel
from signpose.estimator.trajectory import Trajectory
from signpose.maps.loader import MapSign, SignMap, bundled_map_path, load_map

from signpose.core.fileio import atomic_path, atomic_write, ensure_dir
from signpose.io.camera_file import write_camera_info
from signpose.io.tum import write_tum
from signpose.sim.flight import SimSettings, simulated_camera
from signpose.sim.trajectories import make_trajectory

PHOTOS = ("brick", "coffee", "astronaut", "gravel", "rocket")
TEXTURE_PX = 256
BLACK, WHITE = 28.0, 222.0  # printed face levels [gray]
MEMBER_RADIUS_M = 0.07  # pylon angle members in front of the signs
MEMBER_SHARE = 0.35  # of the signs with a member crossing in front
CONDUCTORS = 1  # across the whole view, in front of the pylon
CONDUCTOR_RADIUS_M = 0.02
NOISE_SIGMA = 2.0
NOISE_BANK = 6  # noise images cycled over the frames
BLUR_EVERY = 45  # frames between motion blur bursts (3 frames each)
RIM_POINTS = 48  # points on a sign's rim projected for its box in truth.jsonl
VIBRATION_HZ = (6.0, 14.0)  # frequency range of the camera's rotation jitter
PAN_PERIOD_S = (8.0, 5.3)  # periods of the slow yaw and pitch pan
LENS_NEWTON_STEPS = 30
LENSES = (PLUMB_BOB, EQUIDISTANT)
MAX_FISHEYE_THETA = math.radians(85.0)  # rays drawn through the pinhole canvas


@dataclass(frozen=True)
class FlightOptions:
    """What a flight shows beyond the benchmarks' defaults.

    Attributes:
        seed: seeds the members, the noise, the JPEG qualities and the jitter.
        dist: plumb_bob (k1, k2, p1, p2[, k3]) or equidistant (k1, k2, k3, k4);
            () = the ideal pinhole.
        lens: the model of ``dist``, ``"plumb_bob"`` or ``"equidistant"``.
        hfov_deg: the angle the principal row spans [deg] through the lens, which
            sets the focal length (plumb_bob with p1, p2: to a few tenths of a
            degree); None = the simulator's camera (``SimSettings.hfov_deg``).
        jpeg: (lowest, highest) JPEG quality per frame, or None (no JPEG).
        vibration_deg: RMS rotation jitter per camera axis [deg] (0 = none).
        pan_deg: amplitude of a slow yaw pan (pitch: 0.45 of it) that sweeps
            the signs toward the image's edges, where the lens bends most.
        distance_m: nominal distance from the signs [m].
        member_share: share of the signs with a member crossing in front.
        map_path: the map drawn; None = the bundled one.
        trajectory: one of ``signpose.sim.trajectories.TRAJECTORIES``.
        speed_mps: cruise speed [m/s]; None = the whole path once (the old timing).
        wobble_seed: seeds the trajectory's wobble.
        truth: also write ``truth.jsonl``.
    """

    seed: int = 0
    dist: tuple[float, ...] = ()
    lens: str = PLUMB_BOB
    hfov_deg: float | None = None
    jpeg: tuple[int, int] | None = None
    vibration_deg: float = 0.0
    pan_deg: float = 0.0
    distance_m: float = SimSettings().distance_m
    member_share: float = MEMBER_SHARE
    map_path: Path | None = None
    trajectory: str = field(default=SimSettings().trajectory)
    speed_mps: float | None = None
    wobble_seed: int = 0
    truth: bool = False


@dataclass(frozen=True)
class Bar:
    """A cylinder in the world frame, ``p0_m`` to ``p1_m`` [m], ``radius_m``, gray ``shade``."""

    p0_m: np.ndarray
    p1_m: np.ndarray
    radius_m: float
    shade: float


@dataclass(frozen=True)
class Lens:
    """How a pinhole canvas becomes the raw image.

    Attributes:
        canvas_K: (3, 3) intrinsics of the pinhole canvas (the camera's K, shifted).
        canvas_size: (width, height) of the canvas [px].
        map_x, map_y: (H, W) float32 canvas coordinates each raw pixel samples.
    """

    canvas_K: np.ndarray
    canvas_size: tuple[int, int]
    map_x: np.ndarray
    map_y: np.ndarray


# --------------------------------------------------------------------------- the lens


def _coefficients(dist) -> tuple[float, float, float, float, float]:
    d = [float(x) for x in dist] + [0.0] * 5
    return d[0], d[1], d[2], d[3], d[4]


def distort_normalized(xy: np.ndarray, dist) -> np.ndarray:
    """plumb_bob: (N, 2) ideal normalised image points to distorted ones (OpenCV's convention)."""
    k1, k2, p1, p2, k3 = _coefficients(dist)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def _distortion_jacobian(xy: np.ndarray, dist) -> np.ndarray:
    """(N, 2, 2) d distorted / d ideal of ``distort_normalized``."""
    k1, k2, p1, p2, k3 = _coefficients(dist)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d_radial = 2 * (k1 + r2 * (2 * k2 + 3 * k3 * r2))  # d radial / d r2, times 2
    j = np.empty((len(xy), 2, 2))
    j[:, 0, 0] = radial + x * x * d_radial + 2 * p1 * y + 6 * p2 * x
    j[:, 0, 1] = x * y * d_radial + 2 * p1 * x + 2 * p2 * y
    j[:, 1, 0] = x * y * d_radial + 2 * p1 * x + 2 * p2 * y
    j[:, 1, 1] = radial + y * y * d_radial + 6 * p1 * y + 2 * p2 * x
    return j


def undistort_normalized(xy_d: np.ndarray, dist) -> np.ndarray:
    """Inverse of ``distort_normalized`` by Newton steps; raises where the lens folds over."""
    xy = np.array(xy_d, dtype=float).reshape(-1, 2)
    for _ in range(LENS_NEWTON_STEPS):
        step = np.linalg.solve(
            _distortion_jacobian(xy, dist), (distort_normalized(xy, dist) - xy_d)[..., None]
        )
        xy -= step[..., 0]
    det = np.linalg.det(_distortion_jacobian(xy, dist))
    worst = float(np.abs(distort_normalized(xy, dist) - xy_d).max(initial=0.0))
    if worst > 1e-9 or (det <= 0).any():
        raise ValueError(f"lens {tuple(dist)} is not invertible over the image (residual {worst})")
    return xy


def _equidistant_coefficients(dist) -> np.ndarray:
    d = [float(x) for x in dist]
    if len(d) != 4:
        raise ValueError(f"an equidistant lens takes 4 coefficients k1..k4, not {len(d)}")
    return np.array(d)


def theta_d(theta: np.ndarray, dist) -> np.ndarray:
    """equidistant: a ray's angle from the axis [rad] to its distorted radius (f = 1)."""
    k1, k2, k3, k4 = _equidistant_coefficients(dist)
    t2 = np.square(theta)
    return theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))


def _theta_d_slope(theta: np.ndarray, dist) -> np.ndarray:
    k1, k2, k3, k4 = _equidistant_coefficients(dist)
    t2 = np.square(theta)
    return 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))


def theta_from_theta_d(r_d: np.ndarray, dist) -> np.ndarray:
    """Inverse of ``theta_d`` by Newton steps; raises where it folds or passes 85 deg."""
    r_d = np.asarray(r_d, dtype=float)
    theta = r_d.copy()
    for _ in range(LENS_NEWTON_STEPS):
        theta -= (theta_d(theta, dist) - r_d) / _theta_d_slope(theta, dist)
        theta = np.clip(theta, 0.0, math.pi)
    worst = float(np.abs(theta_d(theta, dist) - r_d).max(initial=0.0))
    if worst > 1e-12 or (_theta_d_slope(theta, dist) <= 0).any():
        raise ValueError(f"lens {tuple(dist)} is not invertible over the image (residual {worst})")
    if (theta > MAX_FISHEYE_THETA).any():
        raise ValueError(f"lens {tuple(dist)} sees rays beyond 85 deg, which no canvas holds")
    return theta


def distort_equidistant(xy: np.ndarray, dist) -> np.ndarray:
    """equidistant: (N, 2) ideal normalised points (x / z, y / z) to distorted ones."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    r = np.hypot(xy[:, 0], xy[:, 1])
    theta = np.arctan(r)
    scale = np.where(r > 1e-12, theta_d(theta, dist) / np.maximum(r, 1e-300), 1.0)
    return xy * scale[:, None]


def undistort_equidistant(xy_d: np.ndarray, dist) -> np.ndarray:
    """Inverse of ``distort_equidistant`` (a ray's angle by ``theta_from_theta_d``)."""
    xy_d = np.asarray(xy_d, dtype=float).reshape(-1, 2)
    r_d = np.hypot(xy_d[:, 0], xy_d[:, 1])
    r = np.tan(theta_from_theta_d(r_d, dist))
    scale = np.where(r_d > 1e-12, r / np.maximum(r_d, 1e-300), 1.0)
    return xy_d * scale[:, None]


def _distort(xy: np.ndarray, dist, lens: str) -> np.ndarray:
    return distort_equidistant(xy, dist) if lens == EQUIDISTANT else distort_normalized(xy, dist)


def _undistort(xy: np.ndarray, dist, lens: str) -> np.ndarray:
    if lens == EQUIDISTANT:
        return undistort_equidistant(xy, dist)
    return undistort_normalized(xy, dist)


def raw_from_pinhole_px(k: np.ndarray, dist, uv: np.ndarray, lens: str = PLUMB_BOB) -> np.ndarray:
    """(N, 2) pinhole pixels of intrinsics ``k`` to raw pixels through the lens."""
    xy = (np.asarray(uv, float).reshape(-1, 2) - k[:2, 2]) / [k[0, 0], k[1, 1]]
    return _distort(xy, dist, lens) * [k[0, 0], k[1, 1]] + k[:2, 2]


def pinhole_from_raw_px(k: np.ndarray, dist, uv: np.ndarray, lens: str = PLUMB_BOB) -> np.ndarray:
    """(N, 2) raw pixels to the pinhole pixels of intrinsics ``k`` (this script's inverse)."""
    xy = (np.asarray(uv, float).reshape(-1, 2) - k[:2, 2]) / [k[0, 0], k[1, 1]]
    return _undistort(xy, dist, lens) * [k[0, 0], k[1, 1]] + k[:2, 2]


def fisheye_focal_px(width: int, hfov_deg: float, dist) -> float:
    """The focal [px] at which an equidistant lens's principal row spans ``hfov_deg``:
    the centres of its first and last pixels see rays at +-hfov / 2."""
    return ((width - 1) / 2.0) / float(theta_d(np.radians(hfov_deg) / 2.0, dist))


def make_lens(
    k: np.ndarray, dist, width: int, height: int, margin_px: int = 4, lens: str = PLUMB_BOB
) -> Lens:
    """The canvas a raw image of ``width`` x ``height`` through the lens needs, and its map."""
    vv, uu = np.mgrid[0:height, 0:width]
    raw = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)
    ideal = pinhole_from_raw_px(k, dist, raw, lens)
    x0, y0 = np.floor(ideal.min(axis=0)).astype(int) - margin_px
    x1, y1 = np.ceil(ideal.max(axis=0)).astype(int) + margin_px
    canvas_k = np.array(k, dtype=float)
    canvas_k[0, 2] -= x0
    canvas_k[1, 2] -= y0
    at = (ideal - [x0, y0]).astype(np.float32)
    return Lens(
        canvas_k,
        (int(x1 - x0 + 1), int(y1 - y0 + 1)),
        at[:, 0].reshape(height, width).copy(),
        at[:, 1].reshape(height, width).copy(),
    )


# --------------------------------------------------------------------------- the scene


def _panorama(height: int) -> np.ndarray:
    """The photographs side by side at ``height`` rows (float32 gray)."""
    tiles = []
    for name in PHOTOS:
        img = _photo(name)
        scale = height / img.shape[0]
        tiles.append(cv2.resize(img, (int(img.shape[1] * scale), height)))
    return np.hstack(tiles)


def _bars(sign_map: SignMap, rng: np.random.Generator, share: float = MEMBER_SHARE) -> list[Bar]:
    """Members crossing in front of some signs (``share``), and ``CONDUCTORS``."""
    bars = []
    for sign in sign_map.signs:
        if not sign.oriented or rng.random() > share:
            continue
        r = sign.world_R_sign()
        a = rng.uniform(0, math.pi)
        d = math.cos(a) * r[:, 0] + math.sin(a) * r[:, 1]
        offset = rng.uniform(-0.35, 0.35) * sign.diameter_m
        c = sign.center_m + r[:, 2] * rng.uniform(0.3, 1.0) + offset * np.cross(r[:, 2], d)
        bars.append(Bar(c - 4 * d, c + 4 * d, MEMBER_RADIUS_M, rng.uniform(40, 110)))
    center = np.mean([s.center_m for s in sign_map.signs], axis=0)
    normal = np.mean([s.normal for s in sign_map.signs if s.oriented], axis=0)
    normal /= np.linalg.norm(normal)
    side = np.cross(normal, [0.0, 0.0, 1.0])
    side /= np.linalg.norm(side)
    for k in range(CONDUCTORS):
        c = center + normal * 2.0 + np.array([0, 0, 1.5 * k - 0.5])
        bars.append(Bar(c - 40 * side, c + 40 * side + [0, 0, 1.0], CONDUCTOR_RADIUS_M, 35.0))
    return bars


def _sign_roi(sign: MapSign, k: np.ndarray, cam_T_world: np.ndarray, w: int, h: int):
    """(img_H_tex, x0, y0, x1, y1) of a sign in view, or None."""
    r_cw, t_cw = cam_T_world[:3, :3], cam_T_world[:3, 3]
    r_ws = sign.world_R_sign()
    rad = sign.diameter_m / 2
    corners = np.array([[-rad, -rad], [rad, -rad], [rad, rad], [-rad, rad]])
    cam = (sign.center_m + corners @ r_ws[:, :2].T) @ r_cw.T + t_cw
    if (cam[:, 2] < 0.5).any() or (r_cw @ r_ws[:, 2]) @ (r_cw @ sign.center_m + t_cw) > 0:
        return None  # behind the camera, or seen from the back
    uv = (cam @ k.T)[:, :2] / cam[:, 2:]
    x0, y0 = np.floor(uv.min(axis=0)).astype(int) - 2
    x1, y1 = np.ceil(uv.max(axis=0)).astype(int) + 2
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w), min(y1, h)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return None
    scale = TEXTURE_PX / sign.diameter_m
    sign_from_tex = np.array(
        [[1 / scale, 0, 0.5 / scale - rad], [0, -1 / scale, rad - 0.5 / scale], [0, 0, 1]]
    )
    img_from_sign = k @ np.c_[r_cw @ r_ws[:, :2], r_cw @ sign.center_m + t_cw]
    return img_from_sign @ sign_from_tex, x0, y0, x1, y1


def _draw_sign(canvas: np.ndarray, sign: MapSign, k, cam_T_world, gain: float):
    """Draw the sign; returns (x0, y0, its disc's coverage in its box) or None when not drawn."""
    roi = _sign_roi(sign, k, cam_T_world, canvas.shape[1], canvas.shape[0])
    if roi is None:
        return None
    img_h_tex, x0, y0, x1, y1 = roi
    tex, alpha = _face(sign.code, TEXTURE_PX)
    # Drawn at SUPERSAMPLE x the resolution, then area-averaged down (pixel centres at integers).
    s = SUPERSAMPLE
    hi = np.array([[s, 0, (s - 1) / 2], [0, s, (s - 1) / 2], [0, 0, 1]])
    shift = hi @ np.array([[1.0, 0, -x0], [0, 1.0, -y0], [0, 0, 1]]) @ img_h_tex
    size = (x1 - x0, y1 - y0)
    big = (size[0] * s, size[1] * s)
    face = cv2.warpPerspective(tex, shift, big, flags=cv2.INTER_LINEAR)
    cover = cv2.warpPerspective(alpha, shift, big, flags=cv2.INTER_LINEAR)
    face = cv2.resize(face, size, interpolation=cv2.INTER_AREA)
    cover = cv2.resize(cover, size, interpolation=cv2.INTER_AREA)
    face = gain * (BLACK + (WHITE - BLACK) * face)
    patch = canvas[y0:y1, x0:x1]
    patch[:] = patch * (1 - cover) + face * cover
    return x0, y0, cover


def _draw_bar(canvas: np.ndarray, bar: Bar, k, cam_T_world) -> np.ndarray | None:
    """Draw the cylinder; returns its coverage of the canvas (None when out of view)."""
    ends = np.stack([bar.p0_m, bar.p1_m]) @ cam_T_world[:3, :3].T + cam_T_world[:3, 3]
    z_min = 0.3
    if (ends[:, 2] < z_min).all():
        return None
    for i in (0, 1):  # keep the segment in front of the camera
        a, b = ends[i], ends[1 - i]
        if a[2] < z_min:
            ends[i] = a + (z_min - a[2]) / (b[2] - a[2]) * (b - a)
    poly = _bar_polygon(k, ends[0], ends[1], bar.radius_m)
    if not np.isfinite(poly).all() or np.abs(poly).max() > 1e6:
        return None
    mask = np.zeros(canvas.shape, np.uint8)
    cv2.fillConvexPoly(mask, np.round(poly * 16).astype(np.int32), 255, cv2.LINE_AA, 4)
    cover = mask.astype(np.float32) / 255.0
    canvas *= 1 - cover
    canvas += cover * bar.shade
    return cover


def _gain(i: int) -> float:
    return 1.0 + 0.25 * math.sin(i / 40.0)


def _draw_scene(i: int, world_T_cam: np.ndarray, k, scene: dict, size: tuple[int, int]):
    """(canvas float32 (H, W), {code: share of its disc hidden}) of frame ``i``, before optics."""
    w, h = size
    pano = scene["panorama"]
    x = int(i * 2) % max(1, pano.shape[1] - w)
    canvas = pano[:h, x : x + w].copy()
    cam_T_world = np.linalg.inv(world_T_cam)
    drawn = {}
    for sign in scene["signs"]:
        placed = _draw_sign(canvas, sign, k, cam_T_world, _gain(i))
        if placed is not None:
            drawn[sign.code] = placed
    hidden = np.zeros_like(canvas) if scene.get("truth") else None
    for bar in scene["bars"]:
        cover = _draw_bar(canvas, bar, k, cam_T_world)
        if cover is not None and hidden is not None:
            np.maximum(hidden, cover, out=hidden)
    shares = {}
    for code, (x0, y0, disc) in drawn.items():
        if hidden is not None:
            under = hidden[y0 : y0 + disc.shape[0], x0 : x0 + disc.shape[1]]
            shares[code] = float((disc * under).sum() / max(disc.sum(), 1e-9))
    return canvas, shares


def _optics(canvas: np.ndarray, i: int, scene: dict) -> np.ndarray:
    """Blur bursts, the optics' blur and the sensor's noise: (H, W) gray uint8."""
    if i % BLUR_EVERY < 3:
        canvas = cv2.filter2D(canvas, -1, _motion_kernel(5.0, 0.3 * i))
    canvas = cv2.GaussianBlur(canvas, (0, 0), 0.6) + scene["noise"][i % NOISE_BANK]
    return np.clip(np.round(canvas), 0, 255).astype(np.uint8)


def _frame_gray(i: int, world_T_cam: np.ndarray, k, scene: dict, size: tuple[int, int]):
    """(frame (H, W) gray uint8, {code: hidden share}) through the lens when the scene has one."""
    lens: Lens | None = scene.get("lens")
    if lens is None:
        canvas, shares = _draw_scene(i, world_T_cam, k, scene, size)
    else:
        canvas, shares = _draw_scene(i, world_T_cam, lens.canvas_K, scene, lens.canvas_size)
        canvas = cv2.remap(canvas, lens.map_x, lens.map_y, cv2.INTER_LINEAR, cv2.BORDER_REPLICATE)
    return _optics(canvas, i, scene), shares


def render_frame(
    i: int, world_T_cam: np.ndarray, k: np.ndarray, scene: dict, size: tuple[int, int]
) -> np.ndarray:
    """Frame ``i`` as (H, W, 3) BGR uint8."""
    gray, _ = _frame_gray(i, world_T_cam, k, scene, size)
    return cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)


# --------------------------------------------------------------------------- truth


def signs_in_view(
    signs,
    k: np.ndarray,
    dist,
    world_T_cam: np.ndarray,
    size: tuple[int, int],
    lens: str = PLUMB_BOB,
) -> list[dict]:
    """Every sign facing the camera in front of it: code, raw centre, box, diameter and
    every keypoint of the map's sign [px].

    ``inside``: the whole disc lies in the image. Pixels through this script's own
    lens model (``raw_from_pinhole_px``).
    """
    cam_T_world = np.linalg.inv(world_T_cam)
    r_cw, t_cw = cam_T_world[:3, :3], cam_T_world[:3, 3]
    a = np.linspace(0, 2 * np.pi, RIM_POINTS, endpoint=False)
    out = []
    for s in signs:
        r_ws = s.world_R_sign()
        c_cam = r_cw @ s.center_m + t_cw
        if (r_cw @ r_ws[:, 2]) @ c_cam > 0:
            continue  # seen from the back
        rim = s.center_m + (s.diameter_m / 2) * np.outer(np.cos(a), r_ws[:, 0])
        rim = rim + (s.diameter_m / 2) * np.outer(np.sin(a), r_ws[:, 1])
        names, points = zip(*s.keypoints_world().items(), strict=True)
        cam = np.vstack([c_cam, rim @ r_cw.T + t_cw, np.array(points) @ r_cw.T + t_cw])
        if (cam[:, 2] < 0.5).any():
            continue
        px = raw_from_pinhole_px(k, dist, (cam @ k.T)[:, :2] / cam[:, 2:], lens)
        lo, hi = px[1 : 1 + RIM_POINTS].min(axis=0), px[1 : 1 + RIM_POINTS].max(axis=0)
        keypoints = {
            n: [round(float(v), 4) for v in p]
            for n, p in zip(names, px[1 + RIM_POINTS :], strict=True)
        }
        inside = bool((lo >= 0).all() and hi[0] <= size[0] - 1 and hi[1] <= size[1] - 1)
        out.append(
            {
                "code": s.code,
                "center_px": [round(float(v), 4) for v in px[0]],
                "box_px": [round(float(v), 2) for v in (*lo, *hi)],
                "diameter_px": round(float((hi - lo).max()), 2),
                "inside": inside,
                "keypoints_px": keypoints,
            }
        )
    return out


def _truth_line(i: int, signs: list[dict], shares: dict, quality: int | None) -> str:
    for s in signs:
        s["hidden"] = round(shares.get(s["code"], 0.0), 4)
    conditions = {"jpeg_quality": quality, "blur": i % BLUR_EVERY < 3, "gain": _gain(i)}
    return json.dumps({"frame": i, "conditions": conditions, "signs": signs}) + "\n"


# --------------------------------------------------------------------------- the flight


def _vibrated(traj: Trajectory, deg: float, rng: np.random.Generator) -> Trajectory:
    """The trajectory with a rotation jitter of ``deg`` RMS per camera axis (about its centre)."""
    if deg <= 0:
        return traj
    freqs = rng.uniform(*VIBRATION_HZ, size=(3, 3))
    phases = rng.uniform(0, 2 * np.pi, size=(3, 3))
    poses = traj.world_T_cam()
    for i, t in enumerate(traj.stamps_s):
        # Three unit sinusoids per axis sum to an RMS of sqrt(3 / 2).
        rotvec = np.radians(deg) * np.sin(2 * np.pi * freqs * t + phases).sum(axis=1) / 1.2247
        poses[i, :3, :3] = poses[i, :3, :3] @ cv2.Rodrigues(rotvec)[0]
    return Trajectory.from_matrices(traj.stamps_s, poses)


def _panned(traj: Trajectory, deg: float) -> Trajectory:
    """The trajectory with a slow pan: yaw about world up, pitch about the camera's x axis."""
    if deg <= 0:
        return traj
    poses = traj.world_T_cam()
    for i, t in enumerate(traj.stamps_s):
        yaw = math.radians(deg) * math.sin(2 * math.pi * t / PAN_PERIOD_S[0])
        pitch = 0.45 * math.radians(deg) * math.sin(2 * math.pi * t / PAN_PERIOD_S[1] + 1.0)
        r_yaw = cv2.Rodrigues(np.array([0.0, 0.0, yaw]))[0]
        r_pitch = cv2.Rodrigues(np.array([pitch, 0.0, 0.0]))[0]
        poses[i, :3, :3] = r_yaw @ poses[i, :3, :3] @ r_pitch
    return Trajectory.from_matrices(traj.stamps_s, poses)


def _jpeg(gray: np.ndarray, quality: int) -> np.ndarray:
    ok, buf = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise RuntimeError("JPEG encoding failed")
    return cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)


def _scene(sign_map: SignMap, o: FlightOptions, camera, size) -> dict:
    w, h = size
    rng = np.random.default_rng(o.seed)
    lens = make_lens(camera.K, o.dist, w, h, lens=o.lens) if any(o.dist) else None
    return {
        "panorama": _panorama(h if lens is None else max(h, lens.canvas_size[1])),
        "signs": [s for s in sign_map.signs if s.oriented],
        "bars": _bars(sign_map, rng, o.member_share),
        "noise": [rng.normal(0, NOISE_SIGMA, (h, w)).astype(np.float32) for _ in range(NOISE_BANK)],
        "lens": lens,
        "truth": o.truth,
    }


def flight_camera(o: FlightOptions, width: int, height: int) -> CameraModel:
    """The camera a flight is drawn through (camera.yaml): the simulator's intrinsics, or
    the focal ``o.hfov_deg`` asks for, with ``o``'s lens.

    Raises:
        ValueError: a lens model this script does not draw, or the wrong coefficients.
    """
    settings = SimSettings(width=width, height=height)
    camera = replace(simulated_camera(settings), dist=np.zeros(5), name="independent")
    if o.lens not in LENSES:
        raise ValueError(f"lens '{o.lens}' is not one of {', '.join(LENSES)}")
    if o.hfov_deg is not None:
        half = math.radians(o.hfov_deg) / 2.0
        if o.lens == EQUIDISTANT:
            f = fisheye_focal_px(width, o.hfov_deg, o.dist)
        else:  # the ray at hfov / 2 lands on the last pixel (tangential terms: nearly)
            x_d = distort_normalized(np.array([[math.tan(half), 0.0]]), o.dist)[0, 0]
            f = ((width - 1) / 2.0) / float(x_d)
        camera.K[0, 0] = camera.K[1, 1] = f
    if o.lens == EQUIDISTANT:
        camera = replace(camera, dist=_equidistant_coefficients(o.dist), model=EQUIDISTANT)
    elif any(o.dist):
        camera = replace(camera, dist=np.array(_coefficients(o.dist)))
    return camera


def write_flight(
    out_dir: Path,
    frames: int,
    width: int,
    height: int,
    seed: int = 0,
    options: FlightOptions | None = None,
) -> Path:
    """Render the flight into ``out_dir``; returns the video's path.

    ``options`` (its ``seed`` replaced by ``seed``) says what the flight shows;
    None: the benchmarks' flight.
    """
    o = replace(options or FlightOptions(), seed=seed)
    out = ensure_dir(out_dir)
    sign_map = load_map(o.map_path or bundled_map_path())
    settings = SimSettings(frames=frames, width=width, height=height, seed=seed)
    camera = flight_camera(o, width, height)
    traj = make_trajectory(
        o.trajectory,
        sign_map,
        n_frames=frames,
        fps=settings.fps,
        distance_m=o.distance_m,
        seed=o.wobble_seed,
        speed_mps=o.speed_mps,
    )
    scene = _scene(sign_map, o, camera, (width, height))
    traj = _vibrated(_panned(traj, o.pan_deg), o.vibration_deg, np.random.default_rng(o.seed + 1))
    qualities = np.random.default_rng(o.seed + 2).integers(
        *(o.jpeg or (0, 1)), frames, endpoint=True
    )
    video, truth = out / "video.mp4", []
    with atomic_path(video) as tmp:
        writer = cv2.VideoWriter(
            str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), settings.fps, (width, height)
        )
        try:
            for i, world_T_cam in enumerate(traj.world_T_cam()):
                gray, shares = _frame_gray(i, world_T_cam, camera.K, scene, (width, height))
                q = int(qualities[i]) if o.jpeg else None
                if q is not None:
                    gray = _jpeg(gray, q)
                writer.write(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR))
                if o.truth:
                    seen = signs_in_view(
                        scene["signs"], camera.K, o.dist, world_T_cam, (width, height), o.lens
                    )
                    truth.append(_truth_line(i, seen, shares, q))
        finally:
            writer.release()
    write_camera_info(out / "camera.yaml", camera)
    write_tum(out / "groundtruth.tum", traj, ("scripts/independent_flight.py",))
    if o.truth:
        with atomic_write(out / "truth.jsonl") as f:
            f.writelines(truth)
    return video


def drawn_once(out_dir: Path, frames: int, width: int, height: int, stamp_name: str) -> Path:
    """The flight's video in ``out_dir``, drawn only when ``stamp_name`` there does not
    say it was drawn at this size (the benchmarks' cache); returns the video's path."""
    stamp = out_dir / stamp_name
    key = {"frames": frames, "width": width, "height": height}
    video = out_dir / "video.mp4"
    if not (stamp.is_file() and video.is_file() and json.loads(stamp.read_text()) == key):
        write_flight(out_dir, frames, width, height)
        with atomic_write(stamp) as f:
            json.dump(key, f)
    return video


def options_from_args(args: argparse.Namespace) -> FlightOptions:
    return FlightOptions(
        seed=args.seed,
        dist=tuple(args.distortion or ()),
        lens=args.lens,
        hfov_deg=args.hfov,
        jpeg=tuple(args.jpeg) if args.jpeg else None,
        vibration_deg=args.vibration,
        pan_deg=args.pan,
        distance_m=args.distance,
        member_share=args.members,
        map_path=args.map,
        trajectory=args.trajectory,
        speed_mps=args.speed,
        wobble_seed=args.wobble_seed,
        truth=args.truth,
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path, help="output folder")
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--distortion", type=float, nargs="+", metavar="K",
        help="plumb_bob: k1 k2 p1 p2 [k3]; equidistant: k1 k2 k3 k4",
    )  # fmt: skip
    ap.add_argument("--lens", choices=LENSES, default=PLUMB_BOB, help="the model of --distortion")
    ap.add_argument(
        "--hfov", type=float, default=None,
        help="angle the principal row spans [deg] (sets the focal; default: the simulator's)",
    )  # fmt: skip
    ap.add_argument("--jpeg", type=int, nargs=2, metavar=("LO", "HI"), help="JPEG quality range")
    ap.add_argument("--vibration", type=float, default=0.0, help="rotation jitter, deg RMS/axis")
    ap.add_argument("--pan", type=float, default=0.0, help="slow yaw pan amplitude [deg]")
    ap.add_argument("--distance", type=float, default=SimSettings().distance_m, help="[m]")
    ap.add_argument("--members", type=float, default=MEMBER_SHARE, help="share of signs crossed")
    ap.add_argument("--map", type=Path, default=None, help="map drawn (default: the bundled one)")
    ap.add_argument("--trajectory", default=SimSettings().trajectory)
    ap.add_argument("--speed", type=float, default=None, help="cruise speed [m/s]")
    ap.add_argument("--wobble-seed", type=int, default=0)
    ap.add_argument("--truth", action="store_true", help="also write truth.jsonl")
    args = ap.parse_args(argv)
    options = options_from_args(args)
    try:
        flight_camera(options, args.width, args.height)
    except ValueError as e:
        print(f"independent_flight: {e}", file=sys.stderr)
        return 2
    print(write_flight(args.out, args.frames, args.width, args.height, args.seed, options))
    return 0


if __name__ == "__main__":
    sys.exit(main())
