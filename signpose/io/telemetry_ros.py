"""Telemetry topics of a recorded log (MCAP, rosbag2): fixes and IMU samples.

Read through the log readers (``signpose.io.mcap_read`` / ``rosbag``), which
decode ROS 2 CDR with the ``rosbags`` typestore:

* ``sensor_msgs/msg/NavSatFix``: ``latitude``/``longitude`` [deg],
  ``altitude`` [m above the WGS84 ellipsoid, as the message defines it],
  ``position_covariance`` (ENU, row-major [m^2]) for the sigmas unless its
  type is 0 (unknown), ``status.status`` < 0 (no fix) skipped as ``no_fix``;
  ``foxglove.LocationFix`` (JSON or CDR) alike, so a ``result.mcap`` reads back.
* ``sensor_msgs/msg/Imu``: ``angular_velocity`` [rad/s] and
  ``linear_acceleration`` [m/s^2] in the message's frame, taken as the body
  frame (REP 103: FLU); a message whose covariance starts with -1 (the field
  is not measured) is skipped (``no_gyro`` / ``no_accel``).

Times are the header stamps (the log time where a stamp is zero), in seconds:
the clock of the log's image stamps.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

import numpy as np

from signpose.core.errors import InputError
from signpose.estimator.telemetry import Telemetry
from signpose.io.messages import LogChannel, LogMessage, MessageLog, message_stamp_ns
from signpose.io.telemetry_build import count, fixes_from_rows, imu_from_rows, reasons

NAVSATFIX = "sensor_msgs/msg/NavSatFix"
LOCATION_FIX = "foxglove.LocationFix"
IMU = "sensor_msgs/msg/Imu"
GNSS_SCHEMAS = (NAVSATFIX, LOCATION_FIX)
TELEMETRY_SCHEMAS = (*GNSS_SCHEMAS, IMU)
STATUS_NO_FIX = -1
COVARIANCE_UNKNOWN = 0


def _get(msg: Any, key: str, default=None):
    if isinstance(msg, dict):
        return msg.get(key, default)
    return getattr(msg, key, default)


def _xyz(v: Any) -> list[float]:
    return [float(_get(v, k, math.nan)) for k in ("x", "y", "z")]


def _stamp_s(msg: LogMessage) -> float:
    try:
        ns = message_stamp_ns(msg.schema_name, msg.decoded)
    except ValueError:
        return math.nan
    return (ns if ns else msg.log_time_ns) * 1e-9


def _fix_row(msg: LogMessage, skipped: dict[str, int]) -> list[float] | None:
    m = msg.decoded
    status = _get(m, "status")
    if status is not None and int(_get(status, "status", 0)) <= STATUS_NO_FIX:
        count(skipped, "no_fix")
        return None
    cov = _get(m, "position_covariance")
    cov = np.asarray([] if cov is None else cov, dtype=float).reshape(-1)
    kind = int(_get(m, "position_covariance_type", COVARIANCE_UNKNOWN) or 0)
    sh = sv = math.nan  # the reader's default
    if kind != COVARIANCE_UNKNOWN and cov.size == 9 and cov[0] > 0 and cov[4] > 0 and cov[8] > 0:
        sh, sv = math.sqrt(0.5 * (cov[0] + cov[4])), math.sqrt(cov[8])
    lat = float(_get(m, "latitude", math.nan))
    lon = float(_get(m, "longitude", math.nan))
    return [_stamp_s(msg), lat, lon, float(_get(m, "altitude", math.nan)), sh, sv]


def _imu_row(msg: LogMessage, skipped: dict[str, int]) -> list[float] | None:
    m = msg.decoded
    for field, reason in (("angular_velocity", "no_gyro"), ("linear_acceleration", "no_accel")):
        cov = _get(m, f"{field}_covariance")
        if cov is not None and len(cov) and float(cov[0]) == -1.0:
            count(skipped, reason)
            return None
    return [
        _stamp_s(msg),
        *_xyz(_get(m, "angular_velocity")),
        *_xyz(_get(m, "linear_acceleration")),
    ]


def telemetry_channels(
    source: str, channels: Iterable[LogChannel], topics: Iterable[str] | None
) -> tuple[LogChannel | None, LogChannel | None]:
    """(GNSS channel, IMU channel) of a log: the ones named in ``topics``, else the only ones.

    Raises:
        InputError: a named topic is missing or not telemetry; several GNSS or
            IMU topics and none named.
    """
    channels = tuple(channels)
    by_topic = {c.topic: c for c in channels}
    if topics:
        chosen = []
        for t in topics:
            c = by_topic.get(t)
            if c is None or c.schema_name not in TELEMETRY_SCHEMAS:
                have = ", ".join(
                    c.describe() for c in channels if c.schema_name in TELEMETRY_SCHEMAS
                )
                raise InputError(
                    f"{source}: --telemetry-topic {t}: not a NavSatFix / LocationFix / Imu "
                    f"topic of the log (telemetry topics: {have or 'none'})"
                )
            chosen.append(c)
        channels = tuple(chosen)
    gnss = [c for c in channels if c.schema_name in GNSS_SCHEMAS]
    imu = [c for c in channels if c.schema_name == IMU]
    for kind, found in (("GNSS", gnss), ("IMU", imu)):
        if len(found) > 1:
            raise InputError(
                f"{source}: {len(found)} {kind} topics ({', '.join(c.topic for c in found)}); "
                "name one with --telemetry-topic"
            )
    return (gnss[0] if gnss else None), (imu[0] if imu else None)


def read_log_telemetry(log: MessageLog, topics: Iterable[str] | None = None) -> Telemetry:
    """The GNSS and IMU topics of a log as ``Telemetry``.

    Raises:
        InputError: no telemetry topic (or an ambiguous one), or no usable sample.
    """
    source = str(log.path)
    gnss_ch, imu_ch = telemetry_channels(source, log.channels, topics)
    if gnss_ch is None and imu_ch is None:
        raise InputError(
            f"{source}: no sensor_msgs/msg/NavSatFix, foxglove.LocationFix or "
            "sensor_msgs/msg/Imu topic in the log; pass a telemetry file with --telemetry"
        )
    skipped: dict[str, int] = {}
    fixes, samples = [], []
    wanted = [c.topic for c in (gnss_ch, imu_ch) if c is not None]
    for msg in log.messages(wanted):
        if msg.error:
            count(skipped, "garbled")
            continue
        is_gnss = gnss_ch is not None and msg.topic == gnss_ch.topic
        try:
            row = _fix_row(msg, skipped) if is_gnss else _imu_row(msg, skipped)
        except (TypeError, ValueError, OverflowError):  # a field that is not a number
            count(skipped, "garbled")
            continue
        if row is not None:
            (fixes if is_gnss else samples).append(row)
    if log.problem:
        count(skipped, "truncated")
    gnss = fixes_from_rows(fixes, skipped)
    imu = imu_from_rows(samples, skipped)
    if gnss is None and imu is None:
        why = reasons(skipped) or "no messages"
        raise InputError(f"{source}: the telemetry topics hold no usable sample ({why})")
    return Telemetry(source=source, gnss=gnss, imu=imu, skipped=skipped)
