"""`signpose run --telemetry`: the fused method, the WGS84 files, and every bad input as one line.

A tiny simulated flight (16 frames) with the truth replayed as detections; its
GNSS is made here from the true camera positions, converted to WGS84 at the
map's origin, with 0.3 m of noise.
"""

import csv
import io
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import simulate_tiny, truth_detector, write_yaml
from signpose.maps.geodesy import GeoOrigin, enu_from_geodetic, geodetic_from_enu
from signpose.maps.loader import bundled_map_path, load_map, map_to_dict
from test_telemetry_ulog import IMU_FIELDS, _imu_rows, write_ulog

from signpose import pipeline
from signpose.cli import main
from signpose.cli.run import print_result
from signpose.core.errors import InputError
from signpose.io import mcap as mcap_io
from signpose.io.foxglove import camera_calibration, compressed_image, location_fix
from signpose.io.sources import open_source
from signpose.io.telemetry import TelemetryRequest, read_telemetry
from signpose.io.tum import read_tum

ORIGIN = {"lat_deg": 46.5, "lon_deg": 7.25, "height_m": 800.0}


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    # 30 frames at 3 m/s (the tiny default squeezes its path into 16 frames: 30 m/s).
    return simulate_tiny(tmp_path_factory.mktemp("telemetry_flight"), frames=30, speed_mps=3.0)


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("site")
    data = map_to_dict(load_map(bundled_map_path()))
    return {
        "anchored": write_yaml(d / "anchored.yaml", {"origin": dict(ORIGIN), **data}),
        "plain": write_yaml(d / "plain.yaml", data),
    }


def _gnss_csv(path: Path, flight, shift_s: float = 0.0, seed: int = 0) -> Path:
    gt = read_tum(flight.groundtruth_path)
    rng = np.random.default_rng(seed)
    pos = gt.world_t_cam[::2] + rng.normal(0.0, 0.3, (len(gt.world_t_cam[::2]), 3))
    lat, lon, h = geodetic_from_enu(GeoOrigin(**ORIGIN), pos)
    lines = ["t_s,lat_deg,lon_deg,height_m,sigma_h_m,sigma_v_m"]
    for t, a, b, c in zip(gt.stamps_s[::2] + shift_s, lat, lon, h, strict=True):
        lines.append(f"{t:.6f},{a:.9f},{b:.9f},{c:.4f},0.5,0.8")
    path.write_text("\n".join(lines) + "\n")
    return path


def _srt(path: Path, flight) -> Path:
    """The DJI sidecar of the flight's video: one subtitle per frame, the current layout."""
    gt = read_tum(flight.groundtruth_path)
    lat, lon, h = geodetic_from_enu(GeoOrigin(**ORIGIN), gt.world_t_cam)
    cues = []
    for i, t in enumerate(gt.stamps_s - gt.stamps_s[0]):
        ms = int(round(t * 1000))
        start, end = f"00:00:{ms // 1000:02d},{ms % 1000:03d}", f"00:00:{(ms + 33) // 1000:02d}"
        cues.append(
            f"{i + 1}\n{start} --> {end},{(ms + 33) % 1000:03d}\n"
            f"[latitude: {lat[i]:.7f}] [longitude: {lon[i]:.7f}] "
            f"[rel_alt: 30.0 abs_alt: {h[i]:.3f}]\n"
        )
    path.write_text("\n".join(cues))
    return path


def _run(flight, sign_map_path: Path, out: Path, request: TelemetryRequest | None, full=True):
    settings = pipeline.RunSettings(telemetry=request, plots=full, mcap=full)
    return pipeline.run(
        flight.frames_path,
        load_map(sign_map_path),
        out,
        camera=flight.camera,
        settings=settings,
        progress=False,
        detector=truth_detector(flight),
    )


def test_a_fused_run_writes_the_wgs84_files_and_location_fixes(flight, site, tmp_path):
    tel = _gnss_csv(tmp_path / "gnss.csv", flight)
    result = _run(flight, site["anchored"], tmp_path / "out", TelemetryRequest(tel, None, 0.0))
    names = {p.name for p in result.files}
    assert {"fused.tum", "trajectory_wgs84.csv", "trajectory.geojson", "trajectory.kml"} <= names
    assert "gnss.png" in names and "result.mcap" in names
    assert result.notes[0] == f"telemetry {tel}: 15 GNSS fixes"
    assert result.notes[1].startswith("fused: clock offset +0.000 s")
    rows = list(csv.DictReader((tmp_path / "out" / "trajectory_wgs84.csv").open()))
    assert len(rows) == result.n_frames == 30
    gt = read_tum(flight.groundtruth_path)
    geo = np.array([[float(r[k]) for k in ("lat_deg", "lon_deg", "height_m")] for r in rows])
    enu = enu_from_geodetic(GeoOrigin(**ORIGIN), geo[:, 0], geo[:, 1], geo[:, 2])
    fused = read_tum(tmp_path / "out" / "fused.tum").world_t_cam
    np.testing.assert_allclose(enu, fused, atol=1e-3)  # the files say what the estimate says
    assert np.max(np.linalg.norm((enu - gt.world_t_cam)[:, :2], axis=1)) < 0.2
    fixes = mcap_io.read_json_messages(tmp_path / "out" / "result.mcap", "/gnss/fix")
    fused = mcap_io.read_json_messages(tmp_path / "out" / "result.mcap", "/signpose/fused/fix")
    assert len(fixes) == 15 and len(fused) == 30
    report = json.loads((tmp_path / "out" / "report.json").read_text())["pipeline"]
    assert report["notes"] == list(result.notes)
    printed = io.StringIO()
    print_result(result, printed)
    assert result.notes[1] in printed.getvalue()


