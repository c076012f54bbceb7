"""``signpose simulate --telemetry`` (issue 17, deliverable 6): telemetry.csv beside
the frames, an origin in map.yaml, fused by ``signpose run --telemetry``; without the
option every output is as before."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import yaml
from signpose.maps.loader import bundled_map_path, load_map

from signpose.cli import main
from signpose.io.telemetry import read_telemetry
from signpose.io.tum import read_tum
from signpose.sim.flight import SimSettings, telemetry_flight
from signpose.sim.telemetry import SIM_ORIGIN

FRAMES, FPS, OFFSET = 40, 30.0, 0.25
TINY = ["--frames", str(FRAMES), "--width", "480", "--height", "270", "--quiet"]


@pytest.fixture(scope="module")
def flights(tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("simtel")
    with_tel, plain = root / "tel", root / "plain"
    args = ["simulate", "--out", str(with_tel), *TINY, "--telemetry"]
    assert main(args + ["--clock-offset", str(OFFSET)]) == 0
    assert main(["simulate", "--out", str(plain), *TINY]) == 0
    return with_tel, plain


def test_without_telemetry_outputs_unchanged(flights):
    with_tel, plain = flights
    assert not (plain / "telemetry.csv").exists()
    for name in ("groundtruth.tum", "boxes.jsonl", "camera.yaml", "video.mp4"):
        assert (plain / name).read_bytes() == (with_tel / name).read_bytes(), name
    # map.yaml without the option: the bundled map as it is (no origin added).
    bundled = yaml.safe_load(bundled_map_path().read_text())
    written = yaml.safe_load((plain / "map.yaml").read_text())
    assert "origin" not in written and "origin" not in bundled
    assert written["signs"] == yaml.safe_load((with_tel / "map.yaml").read_text())["signs"]


def test_map_gets_the_documented_origin(flights):
    origin = load_map(flights[0] / "map.yaml").origin
    assert origin == SIM_ORIGIN


def test_telemetry_csv_covers_the_video(flights):
    tel = read_telemetry(flights[0] / "telemetry.csv")
    assert tel.gnss is not None and tel.imu is not None
    video_end = (FRAMES - 1) / FPS
    for t in (np.asarray(tel.gnss.t_s), np.asarray(tel.imu.t_s)):
        # Telemetry time = video time + offset, 2 s margin either side.
        assert t[0] <= OFFSET and t[-1] >= video_end + OFFSET
        assert t[0] >= OFFSET - 2.01 and t[-1] <= FRAMES / FPS + OFFSET + 2.01
    assert np.median(np.diff(tel.gnss.t_s)) == pytest.approx(0.1)
    assert np.median(np.diff(tel.imu.t_s)) == pytest.approx(0.005)
    assert np.all(np.isfinite(tel.imu.accel_m_s2))
    # Hovering-ish multirotor: specific force about g, pointing up in the FLU body.
    assert np.median(tel.imu.accel_m_s2[:, 2]) == pytest.approx(9.8, abs=2.0)


def test_telemetry_flight_is_the_rendered_one(flights):
    """The 1 kHz grid the IMU comes from passes through the ground-truth frames."""
    truth = read_tum(flights[0] / "groundtruth.tum")
    sign_map = load_map(bundled_map_path())
    settings = SimSettings(frames=FRAMES, fps=FPS, speed_mps=1.55, width=480, height=270)
    flight = telemetry_flight(sign_map, settings, pad_s=1.0)
    poses = flight.poses(truth.stamps_s)
    assert np.abs(poses[:, :3, 3] - truth.world_t_cam).max() < 1e-5  # the TUM file keeps 1 um
    R = truth.world_T_cam()[:, :3, :3]
    assert np.abs(poses[:, :3, :3] - R).max() < 1e-6


def test_run_fuses_the_simulated_telemetry(flights, tmp_path):
    d = flights[0]
    out = tmp_path / "run"
    args = ["run", str(d / "video.mp4"), "--map", str(d / "map.yaml")]
    args += ["--camera", str(d / "camera.yaml"), "--out", str(out)]
    assert main(args + ["--telemetry", str(d / "telemetry.csv"), "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["pipeline"]["coverage"]["fused"] > 0.9
    (note,) = [n for n in report["pipeline"]["notes"] if "clock offset" in n]
    found = float(re.search(r"clock offset ([+-]?\d+\.\d+) s", note).group(1))
    assert found == pytest.approx(OFFSET, abs=0.005), note
    assert (out / "trajectory_wgs84.csv").exists()


def test_clock_offset_needs_telemetry(tmp_path, capsys):
    code = main(["simulate", "--out", str(tmp_path / "x"), *TINY, "--clock-offset", "0.1"])
    assert code == 2
    assert "--clock-offset needs --telemetry" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
