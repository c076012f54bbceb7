"""WGS84 <-> the map's local frame (issue 17).

A map with an ``origin`` has a local frame that is East-North-Up (ENU) at
that origin: x east, y north, z up along the ellipsoid normal, metres. The
conversions are pymap3d's (WGS84 ellipsoid, ellipsoidal heights).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pymap3d


@dataclass(frozen=True)
class GeoOrigin:
    """The WGS84 point at which the map's ENU frame is anchored.

    Attributes:
        lat_deg: latitude [deg], -90..90.
        lon_deg: longitude [deg], -180..180.
        height_m: ellipsoidal height [m] (not above mean sea level).
    """

    lat_deg: float
    lon_deg: float
    height_m: float

    def __post_init__(self) -> None:
        for name in ("lat_deg", "lon_deg", "height_m"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"GeoOrigin.{name} must be finite")
        if abs(self.lat_deg) > 90.0 or abs(self.lon_deg) > 180.0:
            raise ValueError("GeoOrigin: latitude within +-90, longitude within +-180 degrees")


def enu_from_geodetic(origin: GeoOrigin, lat_deg, lon_deg, height_m) -> np.ndarray:
    """(N, 3) ENU positions [m] of WGS84 points (arrays or scalars of equal length)."""
    lat = np.atleast_1d(np.asarray(lat_deg, dtype=float))
    lon = np.atleast_1d(np.asarray(lon_deg, dtype=float))
    h = np.atleast_1d(np.asarray(height_m, dtype=float))
    e, n, u = pymap3d.geodetic2enu(
        lat, lon, h, origin.lat_deg, origin.lon_deg, origin.height_m, deg=True
    )
    return np.stack([np.asarray(e), np.asarray(n), np.asarray(u)], axis=1).reshape(-1, 3)


def geodetic_from_enu(origin: GeoOrigin, enu_m) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """WGS84 (lat_deg, lon_deg, height_m), each (N,), of (N, 3) ENU positions [m]."""
    p = np.asarray(enu_m, dtype=float).reshape(-1, 3)
    lat, lon, h = pymap3d.enu2geodetic(
        p[:, 0], p[:, 1], p[:, 2], origin.lat_deg, origin.lon_deg, origin.height_m, deg=True
    )
    return np.asarray(lat, float), np.asarray(lon, float), np.asarray(h, float)