def _cli(video, *args) -> list[str]:
    camera = Path(video).parent / "camera.yaml"
    return ["run", str(video), "--camera", str(camera), *[str(a) for a in args]]


def _one_error_line(capsys, *parts: str) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    for part in parts:
        assert part in err, err
    return err


def test_geo_with_a_map_without_origin_exits_2_before_observing(flight, site, tmp_path, capsys):
    out = tmp_path / "out"
    code = main(_cli(flight.frames_path, "--map", site["plain"], "--out", out, "--geo"))
    assert code == 2
    _one_error_line(capsys, str(site["plain"]), "need the map's origin", "origin:")
    assert not (out / "observations.jsonl").exists()


def test_gnss_with_a_map_without_origin_exits_2_before_observing(flight, site, tmp_path, capsys):
    tel = _gnss_csv(tmp_path / "gnss.csv", flight)
    out = tmp_path / "out"
    code = main(_cli(flight.frames_path, "--map", site["plain"], "--out", out, "--telemetry", tel))
    assert code == 2
    _one_error_line(capsys, str(site["plain"]), "no 'origin'", str(tel))
    assert not (out / "observations.jsonl").exists()


@pytest.mark.parametrize(
    ("name", "text", "expect"),
    [
        ("all_garbled.SRT", "1\n00:00:00,000 --> 00:00:00,033\n[latitude: ?]\n", "readable fix"),
        ("empty.csv", "# nothing\n", "empty telemetry CSV"),
        ("nogps.ulg", None, "no GNSS topic"),
    ],
)
def test_unusable_telemetry_exits_2_naming_the_file(
    flight, site, tmp_path, capsys, name, text, expect
):
    tel = tmp_path / name
    if text is None:  # a ULog with an IMU topic only
        write_ulog(tel, {"sensor_combined": (IMU_FIELDS, _imu_rows(4))})
    else:
        tel.write_text(text)
    out = tmp_path / "out"
    code = main(
        _cli(flight.frames_path, "--map", site["anchored"], "--out", out, "--telemetry", tel)
    )
    assert code == 2
    _one_error_line(capsys, str(tel), expect)


def test_telemetry_that_misses_the_video_is_refused_in_one_line(flight, site, tmp_path):
    tel = _gnss_csv(tmp_path / "late.csv", flight, shift_s=3600.0)
    with pytest.raises(InputError) as exc:
        _run(flight, site["anchored"], tmp_path / "out", TelemetryRequest(tel))
    msg = str(exc.value)
    assert msg.startswith(f"{tel}: ") and "no overlap" in msg and "\n" not in msg


def test_telemetry_options_without_a_file_are_refused(flight, site, tmp_path, capsys):
    base = [flight.frames_path, "--map", site["anchored"], "--out", tmp_path / "o"]
    assert main(_cli(*base, "--telemetry-offset", "0.2")) == 2
    _one_error_line(capsys, "--telemetry-offset needs --telemetry")
    assert main(_cli(*base, "--telemetry", tmp_path / "x.csv", "--telemetry-offset", "nan")) == 2
    _one_error_line(capsys, "finite")
    assert main(_cli(*base, "--telemetry-topic", "/fix")) == 2
    _one_error_line(capsys, str(flight.frames_path), "not an MCAP / rosbag2 log")


def _log_with_fixes(path: Path, flight, tel_csv: Path) -> Path:
    """An MCAP with the flight's images, its camera and the GNSS as foxglove.LocationFix."""
    fixes = read_telemetry(tel_csv).gnss
    with mcap_io.McapJsonWriter(path) as w:
        w.write("/camera/calibration", "CameraCalibration", camera_calibration(0, flight.camera), 0)
        for frame in open_source(flight.frames_path):
            msg = compressed_image(frame.stamp_ns, frame.image)
            w.write("/camera/image/compressed", "CompressedImage", msg, frame.stamp_ns)
        for k in range(len(fixes)):
            t = int(round(fixes.t_s[k] * 1e9))
            msg = location_fix(t, "gnss", fixes.lat_deg[k], fixes.lon_deg[k], fixes.height_m[k])
            w.write("/gnss/fix", "LocationFix", msg, t)
    return path


def test_the_input_log_itself_holds_the_telemetry_and_estimate_fuses_it_too(
    flight, site, tmp_path, capsys
):
    tel = _gnss_csv(tmp_path / "gnss.csv", flight)
    log = _log_with_fixes(tmp_path / "flight.mcap", flight, tel)
    run_out = tmp_path / "run"
    settings = pipeline.RunSettings(
        telemetry=TelemetryRequest(None, "/gnss/fix", 0.0), plots=False, mcap=False
    )
    result = pipeline.run(
        log,
        load_map(site["anchored"]),
        run_out,
        settings=settings,
        progress=False,
        detector=truth_detector(flight),
    )
    assert "fused" in result.coverage and result.notes[0] == f"telemetry {log}: 15 GNSS fixes"
    out = tmp_path / "est"
    args = ["estimate", run_out / "observations.jsonl", "--map", site["anchored"]]
    srt = _srt(tmp_path / "DJI_0001.SRT", flight)  # on the video's clock
    args += ["--camera", flight.camera_path, "--out", out, "--telemetry", srt]
    assert main([str(a) for a in args] + ["--telemetry-offset", "0", "--no-sigmas"]) == 0
    printed = capsys.readouterr().out
    assert f"telemetry {srt}: 30 GNSS fixes" in printed and "fused: clock offset" in printed
    assert (out / "fused.tum").is_file() and (out / "trajectory_wgs84.csv").is_file()
    header = (out / "trajectory_wgs84.csv").read_text().splitlines()[0]
    assert header.startswith("t_s,lat_deg,lon_deg,height_m")
