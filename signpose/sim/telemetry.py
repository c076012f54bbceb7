"""Simulated drone telemetry (issue 17): GNSS, a MEMS IMU and a clock offset.

The flight (``away_and_back``) is a continuous-time ground truth: the UAV
looks at the signs, turns away and flies along the line for a stretch where
no sign is in view, comes back and looks again. Its pose at any time gives
the camera frames (``FlightTruth.trajectory``) and the sensors:

* GNSS antenna fixes at ``gnss_rate_hz`` (WGS84 through ``maps.geodesy``):
  white noise (``gnss_sigma_h_m``, ``gnss_sigma_v_m``), a slow Gauss-Markov
  drift and, near the conductors, multipath bursts of 5-20 m lasting 1-3 s;
* IMU samples at ``imu_rate_hz`` in the IMU body frame (FLU, ``body_T_cam``
  of ``estimator.telemetry``): specific force and angular rate from the
  trajectory, white noise and bias random walks of a MEMS unit;
* every telemetry time is ``t_video + clock_offset_s`` (``estimator.telemetry``).

Frames: world = the map's frame (ENU at its ``origin``: x east, y north, z up),
camera axes OpenCV's. ``write_telemetry_csv`` writes the telemetry CSV that
``signpose.io.telemetry_csv`` reads (a ``# signpose telemetry v1`` comment, the
header, one row per GNSS fix or IMU sample).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from signpose.core.fileio import atomic_write
from signpose.estimator.fusion import FusionSettings, gimbal_from_world_R_cam, log_so3
from signpose.estimator.telemetry import GimbalAngles, GnssFixes, ImuSamples, Telemetry
from signpose.estimator.trajectory import Trajectory
from signpose.io.telemetry_csv import (
    ALL_COLUMNS,
    GIMBAL_COLUMNS,
    GNSS_COLUMNS,
    IMU_COLUMNS,
    SIGMA_COLUMNS,
)
from signpose.maps.geodesy import GeoOrigin, geodetic_from_enu
from signpose.maps.loader import SignMap
from signpose.sim.trajectories import site_frame

CSV_MAGIC = "# signpose telemetry v1"
GRAVITY_M_S2 = 9.80665
# The WGS84 anchor ``signpose simulate --telemetry`` gives a map without an
# ``origin`` (Zurich, ellipsoidal height 480 m; also ``scripts/eval_fusion.py``'s).
SIM_ORIGIN = GeoOrigin(47.3769, 8.5417, 480.0)


def default_body_T_cam() -> np.ndarray:
    """(4, 4) camera in the IMU body (FLU): looking forward, at the IMU.

    At the IMU: gtsam's ``body_P_sensor`` corrects a lever arm's centrifugal
    term but not the angular-acceleration one (5 cm and the wobble moved a
    1 s preintegration 8 mm off).
    """
    # Camera axes in the body: x right = -y_body, y down = -z_body, z forward = x_body.
    return np.array(FusionSettings().body_T_cam, float)  # the fusion's default mounting


@dataclass(frozen=True)
class TelemetrySimSettings:
    """Sensor errors of the simulated drone.

    Attributes:
        clock_offset_s: telemetry time minus video time [s].
        margin_s: telemetry starts this long before the first frame and ends
            this long after the last [s].
        gnss_rate_hz: GNSS fix rate [Hz].
        gnss_sigma_h_m / gnss_sigma_v_m: white noise per fix, also written
            as each fix's claimed sigma [m].
        drift_sigma_h_m / drift_sigma_v_m: Gauss-Markov drift, stationary
            standard deviation per axis [m].
        drift_tau_s: its correlation time [s].
        multipath: add bursts near the conductors.
        burst_rate_hz: expected bursts per second while near them.
        burst_m: (min, max) burst offset [m], uniform, random direction.
        burst_s: (min, max) burst duration [s].
        conductor_range_m: bursts happen within this distance of a conductor.
        imu_rate_hz: IMU sample rate [Hz].
        gyro_noise: gyro white noise density [rad/s/sqrt(Hz)].
        accel_noise: accelerometer white noise density [m/s^2/sqrt(Hz)].
        gyro_bias_rw / accel_bias_rw: bias random walk densities
            [rad/s^2/sqrt(Hz)], [m/s^3/sqrt(Hz)].
        gyro_bias0 / accel_bias0: standard deviation of the turn-on biases.
        cam_t_antenna_m: GNSS antenna in the camera frame [m].
        gimbal_rate_hz: gimbal angle rate [Hz] (0: no gimbal stream).
        gimbal_sigma_deg: (yaw, pitch, roll) noise of the reported angles [deg].
        body_T_cam: (4, 4) camera in the IMU body, or None for ``default_body_T_cam``.
    """

    clock_offset_s: float = 0.0
    margin_s: float = 2.0
    gnss_rate_hz: float = 10.0
    gnss_sigma_h_m: float = 1.2
    gnss_sigma_v_m: float = 1.8
    drift_sigma_h_m: float = 0.8
    drift_sigma_v_m: float = 1.2
    drift_tau_s: float = 60.0
    multipath: bool = True
    burst_rate_hz: float = 1.0 / 8.0
    burst_m: tuple[float, float] = (5.0, 20.0)
    burst_s: tuple[float, float] = (1.0, 3.0)
    conductor_range_m: float = 40.0
    imu_rate_hz: float = 200.0
    gyro_noise: float = 5e-4
    accel_noise: float = 4e-3
    gyro_bias_rw: float = 2e-5
    accel_bias_rw: float = 2e-4
    gyro_bias0: float = 2e-3
    accel_bias0: float = 0.05
    cam_t_antenna_m: tuple[float, float, float] = (0.0, -0.25, -0.10)
    gimbal_rate_hz: float = 0.0
    gimbal_sigma_deg: tuple[float, float, float] = (2.0, 0.5, 0.5)
    body_T_cam: np.ndarray | None = field(default=None, compare=False)


class _PosesOfTime:
    """``poses(t)`` from a flight's ``position(t)`` and ``rotations(t)``."""

    def poses(self, t: np.ndarray) -> np.ndarray:
        """(N, 4, 4) world_T_cam at video times ``t`` (N,) [s]."""
        t = np.atleast_1d(np.asarray(t, float))
        T = np.tile(np.eye(4), (len(t), 1, 1))
        T[:, :3, 3] = self.position(t)
        T[:, :3, :3] = self.rotations(t)
        return T


