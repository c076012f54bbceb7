"""Georeferenced outputs: the trajectory in WGS84 as CSV, GeoJSON and KML.

The track is the ``fused`` method when the run has one, else ``smoothed``;
only its frames with a pose. Positions are the camera centre, converted from
the map's world frame (ENU at the map's ``origin``, ``maps/SCHEMA.md``) by
``signpose.maps.geodesy``; heights are WGS84 ellipsoidal [m]. Sigmas are the
method's marginal position sigmas along east, north, up [m] (empty / null
where the method has none); ``status`` is the pose's token (``ok``, ``weak``,
``bridged``, ``suspect``). The GNSS fixes the fusion used can go beside it
(GeoJSON and KML), on the video's clock.

Files (all written atomically):

* ``trajectory_wgs84.csv``: ``t_s,lat_deg,lon_deg,height_m,sigma_east_m,
  sigma_north_m,sigma_up_m,status`` (one row per pose);
* ``trajectory.geojson`` (RFC 7946: coordinates are ``[lon, lat, height]``):
  a LineString Feature per track and a Point Feature per pose with ``t_s``,
  ``status`` and the sigmas as properties;
* ``trajectory.kml`` (KML 2.2): the track as a LineString and one Placemark
  per pose. KML altitudes are above mean sea level, not the ellipsoid, and
  signpose has no geoid model: placemarks are clamped to the ground and the
  ellipsoidal height is given in each one's description.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import escape

import numpy as np

from signpose.core.errors import InputError
from signpose.core.fileio import atomic_write, ensure_dir
from signpose.estimator.estimate import MethodEstimate
from signpose.estimator.fusion import FusionResult
from signpose.estimator.telemetry import GnssFixes, Telemetry
from signpose.maps.geodesy import GeoOrigin, enu_from_geodetic, geodetic_from_enu
from signpose.maps.loader import SignMap

GEO_METHODS = ("fused", "smoothed")
CSV_NAME = "trajectory_wgs84.csv"
GEOJSON_NAME = "trajectory.geojson"
KML_NAME = "trajectory.kml"
CSV_HEADER = (
    "t_s",
    "lat_deg",
    "lon_deg",
    "height_m",
    "sigma_east_m",
    "sigma_north_m",
    "sigma_up_m",
    "status",
)
GNSS_NAME = "gnss"
# KML colours are aabbggrr.
_KML_COLORS = {"fused": "ff1f77b4", "smoothed": "ffbd7200", GNSS_NAME: "ff3c9cf0"}


@dataclass(frozen=True)
class GeoTrack:
    """A track in WGS84.

    Attributes:
        name: ``fused``, ``smoothed``, ... or ``gnss``.
        stamps_s: (N,) times on the video's clock [s].
        lat_deg, lon_deg, height_m: (N,) WGS84 position, ellipsoidal height [m].
        sigma_enu_m: (N, 3) position sigma along east, north, up [m]; NaN where unknown.
        status: (N,) the pose's status token ("gnss" for fixes, "outlier" for
            rejected ones).
    """

    name: str
    stamps_s: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    height_m: np.ndarray
    sigma_enu_m: np.ndarray
    status: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.stamps_s)


def geo_method(methods: Iterable[str]) -> str | None:
    """The method the geodetic outputs show: ``fused`` if present, else ``smoothed``."""
    names = set(methods)
    return next((m for m in GEO_METHODS if m in names), None)


def method_track(m: MethodEstimate, origin: GeoOrigin) -> GeoTrack:
    """The frames of ``m`` with a pose, in WGS84 (world frame = ENU at ``origin``)."""
    ok = np.asarray(m.valid, bool) & np.all(np.isfinite(m.world_T_cam[:, :3, 3]), axis=1)
    lat, lon, h = geodetic_from_enu(origin, m.world_T_cam[ok, :3, 3])
    status = tuple(s.value for s, keep in zip(m.status, ok, strict=True) if keep)
    sigma = np.asarray(m.sigma_xyz, float)[ok].reshape(-1, 3)
    return GeoTrack(m.name, np.asarray(m.stamps_s, float)[ok], lat, lon, h, sigma, status)


def gnss_track(
    gnss: GnssFixes, clock_offset_s: float = 0.0, outlier: np.ndarray | None = None
) -> GeoTrack:
    """The fixes as a track on the video's clock (``t_s - clock_offset_s``).

    Args:
        outlier: (N,) True for the fixes the fusion rejected, or None.
    """
    n = len(gnss)
    flags = np.zeros(n, bool) if outlier is None else np.asarray(outlier, bool).reshape(n)
    sigma = np.stack([gnss.sigma_h_m, gnss.sigma_h_m, gnss.sigma_v_m], axis=1)
    status = tuple("outlier" if f else GNSS_NAME for f in flags)
    return GeoTrack(
        GNSS_NAME,
        gnss.t_s - clock_offset_s,
        gnss.lat_deg,
        gnss.lon_deg,
        gnss.height_m,
        sigma,
        status,
    )


def fused_clock_and_outliers(
    fusion: FusionResult | None, gnss: GnssFixes, clock_offset_s: float | None = None
) -> tuple[float, np.ndarray | None]:
    """(clock offset [s], (G,) rejected-fix flags or None) of a run's fusion.

    Without a fusion result: the given offset (0 when None) and no flags.
    """
    if fusion is None:
        return (clock_offset_s or 0.0), None
    outlier = np.zeros(len(gnss), bool)
    used = np.asarray(fusion.gnss_used, int)
    outlier[used[np.asarray(fusion.gnss_outlier, bool)]] = True
    return float(fusion.clock.offset_s), outlier


def fusion_summary(fusion: FusionResult) -> str:
    """One line for the user: the clock offset found and the GNSS fixes rejected."""
    c = fusion.clock
    sigma = f" +- {1000 * c.sigma_s:.1f} ms" if math.isfinite(c.sigma_s) else ""
    used, rejected = len(fusion.gnss_used), int(np.sum(fusion.gnss_outlier))
    return (
        f"fused: clock offset {c.offset_s:+.3f} s{sigma} ({c.source}); "
        f"{rejected} of {used} GNSS fixes rejected as outliers"
    )


def _num(x: float, digits: int) -> str:
    return f"{x:.{digits}f}" if math.isfinite(x) else ""


def _json_num(x: float, digits: int) -> float | None:
    return round(float(x), digits) if math.isfinite(x) else None


def csv_text(track: GeoTrack) -> str:
    """``trajectory_wgs84.csv``: header with units, one row per pose (9 decimals ~ 0.1 mm)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_HEADER)
    for i in range(len(track)):
        w.writerow(
            [
                f"{track.stamps_s[i]:.9f}",
                f"{track.lat_deg[i]:.9f}",
                f"{track.lon_deg[i]:.9f}",
                f"{track.height_m[i]:.4f}",
                *(_num(v, 4) for v in track.sigma_enu_m[i]),
                track.status[i],
            ]
        )
    return buf.getvalue()


