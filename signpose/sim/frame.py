"""One simulated frame: project the scene for a pose, draw it, and say what is where.

The 3D side of the renderer: every element of a ``Scene`` goes through the
camera model with its lens distortion (``estimator.camera``) into raw
pixels; ``signpose.sim.render`` draws the projected polygons. The truth of
each visible sign (``signpose.io.boxes.SignTruth``) is measured on the same
projection.

Poses are ``world_T_cam`` (OpenCV camera axes: x right, y down, z forward).
Pixels: u right, v down, pixel centres at integers.
"""

from __future__ import annotations

import numpy as np

from signpose.estimator.camera import CameraModel, pixel_from_cam_point, pixel_from_world_point
from signpose.io.boxes import SignTruth
from signpose.sim.pylon import Line3D
from signpose.sim.render import ProjectedLine, ProjectedSign, RenderOptions, compose_frame
from signpose.sim.scene import Scene, SignModel

MIN_DEPTH_M = 0.3  # nearer points are not projected
# Beyond ~1.3 (normalised radius) a barrel polynomial folds back; the image corner is ~0.66.
MAX_NORMALISED_RADIUS = 1.3
EDGE_ON = 0.05  # cosine below which a face is seen edge-on and skipped


def _cam_points(world_T_cam: np.ndarray, world_points: np.ndarray) -> np.ndarray:
    cam_T_world = np.linalg.inv(world_T_cam)
    return (
        np.asarray(world_points, float).reshape(-1, 3) @ cam_T_world[:3, :3].T + cam_T_world[:3, 3]
    )


def project_lines(
    camera: CameraModel, world_T_cam: np.ndarray, lines: tuple[Line3D, ...]
) -> list[ProjectedLine]:
    """Project polylines, cutting them where they leave the cone where the lens model is valid."""
    if not lines:
        return []
    f = camera.fx
    sizes = [len(ln.points_m) for ln in lines]
    cam = _cam_points(world_T_cam, np.concatenate([ln.points_m for ln in lines]))
    z = cam[:, 2]
    ok = z > MIN_DEPTH_M
    rn = np.full(len(cam), np.inf)
    rn[ok] = np.hypot(cam[ok, 0], cam[ok, 1]) / z[ok]
    ok &= rn < MAX_NORMALISED_RADIUS
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


def _motion_px(
    camera: CameraModel,
    exposure_poses: tuple[np.ndarray, np.ndarray] | None,
    point_m: np.ndarray,
) -> np.ndarray | None:
    """(2,) image motion [px] of world point ``point_m`` over the exposure, None if unknown."""
    if exposure_poses is None:
        return None
    p0, _ = pixel_from_world_point(camera, exposure_poses[0], point_m[None])
    p1, _ = pixel_from_world_point(camera, exposure_poses[1], point_m[None])
    m = (p1 - p0)[0]
    return m if np.all(np.isfinite(m)) else None


def _disc_in_view(camera: CameraModel, world_T_cam: np.ndarray, s: SignModel) -> np.ndarray | None:
    """(N, 2) projected disc outline [px] of a face seen from the front and in the image."""
    view = world_T_cam[:3, 3] - s.center_m
    if float(s.normal @ view) <= EDGE_ON * float(np.linalg.norm(view)):
        return None  # seen from behind or edge-on
    cam_disc = _cam_points(world_T_cam, s.disc_m)
    if np.any(cam_disc[:, 2] < MIN_DEPTH_M):
        return None
    rn = np.hypot(cam_disc[:, 0], cam_disc[:, 1]) / cam_disc[:, 2]
    if np.any(rn > MAX_NORMALISED_RADIUS):
        return None
    disc_px = pixel_from_cam_point(camera, cam_disc)  # every depth > 0.3 m: all finite
    lo, hi = disc_px.min(axis=0), disc_px.max(axis=0)
    w, h = camera.width, camera.height
    if hi[0] < -0.5 or hi[1] < -0.5 or lo[0] > w - 0.5 or lo[1] > h - 0.5:
        return None
    return disc_px


def _project_sign(
    camera: CameraModel, world_T_cam: np.ndarray, s: SignModel, disc_px: np.ndarray, motion
) -> ProjectedSign:
    def px(points_m: np.ndarray) -> np.ndarray:
        return pixel_from_world_point(camera, world_T_cam, points_m)[0]

    return ProjectedSign(
        s.code,
        disc_px,
        tuple(px(poly) for poly in s.white_m),
        tuple((px(poly), v, o) for poly, v, o in s.dirt_m),
        tuple((px(poly), v) for poly, v in s.occluders_m),
        motion if motion is not None else np.zeros(2),
        s.shade,
    )


def _sign_truth(
    camera: CameraModel,
    world_T_cam: np.ndarray,
    s: SignModel,
    projected: ProjectedSign,
    front: list[ProjectedLine],
) -> SignTruth:
    w, h = camera.width, camera.height
    disc_px = projected.disc_px
    lo, hi = disc_px.min(axis=0), disc_px.max(axis=0)
    names = list(s.keypoints_m)
    kp_px, _ = pixel_from_world_point(
        camera, world_T_cam, np.array([s.keypoints_m[k] for k in names])
    )
    c = pixel_from_world_point(camera, world_T_cam, s.center_m[None])[0][0]
    half = len(disc_px) // 2
    diameter = float(np.linalg.norm(disc_px[:half] - disc_px[half : 2 * half], axis=1).max())
    occluded = bool(projected.occluders_px) or any(
        _segment_distance(c, ln.points_px) < 0.5 * diameter + 0.5 * float(ln.widths_px.max())
        for ln in front
    )
    x0, y0 = max(lo[0], -0.5), max(lo[1], -0.5)
    x1, y1 = min(hi[0], w - 0.5), min(hi[1], h - 0.5)
    return SignTruth(
        code=s.code,
        bbox_px=(float(x0), float(y0), float(x1 - x0), float(y1 - y0)),
        center_px=(float(c[0]), float(c[1])),
        diameter_px=diameter,
        keypoints_px={k: (float(p[0]), float(p[1])) for k, p in zip(names, kp_px, strict=True)},
        occluded=occluded,
        truncated=bool(lo[0] < -0.5 or lo[1] < -0.5 or hi[0] > w - 0.5 or hi[1] > h - 0.5),
        distance_m=float(np.linalg.norm(world_T_cam[:3, 3] - s.center_m)),
    )


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
        scene: from ``signpose.sim.scene.build_scene``.
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
    front = project_lines(cam, world_T_cam, scene.lines_front) if options.background else []
    behind = project_lines(cam, world_T_cam, scene.lines_behind) if options.background else []
    projected: list[ProjectedSign] = []
    truths: list[SignTruth] = []
    for s in scene.signs:
        disc_px = _disc_in_view(cam, world_T_cam, s)
        if disc_px is None:
            continue
        motion = _motion_px(cam, exposure_poses, s.center_m)
        projected.append(_project_sign(cam, world_T_cam, s, disc_px, motion))
        truths.append(_sign_truth(cam, world_T_cam, s, projected[-1], front))
    # Far signs first so nearer ones cover them.
    order = np.argsort([-t.distance_m for t in truths])
    image = compose_frame(
        scene.backdrop,
        cam.K,
        world_T_cam,
        [projected[i] for i in order],
        rng,
        lines_behind=behind,
        lines_front=front,
        background_motion_px=_motion_px(cam, exposure_poses, scene.center_m),
        gain=gain,
        offset=offset,
        options=options,
        size=(cam.width, cam.height),
    )
    return image, truths
