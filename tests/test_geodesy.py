"""The map's geodetic anchor: ENU at the origin, signs in WGS84, bad origins refused."""

import math

import numpy as np
import pytest
from conftest import valid_map_dict, write_yaml
from signpose.maps.geodesy import GeoOrigin, enu_from_geodetic, geodetic_from_enu
from signpose.maps.loader import load_map, parse_map, write_map

from signpose.core.errors import InputError

ORIGIN = {"lat_deg": 47.3769, "lon_deg": 8.5417, "height_m": 512.0}


def test_enu_axes_point_east_north_up():
    o = GeoOrigin(**ORIGIN)
    # 1e-4 deg of latitude is about 11.1 m north; of longitude, cos(lat) times that east.
    p = enu_from_geodetic(
        o, [o.lat_deg + 1e-4, o.lat_deg], [o.lon_deg, o.lon_deg + 1e-4], [512.0, 522.0]
    )
    assert p.shape == (2, 3)
    assert abs(p[0, 0]) < 1e-6 and p[0, 1] == pytest.approx(11.12, abs=0.02)
    east = 11.13 * math.cos(math.radians(o.lat_deg))
    assert p[1, 0] == pytest.approx(east, abs=0.02) and abs(p[1, 1]) < 1e-3
    assert p[1, 2] == pytest.approx(10.0, abs=1e-3)


def test_geodetic_round_trip_is_below_a_millimetre():
    o = GeoOrigin(**ORIGIN)
    rng = np.random.default_rng(3)
    enu = rng.uniform(-2000.0, 2000.0, size=(50, 3))
    lat, lon, h = geodetic_from_enu(o, enu)
    back = enu_from_geodetic(o, lat, lon, h)
    np.testing.assert_allclose(back, enu, atol=1e-3)


def test_origin_round_trips_through_the_map_file(tmp_path):
    data = valid_map_dict() | {"origin": dict(ORIGIN)}
    m = parse_map(data, "m.yaml")
    assert m.origin == GeoOrigin(**ORIGIN)
    write_map(tmp_path / "m.yaml", m)
    assert load_map(tmp_path / "m.yaml").origin == m.origin
    assert parse_map(valid_map_dict(), "m.yaml").origin is None


def test_a_sign_given_in_wgs84_is_converted_to_enu_at_load():
    o = GeoOrigin(**ORIGIN)
    want = np.array([3.0, -4.0, 20.0])
    lat, lon, h = geodetic_from_enu(o, want[None])
    data = valid_map_dict() | {"origin": dict(ORIGIN)}
    del data["signs"][2]["center_m"]
    data["signs"][2]["center_wgs84"] = [float(lat[0]), float(lon[0]), float(h[0])]
    m = parse_map(data, "m.yaml")
    np.testing.assert_allclose(m.sign("0010").center_m, want, atol=1e-4)


BAD = [
    ({"origin": [47.0, 8.0, 500.0]}, "field 'origin' must be a mapping"),
    ({"origin": {"lat_deg": 47.0, "lon_deg": 8.0}}, "origin: missing field 'height_m'"),
    ({"origin": ORIGIN | {"lat_deg": 95.0}}, "origin: field 'lat_deg' must be a finite number"),
    ({"origin": ORIGIN | {"lon_deg": "east"}}, "origin: field 'lon_deg' must be a number"),
    ({"origin": ORIGIN | {"height_m": math.inf}}, "origin: field 'height_m' must be a finite"),
    ({"origin": ORIGIN | {"alt": 3}}, "origin: unknown field 'alt'"),
    ({"origin": None}, "field 'origin' must be a mapping"),
]


@pytest.mark.parametrize(("extra", "expect"), BAD)
def test_a_bad_origin_is_one_line_naming_the_file_and_field(tmp_path, extra, expect):
    path = write_yaml(tmp_path / "site.yaml", valid_map_dict() | extra)
    with pytest.raises(InputError) as exc:
        load_map(path)
    msg = str(exc.value)
    assert msg.startswith(f"{path}: ") and expect in msg and "\n" not in msg


def test_center_wgs84_without_an_origin_or_with_center_m_is_refused(tmp_path):
    data = valid_map_dict()
    data["signs"][2]["center_wgs84"] = [47.0, 8.0, 500.0]
    with pytest.raises(InputError, match="not both"):
        parse_map(data, "m.yaml")
    del data["signs"][2]["center_m"]
    with pytest.raises(InputError, match="'center_wgs84' needs the map's 'origin'"):
        parse_map(data, "m.yaml")
