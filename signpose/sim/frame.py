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
from signpose.frontend.sign import fill_polygon_aa
from signpose.io.boxes import COVERED_FRACTION, SignTruth
from signpose.sim.pylon import Line3D
from signpose.sim.render import (
    Glare,
    ProjectedLine,
    ProjectedSign,
    RenderOptions,
    compose_frame,
    line_coverage,
)
from signpose.sim.scene import Scene, SignModel

MIN_DEPTH_M = 0.3  # nearer points are not projected
# Beyond ~1.3 (normalised radius) a barrel polynomial folds back; the image corner is ~0.66.
MAX_NORMALISED_RADIUS = 1.3
EDGE_ON = 0.05  # cosine below which a face is seen edge-on and skipped
TRUTH_SUPERSAMPLE = 4  # sub-samples per pixel side of the covered-part masks
MIN_COVER_PX = 0.5  # an occluder covering less of the disc than this [px^2] is not counted


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
            width_m = ln.width_m if ln.widths_m is None else ln.widths_m[run[:-1]]
            out.append(ProjectedLine(p[run], width_m * f / d_mid, ln.bgr))
    return out


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


def _project_glare(camera: CameraModel, world_T_cam: np.ndarray, s: SignModel) -> Glare | None:
    if s.glare is None:
        return None
    view = world_T_cam[:3, 3] - s.glare.center_m
    depth = float(np.linalg.norm(view))
    center_px = pixel_from_world_point(camera, world_T_cam, s.glare.center_m[None])[0][0]
    radius_px = s.glare.radius_m * camera.fx / depth
    return Glare(center_px, radius_px, s.glare.strength_dn(view / depth))


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
        s.fade,
        _project_glare(camera, world_T_cam, s),
    )


def _lines_in_box(
    lines: list[ProjectedLine], lo: np.ndarray, hi: np.ndarray
) -> list[ProjectedLine]:
    """The lines with a segment whose box, grown by the line's width, meets [lo, hi) [px]."""
    out = []
    for ln in lines:
        a, b = ln.points_px[:-1], ln.points_px[1:]
        pad = ln.widths_px[:, None] + 1.0
        seg_lo = np.minimum(a, b) - pad
        seg_hi = np.maximum(a, b) + pad
        if np.any(np.all((seg_lo < hi) & (seg_hi > lo), axis=1)):
            out.append(ln)
    return out


def _coverage(
    camera: CameraModel,
    world_T_cam: np.ndarray,
    s: SignModel,
    projected: ProjectedSign,
    in_front: dict[str, list[ProjectedLine]],
) -> tuple[dict[str, float], tuple[str, ...]]:
    """(part name -> covered share of its area, kinds of occluder over the disc).

    Measured on anti-aliased masks in the disc's bounding box at mid-exposure
    (no blur): bars on the face, then each kind of line in front.
    """
    lo = np.floor(projected.disc_px.min(axis=0)).astype(int) - 1
    hi = np.ceil(projected.disc_px.max(axis=0)).astype(int) + 2
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, [camera.width, camera.height])
    shape = (int(hi[1] - lo[1]), int(hi[0] - lo[0]))
    if shape[0] <= 0 or shape[1] <= 0:
        return {}, ()
    off = lo.astype(float)
    near = {kind: _lines_in_box(lines, lo, hi) for kind, lines in in_front.items()}
    if not projected.occluders_px and not any(near.values()):
        return {name: 0.0 for name in s.parts_m or {}}, ()
    disc = np.zeros(shape, np.float32)
    fill_polygon_aa(disc, projected.disc_px - off, 1.0, TRUTH_SUPERSAMPLE)
    masks = {"bar": np.zeros(shape, np.float32)}
    for poly, _ in projected.occluders_px:
        fill_polygon_aa(masks["bar"], poly - off, 1.0, TRUTH_SUPERSAMPLE)
    for kind, lines in near.items():
        masks[kind] = line_coverage(lines, off, shape) if lines else np.zeros(shape, np.float32)
    clear = np.ones(shape, np.float32)
    for m in masks.values():
        clear *= 1.0 - np.clip(m, 0.0, 1.0)
    kinds = tuple(k for k, m in masks.items() if float((m * disc).sum()) > MIN_COVER_PX)
    cover: dict[str, float] = {}
    for name, poly_m in (s.parts_m or {}).items():
        part = np.zeros(shape, np.float32)
        poly_px = pixel_from_world_point(camera, world_T_cam, poly_m)[0]
        fill_polygon_aa(part, poly_px - off, 1.0, TRUTH_SUPERSAMPLE)
        area = float(part.sum())
        cover[name] = float((part * (1.0 - clear)).sum()) / area if area > 0 else 0.0
    return cover, kinds


def _sign_truth(
    camera: CameraModel,
    world_T_cam: np.ndarray,
    s: SignModel,
    projected: ProjectedSign,
    in_front: dict[str, list[ProjectedLine]],
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
    cover, kinds = _coverage(camera, world_T_cam, s, projected, in_front)
    x0, y0 = max(lo[0], -0.5), max(lo[1], -0.5)
    x1, y1 = min(hi[0], w - 0.5), min(hi[1], h - 0.5)
    return SignTruth(
        code=s.code,
        bbox_px=(float(x0), float(y0), float(x1 - x0), float(y1 - y0)),
        center_px=(float(c[0]), float(c[1])),
        diameter_px=diameter,
        keypoints_px={k: (float(p[0]), float(p[1])) for k, p in zip(names, kp_px, strict=True)},
        occluded=bool(kinds),
        truncated=bool(lo[0] < -0.5 or lo[1] < -0.5 or hi[0] > w - 0.5 or hi[1] > h - 0.5),
        distance_m=float(np.linalg.norm(world_T_cam[:3, 3] - s.center_m)),
        covered_slots=tuple(
            k for k in range(1, 5) if cover.get(f"slot{k}", 0.0) >= COVERED_FRACTION
        ),
        part_cover=cover,
        occluders=kinds,
        fade=s.fade,
        dirty=bool(s.dirt_m),
        glare_dn=projected.glare.peak_dn if projected.glare is not None else 0.0,
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
    vibration_px: np.ndarray | None = None,
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
        vibration_px: (2,) blur segment of a vibration burst added to every
            motion this frame [px]; None = none.

    Returns:
        ((H, W, 3) uint8 BGR image, truth of every sign whose disc is in the image).
    """
    options = options if options is not None else RenderOptions()
    cam = scene.camera
    front = project_lines(cam, world_T_cam, scene.lines_front) if options.background else []
    behind = project_lines(cam, world_T_cam, scene.lines_behind) if options.background else []
    members = project_lines(cam, world_T_cam, scene.members)
    in_front = {"member": members, "conductor": front}

    def motion_of(point_m: np.ndarray) -> np.ndarray | None:
        m = _motion_px(cam, exposure_poses, point_m)
        if vibration_px is None or not options.blur:
            return m
        return np.asarray(vibration_px, float) + (m if m is not None else 0.0)

    projected: list[ProjectedSign] = []
    truths: list[SignTruth] = []
    for s in scene.signs:
        disc_px = _disc_in_view(cam, world_T_cam, s)
        if disc_px is None:
            continue
        projected.append(_project_sign(cam, world_T_cam, s, disc_px, motion_of(s.center_m)))
        truths.append(_sign_truth(cam, world_T_cam, s, projected[-1], in_front))
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
        members_front=members,
        background_motion_px=motion_of(scene.center_m),
        gain=gain,
        offset=offset,
        options=options,
        size=(cam.width, cam.height),
    )
    return image, truths
