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
(``sim.trajectories.make_trajectory``) and its camera, without lens distortion.

Writes ``video.mp4``, ``camera.yaml`` (pinhole) and ``groundtruth.tum`` into OUT:

    .venv/bin/python scripts/independent_flight.py OUT --frames 600 [--width 1920 --height 1080]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from independent_scene import SUPERSAMPLE, _bar_polygon, _face, _motion_kernel, _photo
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


@dataclass(frozen=True)
class Bar:
    """A cylinder in the world frame, ``p0_m`` to ``p1_m`` [m], ``radius_m``, gray ``shade``."""

    p0_m: np.ndarray
    p1_m: np.ndarray
    radius_m: float
    shade: float


def _panorama(height: int) -> np.ndarray:
    """The photographs side by side at ``height`` rows (float32 gray)."""
    tiles = []
    for name in PHOTOS:
        img = _photo(name)
        scale = height / img.shape[0]
        tiles.append(cv2.resize(img, (int(img.shape[1] * scale), height)))
    return np.hstack(tiles)


def _bars(sign_map: SignMap, rng: np.random.Generator) -> list[Bar]:
    """Members crossing in front of some signs (``MEMBER_SHARE``), and ``CONDUCTORS``."""
    bars = []
    for sign in sign_map.signs:
        if not sign.oriented or rng.random() > MEMBER_SHARE:
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


def _draw_sign(canvas: np.ndarray, sign: MapSign, k, cam_T_world, gain: float) -> None:
    roi = _sign_roi(sign, k, cam_T_world, canvas.shape[1], canvas.shape[0])
    if roi is None:
        return
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


def _draw_bar(canvas: np.ndarray, bar: Bar, k, cam_T_world) -> None:
    ends = np.stack([bar.p0_m, bar.p1_m]) @ cam_T_world[:3, :3].T + cam_T_world[:3, 3]
    z_min = 0.3
    if (ends[:, 2] < z_min).all():
        return
    for i in (0, 1):  # keep the segment in front of the camera
        a, b = ends[i], ends[1 - i]
        if a[2] < z_min:
            ends[i] = a + (z_min - a[2]) / (b[2] - a[2]) * (b - a)
    poly = _bar_polygon(k, ends[0], ends[1], bar.radius_m)
    if not np.isfinite(poly).all() or np.abs(poly).max() > 1e6:
        return
    mask = np.zeros(canvas.shape, np.uint8)
    cv2.fillConvexPoly(mask, np.round(poly * 16).astype(np.int32), 255, cv2.LINE_AA, 4)
    cover = mask.astype(np.float32) / 255.0
    canvas *= 1 - cover
    canvas += cover * bar.shade


def render_frame(
    i: int, world_T_cam: np.ndarray, k: np.ndarray, scene: dict, size: tuple[int, int]
) -> np.ndarray:
    """Frame ``i`` as (H, W, 3) BGR uint8."""
    w, h = size
    pano = scene["panorama"]
    x = int(i * 2) % max(1, pano.shape[1] - w)
    canvas = pano[:h, x : x + w].copy()
    gain = 1.0 + 0.25 * math.sin(i / 40.0)
    cam_T_world = np.linalg.inv(world_T_cam)
    for sign in scene["signs"]:
        _draw_sign(canvas, sign, k, cam_T_world, gain)
    for bar in scene["bars"]:
        _draw_bar(canvas, bar, k, cam_T_world)
    if i % BLUR_EVERY < 3:
        canvas = cv2.filter2D(canvas, -1, _motion_kernel(5.0, 0.3 * i))
    canvas = cv2.GaussianBlur(canvas, (0, 0), 0.6) + scene["noise"][i % NOISE_BANK]
    gray = np.clip(np.round(canvas), 0, 255).astype(np.uint8)
    return cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)


def write_flight(out_dir: Path, frames: int, width: int, height: int, seed: int = 0) -> Path:
    """Render the flight into ``out_dir``; returns the video's path."""
    out = ensure_dir(out_dir)
    sign_map = load_map(bundled_map_path())
    settings = SimSettings(frames=frames, width=width, height=height, seed=seed)
    camera = replace(simulated_camera(settings), dist=np.zeros(5), name="independent")
    traj = make_trajectory(settings.trajectory, sign_map, n_frames=frames, fps=settings.fps)
    rng = np.random.default_rng(seed)
    scene = {
        "panorama": _panorama(height),
        "signs": [s for s in sign_map.signs if s.oriented],
        "bars": _bars(sign_map, rng),
        "noise": [
            rng.normal(0, NOISE_SIGMA, (height, width)).astype(np.float32)
            for _ in range(NOISE_BANK)
        ],
    }
    video = out / "video.mp4"
    with atomic_path(video) as tmp:
        writer = cv2.VideoWriter(
            str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), settings.fps, (width, height)
        )
        try:
            for i, world_T_cam in enumerate(traj.world_T_cam()):
                writer.write(render_frame(i, world_T_cam, camera.K, scene, (width, height)))
        finally:
            writer.release()
    write_camera_info(out / "camera.yaml", camera)
    write_tum(out / "groundtruth.tum", traj, ("scripts/independent_flight.py",))
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out", type=Path, help="output folder")
    ap.add_argument("--frames", type=int, default=600)
    ap.add_argument("--width", type=int, default=1920)
    ap.add_argument("--height", type=int, default=1080)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    print(write_flight(args.out, args.frames, args.width, args.height, args.seed))
    return 0


if __name__ == "__main__":
    sys.exit(main())