@dataclass(frozen=True)
class FlightTruth(_PosesOfTime):
    """A continuous-time flight: ``pose(t)`` gives world_T_cam at video time t [s].

    Attributes:
        duration_s: the flight lasts [0, duration_s] of video time.
        center / facing / right / up: the site's axes (``site_frame``).
        away_s: (start, end) video times of the turn away from the signs [s].
        seed: the wobble's phases.
    """

    duration_s: float
    center: np.ndarray
    facing: np.ndarray
    right: np.ndarray
    up: np.ndarray
    away_s: tuple[float, float]
    distance_m: float
    freqs: np.ndarray
    phases: np.ndarray
    wobble_rad: float
    side: float = 1.0  # +1: away to the site's right (turning right), -1: to its left
    reach_m: float = 14.0  # how far along the line the UAV flies away [m]

    def position(self, t: np.ndarray) -> np.ndarray:
        """(N, 3) camera centres at video times ``t`` (N,) [s]."""
        t = np.atleast_1d(np.asarray(t, float))
        a, b = self.away_s
        u = np.clip((t - a) / (b - a), 0.0, 1.0)
        go = 0.5 - 0.5 * np.cos(2 * np.pi * u)  # 0 -> 1 -> 0 over the away stretch
        lateral = 2.0 * np.sin(2 * np.pi * t / 17.0) + self.side * self.reach_m * go
        back = self.distance_m + 1.0 * np.sin(2 * np.pi * t / 13.0) + 4.0 * go
        height = 1.2 * np.sin(2 * np.pi * t / 11.0 + 0.4) + 2.0 * go
        return (
            self.center
            + np.outer(back, self.facing)
            + np.outer(lateral, self.right)
            + np.outer(height, self.up)
        )

    def yaw_away_rad(self, t: np.ndarray) -> np.ndarray:
        """How far the camera is turned from the signs about world up [rad]."""
        a, b = self.away_s
        turn = 2.0  # seconds to turn away or back
        rise = np.clip((np.asarray(t, float) - a) / turn, 0.0, 1.0)
        fall = np.clip((b - np.asarray(t, float)) / turn, 0.0, 1.0)
        smooth = lambda x: x * x * (3 - 2 * x)  # noqa: E731
        return self.side * np.radians(110.0) * np.minimum(smooth(rise), smooth(fall))

    def rotations(self, t: np.ndarray) -> np.ndarray:
        """(N, 3, 3) world_R_cam at video times ``t`` (N,) [s]: looking at the
        signs, turned away by ``yaw_away_rad``, with a multirotor's wobble."""
        t = np.atleast_1d(np.asarray(t, float))
        p = self.position(t)
        z = self.center - p
        z /= np.linalg.norm(z, axis=1, keepdims=True)
        x = np.cross(z, self.up)
        x /= np.linalg.norm(x, axis=1, keepdims=True)
        y = np.cross(z, x)
        R = np.stack([x, y, z], axis=2)
        ang = np.sin(2 * np.pi * self.freqs[None] * t[:, None, None] + self.phases[None])
        ang = self.wobble_rad * ang.sum(axis=2) / 3  # (N, 3): yaw, pitch, roll
        yaw = self.yaw_away_rad(t) + ang[:, 0]
        ex, ez = np.array([1.0, 0, 0]), np.array([0, 0, 1.0])
        return _rots(self.up, yaw) @ R @ _rots(ex, ang[:, 1]) @ _rots(ez, ang[:, 2])

    def trajectory(self, fps: float) -> Trajectory:
        """The camera frames at ``fps`` over the flight (stamps from 0) [s]."""
        n = int(math.floor(self.duration_s * fps)) + 1
        stamps = np.arange(n) / fps
        return Trajectory.from_matrices(stamps, self.poses(stamps))


