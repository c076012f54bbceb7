"""DJI ``.SRT`` sidecars in: one subtitle per video frame with the drone's fix.

Layouts read (fields are ``[key: value]`` groups, spaces around the colon or
not, several ``key: value`` pairs in one group allowed):

* current (Mini 3 / Mavic 3 / Air 2S ...)::

      [latitude: 47.376912] [longitude: 8.541710] [rel_alt: 12.300 abs_alt: 524.300]
      [gb_yaw: -157.8 gb_pitch: -45.0 gb_roll: 0.0]      (gimbal, where present)

* older (Mavic 2 / Phantom 4, longitude spelt ``longtitude``)::

      [latitude : 47.376912] [longtitude : 8.541710] [altitude: 524.300000]

  and the grouped gimbal form ``[Gimbal: Yaw:-157.8, Pitch:-45.0, Roll:0.0]``.

Time: the subtitle's start time (``00:00:01,033 --> ...``) is the frame's time
in the video, so ``t_s = video_start_s + start``: the SRT is on the video's
own clock (no offset, unless the recorder's is off). Height: ``abs_alt`` (or
the older ``altitude``) is taken as the ellipsoidal height; DJI does not say
which datum it uses (often mean sea level: tens of metres from the ellipsoid),
so its vertical sigma (``SIGMA_V_M``, 30 m) lets it barely weigh against the
signs and keeps a geoid-sized offset from reading as an outlier.
``rel_alt`` (above take-off) alone is not a height and such a subtitle is
``garbled``. A subtitle without a readable latitude, longitude and height is
skipped and counted (``garbled``); one at (0, 0) is ``no_fix``.
"""

from __future__ import annotations

import re
from pathlib import Path

from signpose.core.errors import InputError
from signpose.estimator.telemetry import Telemetry
from signpose.io.telemetry_build import count, fixes_from_rows, gimbal_from_rows, reasons

MAX_SRT_BYTES = 512 << 20
SIGMA_H_M = 2.0
SIGMA_V_M = 30.0
_TIMECODE = re.compile(r"^\s*(\d+):(\d{1,2}):(\d{1,2})[,.](\d{1,3})\s*-->")
_GROUP = re.compile(r"\[([^\[\]]*)\]")
_PAIR = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)\s*:\s*([^\s,\]]+)")
_NAMED_GROUP = re.compile(r"^\s*([A-Za-z]+)\s*:\s*([A-Za-z_]+\s*:.*)$")
_LAT_KEYS = ("latitude",)
_LON_KEYS = ("longitude", "longtitude")
_HEIGHT_KEYS = ("abs_alt", "altitude")
_GIMBAL_KEYS = {
    "yaw": ("gb_yaw", "gimbal_yaw"),
    "pitch": ("gb_pitch", "gimbal_pitch"),
    "roll": ("gb_roll", "gimbal_roll"),
}


def subtitle_fields(body: str) -> dict[str, str]:
    """The ``[key: value]`` fields of one subtitle's text, keys lowercase.

    A grouped field ``[Gimbal: Yaw:1.0, Pitch:2.0]`` gives ``gimbal_yaw``,
    ``gimbal_pitch``. A key seen twice keeps its first value.
    """
    fields: dict[str, str] = {}
    for group in _GROUP.findall(body):
        prefix = ""
        named = _NAMED_GROUP.match(group)
        if named:
            prefix, group = named.group(1).lower() + "_", named.group(2)
        for key, value in _PAIR.findall(group):
            fields.setdefault(prefix + key.lower(), value)
    return fields


def _number(fields: dict[str, str], keys: tuple[str, ...]) -> float | None:
    """The first of ``keys`` present, as a float; None when absent or not a number."""
    for key in keys:
        if key in fields:
            try:
                return float(fields[key])
            except ValueError:
                return None
    return None


def _subtitles(text: str) -> list[tuple[float, str]]:
    """(start time [s], body text) of every subtitle, in file order."""
    cues: list[tuple[float, list[str]]] = []
    for line in text.splitlines():
        m = _TIMECODE.match(line)
        if m:
            h, mi, s, ms = m.groups()
            start = int(h) * 3600 + int(mi) * 60 + int(s) + int(ms.ljust(3, "0")) / 1000.0
            cues.append((start, []))
        elif cues:
            cues[-1][1].append(line)
    return [(t, "\n".join(body)) for t, body in cues]


def _read_text(p: Path) -> str:
    try:
        size = p.stat().st_size
        if size > MAX_SRT_BYTES:
            raise InputError(f"{p}: {size} bytes is too large for an SRT sidecar; pass the .SRT")
        return p.read_bytes().decode("utf-8-sig", errors="replace")
    except FileNotFoundError:
        raise InputError(f"{p}: telemetry file not found") from None
    except OSError as exc:
        raise InputError(f"{p}: cannot read telemetry file ({exc.strerror})") from None


def read_srt(path: str | Path, video_start_s: float = 0.0) -> Telemetry:
    """Read a DJI SRT sidecar.

    Args:
        path: the ``.SRT`` file.
        video_start_s: time of the video's first frame on the video's clock [s]
            (the frames' stamps); added to each subtitle's start time.

    Raises:
        InputError: not an SRT, or no subtitle with a readable fix.
    """
    p = Path(path)
    cues = _subtitles(_read_text(p))
    if not cues:
        raise InputError(
            f"{p}: not an SRT sidecar (no subtitle time 'hh:mm:ss,mmm --> ...'); "
            "pass the drone's .SRT file"
        )
    skipped: dict[str, int] = {}
    rows, gimbal_rows = [], []
    for start, body in cues:
        fields = subtitle_fields(body)
        t = video_start_s + start
        angles = [_number(fields, keys) for keys in _GIMBAL_KEYS.values()]
        if all(a is not None for a in angles):  # the gimbal's reading needs no fix
            gimbal_rows.append((t, *angles))
        lat, lon = _number(fields, _LAT_KEYS), _number(fields, _LON_KEYS)
        height = _number(fields, _HEIGHT_KEYS)
        if lat is None or lon is None or height is None:
            count(skipped, "garbled")
            continue
        rows.append((t, lat, lon, height, SIGMA_H_M, SIGMA_V_M))
    gnss = fixes_from_rows(rows, skipped)
    if gnss is None:
        raise InputError(
            f"{p}: none of its {len(cues)} subtitles has a readable fix ({reasons(skipped)}); "
            "expected [latitude: ..] [longitude: ..] [abs_alt: ..] or the older [altitude: ..]"
        )
    gimbal = gimbal_from_rows(gimbal_rows, skipped)
    return Telemetry(source=str(p), gnss=gnss, gimbal=gimbal, skipped=skipped, clock_is_video=True)
