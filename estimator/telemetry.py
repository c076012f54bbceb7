"""The drone's own sensors, as the estimator takes them (issue 17).

Readers of each telemetry format (``signpose.io.telemetry*``) build one
``Telemetry``; the simulator (``signpose.sim.telemetry``) writes files those
readers read; the fusion (``signpose.estimator.fusion``) adds the samples to
the smoother's graph.

Clocks: every ``t_s`` is on the telemetry's own clock [s]. A video frame
stamped ``t_video_s`` was exposed at telemetry time
``t_video_s + clock_offset_s`` (the offset is estimated, or given with
``--telemetry-offset``).

Frames: GNSS fixes are WGS84 (latitude, longitude in degrees, ellipsoidal
height in metres); they reach the map's local frame (ENU at the map's
``origin``) through ``signpose.maps.geodesy``. IMU samples are in the IMU's
body frame (``body``: x forward, y left, z up, FLU); ``body_T_cam`` is the
camera's pose in it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class GnssFixes:
    """GNSS antenna positions.

    Attributes:
        t_s: (N,) telemetry time of each fix [s], strictly increasing.
        lat_deg: (N,) WGS84 latitude [deg].
        lon_deg: (N,) WGS84 longitude [deg].
        height_m: (N,) WGS84 ellipsoidal height [m].
        sigma_h_m: (N,) claimed horizontal standard deviation [m] (the
            reader's default where the format has none).
        sigma_v_m: (N,) claimed vertical standard deviation [m].
    """

    t_s: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    height_m: np.ndarray
    sigma_h_m: np.ndarray
    sigma_v_m: np.ndarray

    def __len__(self) -> int:
        return len(self.t_s)


@dataclass(frozen=True)
class ImuSamples:
    """Gyroscope and accelerometer samples in the IMU body frame (FLU).

    Attributes:
        t_s: (N,) telemetry time of each sample [s], strictly increasing.
        gyro_rad_s: (N, 3) angular rate of body in body [rad/s].
        accel_m_s2: (N, 3) specific force in body [m/s^2] (about +9.81 on z at rest).
    """

    t_s: np.ndarray
    gyro_rad_s: np.ndarray
    accel_m_s2: np.ndarray

    def __len__(self) -> int:
        return len(self.t_s)


@dataclass(frozen=True)
class GimbalAngles:
    """Camera attitude the drone reports (gimbal yaw/pitch/roll, DJI convention).

    Attributes:
        t_s: (N,) telemetry time [s].
        yaw_deg: (N,) heading from north, clockwise [deg].
        pitch_deg: (N,) [deg], negative looking down.
        roll_deg: (N,) [deg].
    """

    t_s: np.ndarray
    yaw_deg: np.ndarray
    pitch_deg: np.ndarray
    roll_deg: np.ndarray

    def __len__(self) -> int:
        return len(self.t_s)


@dataclass(frozen=True)
class Telemetry:
    """What one telemetry file holds.

    Attributes:
        source: the file it was read from (for messages).
        gnss: the fixes, or None when the file has none.
        imu: the IMU samples, or None.
        gimbal: gimbal angles, or None.
        skipped: samples dropped by the reader, counted by reason
            (``"garbled"``, ``"gap"``, ``"non_finite"``, ...): never a NaN downstream.
        clock_is_video: the times are on the video's own clock by construction
            (a DJI SRT sidecar: one subtitle per frame), so the offset is 0
            unless one is given; not estimated.
    """

    source: str
    gnss: GnssFixes | None = None
    imu: ImuSamples | None = None
    gimbal: GimbalAngles | None = None
    skipped: dict[str, int] = field(default_factory=dict)
    clock_is_video: bool = False

    def span_s(self) -> tuple[float, float] | None:
        """(first, last) telemetry time over all streams [s], or None when empty."""
        ts = [s.t_s for s in (self.gnss, self.imu, self.gimbal) if s is not None and len(s)]
        if not ts:
            return None
        return float(min(t[0] for t in ts)), float(max(t[-1] for t in ts))
