"""Georeferenced outputs: WGS84 CSV, GeoJSON, KML and foxglove.LocationFix in result.mcap."""

import csv
import json
import xml.etree.ElementTree as ET
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from conftest import valid_map_dict
from signpose.estimator.estimate import MethodEstimate
from signpose.estimator.status import PoseStatus
from signpose.estimator.telemetry import GnssFixes
from signpose.estimator.trajectory import Trajectory
from signpose.frontend.observations import FrameObservations
from signpose.maps.geodesy import GeoOrigin, enu_from_geodetic
from signpose.maps.loader import parse_map

from signpose.core.errors import InputError
from signpose.io import mcap as mcap_io
from signpose.io.geo_out import (
    CSV_HEADER,
    geo_method,
    gnss_track,
    method_track,
    run_geo,
    write_run_geo,
)
from signpose.io.mcap_write import GNSS_FIX_TOPIC, write_result_mcap
from signpose.io.telemetry import read_telemetry
from signpose.plots import plot_gnss_track

ORIGIN = {"lat_deg": 47.3769, "lon_deg": 8.5417, "height_m": 512.0}
REFERENCE = Path(__file__).resolve().parents[2] / "shared" / "reference" / "foxglove-jsonschema"
T0_S = 1_700_000_000.0
KML = "{http://www.opengis.net/kml/2.2}"


def _method(name: str = "fused", n: int = 12) -> MethodEstimate:
    T = np.tile(np.eye(4), (n, 1, 1))
    T[:, 0, 3] = np.linspace(-20.0, 25.0, n)  # east
    T[:, 1, 3] = 8.0 + 0.5 * np.arange(n)  # north
    T[:, 2, 3] = 15.0
    valid = np.ones(n, bool)
    valid[3] = False  # no pose: left out
    sigma = np.full((n, 3), 0.02)
    sigma[5] = np.nan  # unknown: empty cell / null, never "nan"
    status = [PoseStatus.OK] * n
    status[7] = PoseStatus.BRIDGED
    stamps = T0_S + 0.1 * np.arange(n)
    return MethodEstimate(name, stamps, T, valid, sigma, np.full(n, 3), tuple(status))


def _map(with_origin: bool = True):
    data = valid_map_dict() | ({"origin": dict(ORIGIN)} if with_origin else {})
    return parse_map(data, "site.yaml")


def test_the_track_goes_to_wgs84_and_back_within_a_millimetre():
    m = _method()
    origin = GeoOrigin(**ORIGIN)
    track = method_track(m, origin)
    assert len(track) == 11 and track.status[6] == "bridged"
    back = enu_from_geodetic(origin, track.lat_deg, track.lon_deg, track.height_m)
    np.testing.assert_allclose(back, m.world_T_cam[m.valid, :3, 3], atol=1e-3)
    assert track.lat_deg[-1] > track.lat_deg[0] and track.lon_deg[-1] > track.lon_deg[0]
    assert geo_method(["baseline", "smoothed", "fused"]) == "fused"
    assert geo_method(["baseline", "smoothed"]) == "smoothed"
    assert geo_method(["baseline"]) is None


def test_csv_geojson_and_kml_hold_the_same_poses_without_nan(tmp_path):
    m = _method()
    gnss = GnssFixes(
        T0_S + 0.2 * np.arange(5) + 0.3,
        np.full(5, 47.377),
        8.5417 + 1e-5 * np.arange(5),
        np.full(5, 530.0),
        np.full(5, 1.5),
        np.full(5, 3.0),
    )
    methods = {"smoothed": _method("smoothed"), "fused": m}
    geo = run_geo(_map(), methods, gnss, 0.3, outlier=np.array([0, 0, 1, 0, 0], bool))
    assert geo.note == "" and geo.track.name == "fused" and geo.gnss.status[2] == "outlier"
    files = write_run_geo(tmp_path, geo)
    assert [p.name for p in files] == [
        "trajectory_wgs84.csv",
        "trajectory.geojson",
        "trajectory.kml",
    ]
    rows = list(csv.reader((tmp_path / "trajectory_wgs84.csv").open()))
    assert tuple(rows[0]) == CSV_HEADER
    assert len(rows) == 12 and "nan" not in (tmp_path / "trajectory_wgs84.csv").read_text().lower()
    assert rows[5][4:7] == ["", "", ""] and rows[1][4] == "0.0200"
    lat = np.array([float(r[1]) for r in rows[1:]])

    gj = json.loads((tmp_path / "trajectory.geojson").read_text())
    lines = [f for f in gj["features"] if f["geometry"]["type"] == "LineString"]
    points = [f for f in gj["features"] if f["geometry"]["type"] == "Point"]
    assert [f["properties"]["track"] for f in lines] == ["fused", "gnss"]
    assert len(points) == 11
    lon0, lat0, _ = points[0]["geometry"]["coordinates"]  # RFC 7946: longitude first
    assert lat0 == pytest.approx(lat[0], abs=1e-9) and 8.0 < lon0 < 9.0
    assert points[4]["properties"]["sigma_east_m"] is None
    assert points[6]["properties"]["status"] == "bridged"
    np.testing.assert_allclose(lines[1]["properties"]["start_s"], T0_S, atol=1e-6)  # video clock

    root = ET.parse(tmp_path / "trajectory.kml").getroot()
    marks = root.iter(f"{KML}Placemark")
    names = [p.find(f"{KML}name").text for p in marks]
    assert names[:2] == ["fused", "gnss"] and len(names) == 2 + 11
    coords = root.find(f".//{KML}LineString/{KML}coordinates").text.split()
    assert len(coords) == 11
    assert float(coords[0].split(",")[1]) == pytest.approx(lat[0], abs=1e-9)