def _coords(track: GeoTrack, i: int) -> list[float]:
    return [
        round(float(track.lon_deg[i]), 9),
        round(float(track.lat_deg[i]), 9),
        round(float(track.height_m[i]), 4),
    ]


def geojson_dict(track: GeoTrack, others: Sequence[GeoTrack] = ()) -> dict:
    """A GeoJSON FeatureCollection: a LineString per track, a Point per pose of ``track``."""
    features = []
    for t in (track, *others):
        if len(t) < 2:
            continue
        features.append(
            {
                "type": "Feature",
                "geometry": {
                    "type": "LineString",
                    "coordinates": [_coords(t, i) for i in range(len(t))],
                },
                "properties": {
                    "track": t.name,
                    "poses": len(t),
                    "start_s": float(t.stamps_s[0]),
                    "end_s": float(t.stamps_s[-1]),
                },
            }
        )
    for i in range(len(track)):
        e, n, u = (_json_num(v, 4) for v in track.sigma_enu_m[i])
        features.append(
            {
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": _coords(track, i)},
                "properties": {
                    "track": track.name,
                    "t_s": float(track.stamps_s[i]),
                    "status": track.status[i],
                    "sigma_east_m": e,
                    "sigma_north_m": n,
                    "sigma_up_m": u,
                },
            }
        )
    return {"type": "FeatureCollection", "features": features}


def _kml_coords(t: GeoTrack) -> str:
    return " ".join(
        f"{t.lon_deg[i]:.9f},{t.lat_deg[i]:.9f},{t.height_m[i]:.3f}" for i in range(len(t))
    )


def kml_text(track: GeoTrack, others: Sequence[GeoTrack] = (), title: str = "signpose") -> str:
    """KML 2.2: a LineString per track, a Placemark per pose of ``track`` (clamped to ground)."""
    parts = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        '<kml xmlns="http://www.opengis.net/kml/2.2">',
        f"<Document><name>{escape(title)}</name>",
    ]
    for t in (track, *others):
        color = _KML_COLORS.get(t.name, "ff808080")
        parts.append(
            f'<Style id="{t.name}"><LineStyle><color>{color}</color><width>3</width></LineStyle>'
            f"<IconStyle><color>{color}</color><scale>0.4</scale></IconStyle></Style>"
        )
    for t in (track, *others):
        if len(t) < 2:
            continue
        parts.append(
            f"<Placemark><name>{escape(t.name)}</name><styleUrl>#{t.name}</styleUrl>"
            "<LineString><tessellate>1</tessellate><altitudeMode>clampToGround</altitudeMode>"
            f"<coordinates>{_kml_coords(t)}</coordinates></LineString></Placemark>"
        )
    parts.append(f"<Folder><name>{escape(track.name)} poses</name>")
    for i in range(len(track)):
        sig = ", ".join(_num(v, 3) or "n/a" for v in track.sigma_enu_m[i])
        desc = (
            f"t {track.stamps_s[i]:.3f} s, status {track.status[i]}, ellipsoidal height "
            f"{track.height_m[i]:.3f} m, sigma E/N/U {sig} m"
        )
        parts.append(
            f"<Placemark><name>{i}</name><description>{escape(desc)}</description>"
            f"<styleUrl>#{track.name}</styleUrl><Point><altitudeMode>clampToGround</altitudeMode>"
            f"<coordinates>{track.lon_deg[i]:.9f},{track.lat_deg[i]:.9f},"
            f"{track.height_m[i]:.3f}</coordinates></Point></Placemark>"
        )
    parts += ["</Folder>", "</Document>", "</kml>", ""]
    return "\n".join(parts)


