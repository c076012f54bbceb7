"""Flight simulator: a sign map + a trajectory -> frames with ground truth.

The flight writer: builds the scene once (``signpose.sim.scene``), renders
every pose (``signpose.sim.frame``) and writes the frames
(``signpose.sim.writers``) with their ground truth.

World frame: the map's (z up, metres). Camera poses are ``world_T_cam`` with
OpenCV axes (x right, y down, z forward). Time: frame ``i`` is at
``i / fps`` seconds, ``stamp_ns = round(i * 1e9 / fps)``; the exposure is
centred on the stamp.

Speed: ``SimSettings.speed_mps`` is the cruise speed (the mean path speed,
``signpose.sim.trajectories``): the frames cover the first frames / fps
seconds of the flight at that speed, repeating the orbit and flying the other
paths back and forth when they last longer than one pass. None (the
library's default, kept by the evaluations) squeezes the whole path into the
frames once; ``signpose simulate`` always passes a speed
(``DEFAULT_SPEED_MPS`` unless ``--speed``). The flight's mean and peak speed
are in ``SimResult`` and in ``groundtruth.tum``'s ``#`` header line.

Conditions: every real-pylon condition is off by default (a default flight
renders as it always did) and switchable in ``SimSettings``; ``hard()`` turns
them all on at the ``HARD`` rates. Scene conditions (members and conductors in
front of signs, insulator strings, faded or dirty faces, glare, photographs)
are described in ``signpose.sim.scene``, per-frame ones (JPEG 70-90,
vibration bursts, exposure steps) in ``signpose.sim.conditions``; what each
frame and sign got is in ``boxes.jsonl``.

Output folder (``simulate``):
    video.mp4, frames/ or flight.mcap the frames (``signpose.sim.writers``)
    camera.yaml                      ROS camera_info (``signpose.io.camera_file``)
    groundtruth.tum                  world_T_cam per frame (``signpose.io.tum``),
                                     after one ``#`` line: trajectory, frames, fps,
                                     duration_s, speed_mps, mean/peak_speed_mps
    boxes.jsonl                      per-frame truth of every visible sign
                                     (``signpose.io.boxes``, which documents it)
    map.yaml                         copy of the map (``signpose.maps.loader``)
    telemetry.csv                    only with ``telemetry``: GNSS + IMU of the flight
                                     (``signpose.sim.telemetry``); map.yaml then has
                                     an ``origin`` (the map's own, else ``SIM_ORIGIN``)
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from signpose.core.errors import InputError
from signpose.core.fileio import ensure_dir
from signpose.estimator.camera import CameraModel, pinhole_camera
from signpose.estimator.trajectory import Trajectory
from signpose.io.boxes import FrameConditions, FrameTruth, write_boxes
from signpose.io.camera_file import write_camera_info
from signpose.io.tum import write_tum
from signpose.maps.loader import SignMap, write_map
from signpose.sim.conditions import ConditionSettings, frame_draws
from signpose.sim.frame import render_frame
from signpose.sim.render import RenderOptions
from signpose.sim.scene import Scene, SceneOptions, build_scene
from signpose.sim.telemetry import (
    SIM_ORIGIN,
    SampledFlight,
    TelemetrySimSettings,
    simulate_telemetry,
    write_telemetry_csv,
)
from signpose.sim.trajectories import (
    CONTINUATION,
    MAX_SPEED_MPS,
    TRAJECTORIES,
    make_trajectory,
    site_frame,
    speed_stats,
)
from signpose.sim.writers import FORMATS, FrameWriter, make_frame_writer

__all__ = [
    "FORMATS",
    "SimResult",
    "SimSettings",
    "frames_for_duration",
    "lighting_at",
    "pose_at",
    "simulate",
    "simulated_camera",
    "stamp_ns_of",
    "telemetry_flight",
]

log = logging.getLogger(__name__)

# Real-pylon conditions at the rates ``SimSettings.hard`` uses: a fifth of the signs
# crossed by a member, two extra conductors, JPEG 70-90, a vibration burst every
# ~3 s and an exposure step every ~5 s. The older opaque face bars (``occlusion``)
# stay off: they are this simulator's own invention, not a pylon's.
HARD = {
    "dirt": True,
    "members": 0.2,
    "conductors": 2,
    "insulators": True,
    "faded": 0.3,
    "glare": 0.3,
    "photo": True,
    "jpeg_range": (70, 90),
    "vibration": 0.3,
    "exposure_steps": 0.2,
}


# --------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class SimSettings:
    """What to simulate (defaults: the paper's simulated set, 1080p at 25-30 m).

    Attributes:
        frames: number of frames (the flight lasts frames / fps seconds).
        fps: frame rate [Hz].
        speed_mps: cruise speed, the mean path speed [m/s], in (0, 30]; None:
            the whole path once over the frames (the library's old behaviour,
            whatever speed that takes).
        trajectory: one of ``signpose.sim.trajectories.TRAJECTORIES``.
        seed: seeds the trajectory wobble, the scene textures, dirt, occluders,
            lighting and noise. Same seed, same outputs.
        width, height: image size [px].
        hfov_deg: horizontal field of view [deg].
        distortion_k1: plumb_bob k1 of the simulated lens (0 = ideal pinhole).
        distance_m: nominal distance from the signs [m].
        format: ``"mp4"`` (video.mp4, mp4v), ``"png"`` (frames/NNNNNN.png) or ``"mcap"``
            (flight.mcap: images, ground truth and camera; ``signpose.io.mcap``).
        dirt: stains on some sign faces.
        occlusion: opaque bars in front of some sign faces.
        blur: motion blur from the real motion during the exposure.
        exposure_fraction: exposure time as a fraction of the frame period.
        noise_sigma: sensor noise [DN], 0 = off.
        jpeg_quality: JPEG round-trip quality, None = off.
        background: sky, ground, lattice and conductors (False: flat grey).
        lighting: slowly varying global gain/offset.
        supersample: sub-samples per pixel side for the sign faces.
        members: share of signs with a lattice member in front (``sim.scene``).
        conductors: extra conductors strung in front of the signs (``sim.scene``).
        insulators: insulator strings drawn with their sheds (``sim.scene``).
        faded: share of faces with faded paint (``sim.scene``).
        glare: share of faces with a specular highlight (``sim.scene``).
        photo: a real photograph as the background (``sim.scene``, ``sim.photos``).
        jpeg_range: per-frame JPEG quality range, e.g. (70, 90) (``sim.conditions``).
        vibration: vibration blur bursts per second (``sim.conditions``).
        exposure_steps: auto-exposure gain steps per second (``sim.conditions``).
    """

    frames: int = 210
    fps: float = 30.0
    speed_mps: float | None = None
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
    members: float = 0.0
    conductors: int = 0
    insulators: bool = False
    faded: float = 0.0
    glare: float = 0.0
    photo: bool = False
    jpeg_range: tuple[int, int] | None = None
    vibration: float = 0.0
    exposure_steps: float = 0.0

    def hard(self) -> SimSettings:
        """These settings with every real-pylon condition on at ``HARD`` rates."""
        return replace(self, **HARD)

    def render_options(self) -> RenderOptions:
        return RenderOptions(
            supersample=self.supersample,
            blur=self.blur,
            noise_sigma=self.noise_sigma,
            jpeg_quality=self.jpeg_quality,
            background=self.background,
            lighting=self.lighting,
        )

    def scene_options(self) -> SceneOptions:
        return SceneOptions(
            dirt=self.dirt,
            occlusion=self.occlusion,
            background=self.background,
            members=self.members,
            conductors=self.conductors,
            insulators=self.insulators,
            faded=self.faded,
            glare=self.glare,
            photo=self.photo,
        )

    def condition_settings(self) -> ConditionSettings:
        return ConditionSettings(self.jpeg_range, self.vibration, self.exposure_steps)

    def validate(self) -> SimSettings:
        """Return self, or raise InputError naming the bad setting."""
        if self.frames < 1:
            raise InputError(f"--frames must be >= 1, got {self.frames}")
        if not (self.fps > 0 and math.isfinite(self.fps)):
            raise InputError(f"--fps must be > 0, got {self.fps}")
        if self.speed_mps is not None and not 0.0 < self.speed_mps <= MAX_SPEED_MPS:
            raise InputError(f"--speed must be in (0, {MAX_SPEED_MPS:g}] m/s, got {self.speed_mps}")
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
        for name in ("members", "faded", "glare"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise InputError(f"{name} must be a share in [0, 1], got {getattr(self, name)}")
        for name in ("conductors", "vibration", "exposure_steps"):
            if not getattr(self, name) >= 0:
                raise InputError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.jpeg_range is not None and not 1 <= self.jpeg_range[0] <= self.jpeg_range[1] <= 100:
            raise InputError(
                f"jpeg_range must be lo,hi with 1 <= lo <= hi <= 100, got {self.jpeg_range}"
            )
        return self


def frames_for_duration(duration_s: float, fps: float) -> int:
    """Frames of a flight of ``duration_s`` seconds at ``fps`` (at least one); InputError if bad."""
    if not (duration_s > 0 and math.isfinite(duration_s)):
        raise InputError(f"--duration must be a number of seconds > 0, got {duration_s}")
    if not (fps > 0 and math.isfinite(fps)):
        raise InputError(f"--fps must be > 0, got {fps}")
    return max(1, round(duration_s * fps))


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
        duration_s: the flight's length, frames / fps [s].
        mean_speed_mps: distance flown / time flown [m/s] (0 for one frame).
        peak_speed_mps: fastest frame-to-frame speed [m/s].
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
    duration_s: float = 0.0
    mean_speed_mps: float = 0.0
    peak_speed_mps: float = 0.0
    telemetry_path: Path | None = None

    def paths(self) -> tuple[Path, ...]:
        extra = () if self.telemetry_path is None else (self.telemetry_path,)
        return (
            self.frames_path,
            self.camera_path,
            self.groundtruth_path,
            self.boxes_path,
            self.map_path,
            *extra,
        )


def simulated_camera(settings: SimSettings = SimSettings()) -> CameraModel:
    """The simulated camera: pinhole of ``hfov_deg`` with plumb_bob k1 distortion."""
    cam = pinhole_camera(settings.width, settings.height, settings.hfov_deg, name="sim")
    dist = np.array([settings.distortion_k1, 0.0, 0.0, 0.0, 0.0])
    return replace(cam, dist=dist)


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


# --------------------------------------------------------------------------- a flight


def _exposure_poses(
    settings: SimSettings, poses: np.ndarray, stamps_s: np.ndarray, i: int
) -> tuple[np.ndarray, np.ndarray] | None:
    """Poses at the start and end of frame ``i``'s exposure, None without motion blur."""
    half_exposure = 0.5 * settings.exposure_fraction / settings.fps
    if not (settings.blur and half_exposure > 0 and len(poses) > 1):
        return None
    t = float(stamps_s[i])
    return pose_at(poses, stamps_s, t - half_exposure), pose_at(poses, stamps_s, t + half_exposure)


def _render_flight(
    scene: Scene,
    traj: Trajectory,
    settings: SimSettings,
    writer: FrameWriter,
    progress: bool,
) -> list[FrameTruth]:
    """Render and write every frame of ``traj``; return their truth."""
    poses, stamps = traj.world_T_cam(), traj.stamps_s
    options = settings.render_options()
    draws = frame_draws(
        settings.condition_settings(), len(traj), settings.fps, settings.width, settings.seed
    )
    truths: list[FrameTruth] = []
    for i in tqdm(range(len(traj)), desc="simulate", unit="frame", disable=not progress):
        gain, offset = lighting_at(float(stamps[i]), settings.seed)
        gain *= draws[i].gain_factor
        frame_options = options
        if draws[i].jpeg_quality is not None:
            frame_options = replace(options, jpeg_quality=draws[i].jpeg_quality)
        vibration = draws[i].vibration_px if settings.vibration > 0 else None
        image, signs = render_frame(
            scene,
            poses[i],
            np.random.default_rng([settings.seed, i]),
            options=frame_options,
            exposure_poses=_exposure_poses(settings, poses, stamps, i),
            gain=gain,
            offset=offset,
            vibration_px=None if vibration is None else np.asarray(vibration),
        )
        stamp_ns = stamp_ns_of(i, settings.fps)
        writer.write(i, stamp_ns, image)
        if not settings.lighting:
            gain, offset = 1.0, 0.0
        conditions = FrameConditions(
            frame_options.jpeg_quality,
            gain,
            offset,
            draws[i].vibration_px if settings.blur else (0.0, 0.0),
            scene.background,
        )
        truths.append(FrameTruth(i, stamp_ns, tuple(signs), conditions))
    return truths


def _flight_comment(settings: SimSettings, result: SimResult) -> str:
    """groundtruth.tum's header: what was flown, ``key=value`` separated by spaces."""
    speed = "fit" if settings.speed_mps is None else f"{settings.speed_mps:g}"
    return (
        f"signpose simulate trajectory={settings.trajectory} frames={result.n_frames} "
        f"fps={settings.fps:g} duration_s={result.duration_s:.3f} speed_mps={speed} "
        f"mean_speed_mps={result.mean_speed_mps:.3f} peak_speed_mps={result.peak_speed_mps:.3f} "
        f"continuation={CONTINUATION[settings.trajectory].replace(' ', '-')} seed={settings.seed}"
    )


TELEMETRY_GRID_HZ = 1000.0


def telemetry_flight(sign_map: SignMap, settings: SimSettings, pad_s: float) -> SampledFlight:
    """The flight of ``settings`` as a ``SampledFlight``: its trajectory sampled at 1 kHz
    over [-pad_s, frames / fps + pad_s] of video time.

    The trajectory is a function of time when ``speed_mps`` is set (a shorter flight
    is the start of a longer one; before 0 it runs backwards the same way), so the
    grid's poses are the rendered frames' own function, not a fit to them.
    """
    if settings.speed_mps is None:
        raise ValueError("telemetry_flight: needs settings.speed_mps (a flight in time)")
    duration = settings.frames / settings.fps
    n_after = int(math.ceil((duration + pad_s) * TELEMETRY_GRID_HZ)) + 2
    n_before = int(math.ceil(pad_s * TELEMETRY_GRID_HZ)) + 2

    def grid(n: int, rate: float) -> np.ndarray:
        return make_trajectory(
            settings.trajectory,
            sign_map,
            n_frames=n,
            fps=rate,
            distance_m=settings.distance_m,
            seed=settings.seed,
            speed_mps=settings.speed_mps,
        ).world_T_cam()

    before = grid(n_before, -TELEMETRY_GRID_HZ)[:0:-1]  # times -(n_before-1)/rate .. -1/rate
    poses = np.concatenate([before, grid(n_after, TELEMETRY_GRID_HZ)])
    center, facing, right, up = site_frame(sign_map)
    t0 = -(n_before - 1) / TELEMETRY_GRID_HZ
    return SampledFlight(duration, center, facing, right, up, t0, TELEMETRY_GRID_HZ, poses)


def _write_telemetry(
    sign_map: SignMap, settings: SimSettings, result: SimResult, tel: TelemetrySimSettings
) -> SimResult:
    """Write telemetry.csv (clock offset rounded to 1 ms); ``sign_map`` has an origin."""
    tel = replace(tel, clock_offset_s=round(tel.clock_offset_s, 3))
    flight = telemetry_flight(sign_map, settings, tel.margin_s + abs(tel.clock_offset_s) + 0.01)
    rng = np.random.default_rng([settings.seed, 17])
    telemetry, _ = simulate_telemetry(flight, sign_map, rng, tel)
    path = result.out_dir / "telemetry.csv"
    write_telemetry_csv(path, telemetry)
    return replace(result, telemetry_path=path)


def simulate(
    sign_map: SignMap,
    out_dir: str | Path,
    settings: SimSettings = SimSettings(),
    progress: bool = True,
    telemetry: TelemetrySimSettings | None = None,
) -> SimResult:
    """Render a flight in front of ``sign_map`` and write it with its ground truth to ``out_dir``.

    Args:
        sign_map: the signs (and the site the pylon is built around).
        out_dir: output folder, created if missing.
        settings: what to simulate.
        progress: show a tqdm bar over frames.
        telemetry: also write telemetry.csv with these sensor errors (needs
            ``settings.speed_mps``) and give map.yaml an origin; None: not.

    Returns:
        The paths written. Raises OutputError when ``out_dir`` is not writable.
    """
    settings.validate()
    if telemetry is not None and settings.speed_mps is None:
        raise ValueError("simulate: telemetry needs settings.speed_mps (a flight in time)")
    out = ensure_dir(out_dir)
    camera = simulated_camera(settings)
    traj = make_trajectory(
        settings.trajectory,
        sign_map,
        n_frames=settings.frames,
        fps=settings.fps,
        distance_m=settings.distance_m,
        seed=settings.seed,
        speed_mps=settings.speed_mps,
    )
    mean_speed, peak_speed = speed_stats(traj)
    scene = build_scene(sign_map, camera, settings.seed, settings.scene_options())
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
    poses = traj.world_T_cam()
    with make_frame_writer(
        settings.format, out, settings.fps, camera, poses, world_frame=sign_map.frame
    ) as writer:
        truths = _render_flight(scene, traj, settings, writer, progress)
    result = SimResult(
        out_dir=out,
        frames_path=writer.path,
        camera_path=out / "camera.yaml",
        groundtruth_path=out / "groundtruth.tum",
        boxes_path=out / "boxes.jsonl",
        map_path=out / "map.yaml",
        n_frames=len(traj),
        camera=camera,
        trajectory=traj,
        duration_s=settings.frames / settings.fps,
        mean_speed_mps=mean_speed,
        peak_speed_mps=peak_speed,
    )
    write_boxes(result.boxes_path, truths)
    write_camera_info(result.camera_path, camera)
    write_tum(result.groundtruth_path, traj, (_flight_comment(settings, result),))
    if telemetry is not None and sign_map.origin is None:  # map.yaml anchors the telemetry
        sign_map = replace(sign_map, origin=SIM_ORIGIN)
    write_map(result.map_path, sign_map)
    if telemetry is not None:
        result = _write_telemetry(sign_map, settings, result, telemetry)
    return result