def test_a_map_without_origin_skips_geodetic_outputs_or_refuses_when_asked(tmp_path):
    geo = run_geo(_map(False), {"fused": _method()})
    assert geo.track is None and "need the map's origin" in geo.note
    assert write_run_geo(tmp_path, geo) == [] and not list(tmp_path.iterdir())
    with pytest.raises(InputError) as exc:
        run_geo(_map(False), {"fused": _method()}, required=True)
    msg = str(exc.value)
    assert msg.startswith("site.yaml: ") and "origin" in msg and "\n" not in msg
    geo = run_geo(_map(), {"baseline": _method("baseline")})
    assert geo.track is None and "no fused or smoothed pose" in geo.note


def _validate(message: dict) -> None:
    jsonschema.validate(message, mcap_io.schema("LocationFix"))
    ref = REFERENCE / "LocationFix.json"
    if ref.is_file():
        jsonschema.validate(message, json.loads(ref.read_text()))


def test_location_fixes_in_result_mcap_match_the_schemas_and_read_back(tmp_path):
    m = _method()
    track = method_track(m, GeoOrigin(**ORIGIN))
    gnss = GnssFixes(
        T0_S + np.arange(4) * 0.3,
        np.full(4, 47.377),
        np.full(4, 8.5418),
        np.full(4, 530.0),
        np.full(4, 1.5),
        np.full(4, 3.0),
    )
    frames = [FrameObservations(i, int(round(t * 1e9)), (64, 48)) for i, t in enumerate(m.stamps_s)]
    path = tmp_path / "result.mcap"
    write_result_mcap(path, _map(), frames, {}, geo_tracks=(track, gnss_track(gnss)))
    fused = mcap_io.read_json_messages(path, "/signpose/fused/fix")
    fixes = mcap_io.read_json_messages(path, GNSS_FIX_TOPIC)
    assert len(fused) == 11 and len(fixes) == 4
    for msg in fused + fixes:
        _validate(msg)
    assert fused[0]["latitude"] == pytest.approx(track.lat_deg[0], abs=1e-12)
    assert fused[0]["position_covariance_type"] == 2 and fused[4]["position_covariance_type"] == 0
    assert fused[0]["position_covariance"][0] == pytest.approx(0.02**2)
    assert fixes[1]["position_covariance"][8] == pytest.approx(9.0)
    back = read_telemetry(path, topic=GNSS_FIX_TOPIC)  # the log reads back as telemetry
    np.testing.assert_allclose(back.gnss.t_s, gnss.t_s, atol=1e-6)
    np.testing.assert_allclose(back.gnss.sigma_v_m, 3.0)


@pytest.mark.skipif(not REFERENCE.is_dir(), reason="../shared/reference is absent")
def test_our_location_fix_schema_asks_for_what_foxglove_requires():
    ours = mcap_io.schema("LocationFix")
    ref = json.loads((REFERENCE / "LocationFix.json").read_text())
    assert set(ref["required"]) <= set(ours["required"])
    assert set(ours["properties"]) <= set(ref["properties"])


def test_the_gnss_plot_draws_fixes_beside_the_track(tmp_path):
    m = _method()
    n = 6
    gnss = GnssFixes(
        T0_S + 0.2 * np.arange(n),
        np.full(n, 47.3770),
        8.5417 + 1e-5 * np.arange(n),
        np.full(n, 530.0),
        np.full(n, 1.5),
        np.full(n, 3.0),
    )
    geo = run_geo(_map(), {"fused": m}, gnss, outlier=np.arange(n) == 2)
    assert geo.gnss_world_m.shape == (n, 3)
    traj = Trajectory.from_matrices(m.stamps_s, m.world_T_cam)
    path = plot_gnss_track(
        tmp_path / "gnss.png", traj, "fused", geo.gnss_world_m, geo.gnss.stamps_s, np.arange(n) == 2
    )
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 10_000