def _rots(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations by angles (N,) [rad] about one unit axis (3,)."""
    axis = axis / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    a = np.asarray(angle, float)[:, None, None]
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * (K @ K)


def away_and_back(
    sign_map: SignMap,
    duration_s: float = 30.0,
    away_s: tuple[float, float] = (8.0, 22.0),
    distance_m: float = 27.0,
    seed: int = 0,
    wobble_deg: float = 1.5,
) -> FlightTruth:
    """A flight that looks at the signs, turns 110 deg away for ``away_s`` and comes back.

    The seed draws the wobble's phases, the side the UAV turns and flies to
    (along the line) and how far it goes (10-16 m).

    With the default 14 s away (2 s turns each way) about 10 s have no sign
    in view for a 60 deg lens.
    """
    rng = np.random.default_rng(seed)
    center, facing, right, up = site_frame(sign_map)
    return FlightTruth(
        duration_s=float(duration_s),
        center=center,
        facing=facing,
        right=right,
        up=up,
        away_s=(float(away_s[0]), float(away_s[1])),
        distance_m=float(distance_m),
        freqs=rng.uniform(0.2, 1.5, size=(3, 3)),
        phases=rng.uniform(0, 2 * np.pi, size=(3, 3)),
        wobble_rad=math.radians(wobble_deg),
        side=float(rng.choice([-1.0, 1.0])),
        reach_m=float(rng.uniform(10.0, 16.0)),
    )


def imu_truth(
    flight: FlightTruth, t_video_s: np.ndarray, body_T_cam: np.ndarray, h: float = 1e-3
) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free ((N, 3) angular rate [rad/s], (N, 3) specific force [m/s^2]), body frame.

    Central differences of the pose of the IMU body (world_T_body =
    world_T_cam * cam_T_body) with step ``h`` [s].
    """
    cam_T_body = np.linalg.inv(body_T_cam)
    t = np.asarray(t_video_s, float)
    T0, T1, T2 = (flight.poses(t + d) @ cam_T_body for d in (-h, 0.0, h))
    R0, R1, R2 = T0[:, :3, :3], T1[:, :3, :3], T2[:, :3, :3]
    gyro = log_so3(np.swapaxes(R0, 1, 2) @ R2) / (2 * h)
    a_world = (T2[:, :3, 3] - 2 * T1[:, :3, 3] + T0[:, :3, 3]) / h**2
    gravity = np.array([0.0, 0.0, -GRAVITY_M_S2])
    accel = np.einsum("nji,nj->ni", R1, a_world - gravity)
    return gyro, accel


def _gauss_markov(
    rng: np.random.Generator, n: int, dt: float, sigma: np.ndarray, tau: float
) -> np.ndarray:
    """(n, 3) first-order Gauss-Markov process, stationary sigma (3,), correlation time tau."""
    phi = math.exp(-dt / tau)
    out = np.empty((n, 3))
    out[0] = rng.normal(0.0, sigma)
    q = sigma * math.sqrt(1 - phi**2)
    for k in range(1, n):
        out[k] = phi * out[k - 1] + rng.normal(0.0, q)
    return out


def conductor_distance_m(flight: FlightTruth, sign_map: SignMap, p_world: np.ndarray) -> np.ndarray:
    """(N,) distance of points (N, 3) to the conductors [m].

    The conductors: two horizontal lines along the site's ``right`` axis,
    6 m above the highest sign, 4 m in front of and behind the face.
    """
    top = float(sign_map.centers_m()[:, 2].max()) + 6.0
    d = np.full(len(p_world), np.inf)
    for side in (-4.0, 4.0):
        base = flight.center + side * flight.facing
        base = base + (top - base[2]) * flight.up
        rel = p_world - base
        along = rel @ flight.right
        d = np.minimum(d, np.linalg.norm(rel - np.outer(along, flight.right), axis=1))
    return d


@dataclass(frozen=True)
class SimTelemetryTruth:
    """What the simulated sensors really measured.

    Attributes:
        gnss_t_s: (G,) telemetry time of each fix [s].
        antenna_world_m: (G, 3) true antenna positions [m].
        gnss_error_m: (G, 3) error of each fix, world axes [m].
        burst: (G,) True for fixes inside a multipath burst.
        gyro_bias: (I, 3), accel_bias: (I, 3) the IMU's true biases.
        clock_offset_s: the true offset [s].
    """

    gnss_t_s: np.ndarray
    antenna_world_m: np.ndarray
    gnss_error_m: np.ndarray
    burst: np.ndarray
    gyro_bias: np.ndarray
    accel_bias: np.ndarray
    clock_offset_s: float


def _bursts(
    rng: np.random.Generator, t: np.ndarray, near: np.ndarray, s: TelemetrySimSettings
) -> tuple[np.ndarray, np.ndarray]:
    """((G, 3) multipath offsets [m], (G,) in-burst mask) for fixes at times t, near (G,)."""
    offset = np.zeros((len(t), 3))
    inside = np.zeros(len(t), bool)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    k = 0
    while k < len(t):
        if near[k] and rng.random() < s.burst_rate_hz * dt:
            length = rng.uniform(*s.burst_s)
            mag = rng.uniform(*s.burst_m)
            direction = rng.normal(size=3) * np.array([1.0, 1.0, 0.5])
            direction /= np.linalg.norm(direction)
            sel = (t >= t[k]) & (t < t[k] + length)
            offset[sel] = mag * direction
            inside |= sel
            k = int(np.nonzero(sel)[0][-1]) + 1 + int(round(1.0 / dt))  # at least 1 s apart
            continue
        k += 1
    return offset, inside


def simulate_telemetry(
    flight: FlightTruth,
    sign_map: SignMap,
    rng: np.random.Generator,
    settings: TelemetrySimSettings | None = None,
) -> tuple[Telemetry, SimTelemetryTruth]:
    """GNSS and IMU of ``flight`` (the map must have an ``origin``).

    The noise streams are drawn from child generators in a fixed order, so
    the same seed gives the same white noise, drift and IMU errors with and
    without ``multipath``.
    """
    s = settings or TelemetrySimSettings()
    if sign_map.origin is None:
        raise ValueError("simulate_telemetry: the map needs an origin (WGS84 anchor)")
    body_T_cam = default_body_T_cam() if s.body_T_cam is None else np.asarray(s.body_T_cam)
    r_white, r_drift, r_burst, r_imu = rng.spawn(4)
    t0 = -s.margin_s + s.clock_offset_s
    t1 = flight.duration_s + s.margin_s + s.clock_offset_s
    # GNSS.
    tg = np.arange(math.ceil(t0 * s.gnss_rate_hz), math.floor(t1 * s.gnss_rate_hz) + 1)
    tg = tg / s.gnss_rate_hz
    poses = flight.poses(tg - s.clock_offset_s)
    antenna = poses[:, :3, 3] + np.einsum("nij,j->ni", poses[:, :3, :3], s.cam_t_antenna_m)
    sig = np.array([s.gnss_sigma_h_m, s.gnss_sigma_h_m, s.gnss_sigma_v_m])
    white = r_white.normal(0.0, 1.0, size=(len(tg), 3)) * sig
    drift_sig = np.array([s.drift_sigma_h_m, s.drift_sigma_h_m, s.drift_sigma_v_m])
    drift = _gauss_markov(r_drift, len(tg), 1.0 / s.gnss_rate_hz, drift_sig, s.drift_tau_s)
    near = conductor_distance_m(flight, sign_map, antenna) < s.conductor_range_m
    burst_off, burst = _bursts(r_burst, tg, near, s)
    if not s.multipath:
        burst_off, burst = np.zeros_like(burst_off), np.zeros_like(burst)
    err = white + drift + burst_off
    lat, lon, h = geodetic_from_enu(sign_map.origin, antenna + err)
    gnss = GnssFixes(
        t_s=tg,
        lat_deg=lat,
        lon_deg=lon,
        height_m=h,
        sigma_h_m=np.full(len(tg), s.gnss_sigma_h_m),
        sigma_v_m=np.full(len(tg), s.gnss_sigma_v_m),
    )
    imu, gb, ab = _simulate_imu(flight, r_imu, t0, t1, body_T_cam, s)
    truth = SimTelemetryTruth(tg, antenna, err, burst, gb, ab, float(s.clock_offset_s))
    gimbal = None
    if s.gimbal_rate_hz > 0:
        gimbal = _simulate_gimbal(flight, rng.spawn(1)[0], t0, t1, s)
    return Telemetry(source="<simulated>", gnss=gnss, imu=imu, gimbal=gimbal), truth


def _simulate_gimbal(
    flight: FlightTruth, rng: np.random.Generator, t0: float, t1: float, s: TelemetrySimSettings
) -> GimbalAngles:
    """The camera's attitude as DJI gimbal angles with noise, over telemetry times [t0, t1]."""
    t = np.arange(math.ceil(t0 * s.gimbal_rate_hz), math.floor(t1 * s.gimbal_rate_hz) + 1)
    t = t / s.gimbal_rate_hz
    angles = np.array([gimbal_from_world_R_cam(R) for R in flight.rotations(t - s.clock_offset_s)])
    angles = angles + rng.normal(0.0, 1.0, angles.shape) * np.asarray(s.gimbal_sigma_deg)
    yaw = (angles[:, 0] + 180.0) % 360.0 - 180.0
    return GimbalAngles(t_s=t, yaw_deg=yaw, pitch_deg=angles[:, 1], roll_deg=angles[:, 2])


def _simulate_imu(
    flight: FlightTruth,
    rng: np.random.Generator,
    t0: float,
    t1: float,
    body_T_cam: np.ndarray,
    s: TelemetrySimSettings,
) -> tuple[ImuSamples, np.ndarray, np.ndarray]:
    """(samples, (I, 3) gyro bias, (I, 3) accel bias) over telemetry times [t0, t1]."""
    dt = 1.0 / s.imu_rate_hz
    ti = np.arange(math.ceil(t0 / dt), math.floor(t1 / dt) + 1) * dt
    gyro, accel = imu_truth(flight, ti - s.clock_offset_s, body_T_cam)
    n = len(ti)
    gb = rng.normal(0.0, s.gyro_bias0, 3) + np.cumsum(
        rng.normal(0.0, s.gyro_bias_rw * math.sqrt(dt), (n, 3)), axis=0
    )
    ab = rng.normal(0.0, s.accel_bias0, 3) + np.cumsum(
        rng.normal(0.0, s.accel_bias_rw * math.sqrt(dt), (n, 3)), axis=0
    )
    gyro = gyro + gb + rng.normal(0.0, s.gyro_noise / math.sqrt(dt), (n, 3))
    accel = accel + ab + rng.normal(0.0, s.accel_noise / math.sqrt(dt), (n, 3))
    return ImuSamples(t_s=ti, gyro_rad_s=gyro, accel_m_s2=accel), gb, ab


def _csv_rows(telemetry: Telemetry) -> list[tuple[float, list[str]]]:
    """(time, cells of the GNSS, IMU and gimbal groups) per sample, empty cells elsewhere."""
    widths = (len(GNSS_COLUMNS) + len(SIGMA_COLUMNS), len(IMU_COLUMNS), len(GIMBAL_COLUMNS))
    rows: list[tuple[float, list[str]]] = []

    def add(t: float, group: int, cells: list[str]) -> None:
        out = [f"{t:.6f}"]
        for g, w in enumerate(widths):
            out += cells if g == group else [""] * w
        rows.append((t, out))

    g = telemetry.gnss
    for k in range(len(g) if g is not None else 0):
        cells = [f"{g.lat_deg[k]:.10f}", f"{g.lon_deg[k]:.10f}", f"{g.height_m[k]:.4f}"]
        add(float(g.t_s[k]), 0, cells + [f"{g.sigma_h_m[k]:.3f}", f"{g.sigma_v_m[k]:.3f}"])
    m = telemetry.imu
    for k in range(len(m) if m is not None else 0):
        cells = [f"{x:.8f}" for x in m.gyro_rad_s[k]] + [f"{x:.7f}" for x in m.accel_m_s2[k]]
        add(float(m.t_s[k]), 1, cells)
    a = telemetry.gimbal
    for k in range(len(a) if a is not None else 0):
        add(float(a.t_s[k]), 2, [f"{x:.4f}" for x in (a.yaw_deg[k], a.pitch_deg[k], a.roll_deg[k])])
    rows.sort(key=lambda r: r[0])
    return rows


def write_telemetry_csv(path: str | Path, telemetry: Telemetry) -> None:
    """Write the telemetry as a CSV ``signpose.io.telemetry_csv`` reads.

    One row per GNSS fix, IMU sample or gimbal sample, in time order; the
    other streams' cells of a row are empty.
    """
    with atomic_write(path) as f:
        f.write(CSV_MAGIC + "\n" + ",".join(ALL_COLUMNS) + "\n")
        for _, cells in _csv_rows(telemetry):
            f.write(",".join(cells) + "\n")


@dataclass(frozen=True)
class SampledFlight(_PosesOfTime):
    """A flight given by its poses on a fine uniform time grid (``FlightTruth``'s interface).

    ``signpose simulate --telemetry`` samples the rendered trajectory's own
    function of time (``sim.flight.telemetry_flight``) at ``rate_hz``, also
    before the first frame and after the last. Between grid times the pose is
    interpolated (translation linearly, rotation along the geodesic); at grid
    times it is the trajectory's own, so the IMU's central differences
    (``imu_truth``, step 1 ms) are exact when the grid is 1 kHz and the sample
    times fall on it (a clock offset in whole milliseconds).

    Attributes:
        duration_s: the video lasts [0, duration_s] [s].
        center / facing / right / up: the site's axes (``site_frame``).
        t0_s: video time of the first grid pose [s].
        rate_hz: grid rate [Hz].
        world_T_cam: (M, 4, 4) poses at t0_s + k / rate_hz.
    """

    duration_s: float
    center: np.ndarray
    facing: np.ndarray
    right: np.ndarray
    up: np.ndarray
    t0_s: float
    rate_hz: float
    world_T_cam: np.ndarray

    def _index(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(grid index i, fraction in [0, 1]) of each time, clamped to the grid."""
        u = (np.atleast_1d(np.asarray(t, float)) - self.t0_s) * self.rate_hz
        u = np.clip(u, 0.0, len(self.world_T_cam) - 1.0)
        i = np.minimum(np.floor(u + 1e-7).astype(int), len(self.world_T_cam) - 2)
        return i, np.clip(u - i, 0.0, 1.0)

    def position(self, t: np.ndarray) -> np.ndarray:
        """(N, 3) camera centres at video times ``t`` (N,) [s]."""
        i, a = self._index(t)
        p = self.world_T_cam[:, :3, 3]
        return p[i] * (1 - a)[:, None] + p[i + 1] * a[:, None]

    def rotations(self, t: np.ndarray) -> np.ndarray:
        """(N, 3, 3) world_R_cam at video times ``t`` (N,) [s]."""
        i, a = self._index(t)
        R = self.world_T_cam[:, :3, :3]
        w = log_so3(np.swapaxes(R[i], 1, 2) @ R[i + 1]) * a[:, None]
        return R[i] @ _exp_so3(w)


def _exp_so3(w: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations of (N, 3) rotation vectors (Rodrigues)."""
    angle = np.linalg.norm(w, axis=1)
    axis = w / np.maximum(angle, 1e-12)[:, None]
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    K -= np.swapaxes(K, 1, 2)
    a = angle[:, None, None]
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * (K @ K)