def write_geo_files(
    out_dir: str | Path, track: GeoTrack, others: Sequence[GeoTrack] = ()
) -> list[Path]:
    """``trajectory_wgs84.csv``, ``trajectory.geojson`` and ``trajectory.kml`` in ``out_dir``."""
    out = ensure_dir(out_dir)
    texts = {
        CSV_NAME: csv_text(track),
        GEOJSON_NAME: json.dumps(geojson_dict(track, others), indent=1) + "\n",
        KML_NAME: kml_text(track, others),
    }
    written = []
    for name, text in texts.items():
        with atomic_write(out / name) as f:
            f.write(text)
        written.append(out / name)
    return written


def _no_origin(sign_map: SignMap) -> str:
    return (
        f"{sign_map.source or 'the map'}: geodetic outputs (WGS84 CSV, GeoJSON, KML, "
        "LocationFix) need the map's origin: add origin: {lat_deg: .., lon_deg: .., "
        "height_m: ..} (maps/SCHEMA.md)"
    )


def check_geo_request(sign_map: SignMap, required: bool) -> None:
    """Refuse at once a run that asks for geodetic outputs (``--geo``) with a map without origin."""
    if required and sign_map.origin is None:
        raise InputError(_no_origin(sign_map))


def check_anchor(sign_map: SignMap, telemetry: Telemetry) -> None:
    """Refuse GNSS fixes with a map that has no origin to put them in its frame."""
    if telemetry.gnss is not None and sign_map.origin is None:
        raise InputError(
            f"{sign_map.source or 'the map'}: the map has no 'origin' (its WGS84 anchor) to put "
            f"the GNSS fixes of {telemetry.source} in its frame; add origin: {{lat_deg: .., "
            "lon_deg: .., height_m: ..} (maps/SCHEMA.md)"
        )


@dataclass(frozen=True)
class RunGeo:
    """A run's georeferenced tracks.

    Attributes:
        track: the fused (else smoothed) track in WGS84, or None (see ``note``).
        gnss: the fixes on the video's clock, or None without GNSS or origin.
        gnss_world_m: (G, 3) the fixes in the world frame (ENU at the origin) [m], or None.
        note: why there are no geodetic outputs ("" when there are).
    """

    track: GeoTrack | None
    gnss: GeoTrack | None = None
    gnss_world_m: np.ndarray | None = None
    note: str = ""

    def tracks(self) -> tuple[GeoTrack, ...]:
        """The tracks to draw: the estimate first, then the fixes."""
        return tuple(t for t in (self.track, self.gnss) if t is not None)


def run_geo(
    sign_map: SignMap,
    methods: dict[str, MethodEstimate],
    gnss: GnssFixes | None = None,
    clock_offset_s: float = 0.0,
    outlier: np.ndarray | None = None,
    *,
    required: bool = False,
) -> RunGeo:
    """The georeferenced tracks of a run, or none and a note saying why.

    Args:
        methods: the run's methods by name (``EstimateResult.methods``).
        gnss: the telemetry's fixes (drawn beside the estimate), or None.
        clock_offset_s: telemetry minus video time [s] (found or given).
        outlier: (G,) True for the fixes the fusion rejected, or None.
        required: the user asked for them (``--geo``): a map without origin
            is then an InputError instead of a note.
    """
    check_geo_request(sign_map, required)
    if sign_map.origin is None:
        return RunGeo(None, note=_no_origin(sign_map))
    name = geo_method(methods)
    track = method_track(methods[name], sign_map.origin) if name is not None else None
    if track is not None and len(track) == 0:
        track = None
    fixes = world = None
    if gnss is not None and len(gnss):
        fixes = gnss_track(gnss, clock_offset_s, outlier)
        world = enu_from_geodetic(sign_map.origin, gnss.lat_deg, gnss.lon_deg, gnss.height_m)
    note = "" if track is not None else "no fused or smoothed pose: geodetic outputs skipped"
    return RunGeo(track, fixes, world, note)


def write_run_geo(out_dir: str | Path, geo: RunGeo) -> list[Path]:
    """The geodetic files of a run (none when it has no track)."""
    if geo.track is None:
        return []
    return write_geo_files(out_dir, geo.track, () if geo.gnss is None else (geo.gnss,))
