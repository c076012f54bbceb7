"""``signpose batch --telemetry NAME``: each flight fused with the telemetry file beside it."""

from __future__ import annotations

import pytest
from signpose.maps.loader import bundled_map_path

from signpose import batch
from signpose.cli import main
from signpose.core.errors import InputError

TINY = ["--frames", "40", "--width", "480", "--height", "270", "--quiet"]


def test_the_name_is_made_from_the_input():
    assert batch.telemetry_name("{stem}.SRT", batch.Path("f/DJI_0001.MP4")) == "DJI_0001.SRT"
    assert batch.telemetry_name("telemetry.csv", batch.Path("f/video.mp4")) == "telemetry.csv"
    with pytest.raises(InputError, match=r"\{stem\}"):
        batch.telemetry_name("{date}.SRT", batch.Path("f/video.mp4"))


def test_a_flight_without_its_telemetry_fails_alone(tmp_path):
    job = batch.FlightJob(
        flight="f1",
        input_path=str(tmp_path / "DJI_0001.MP4"),
        map_path=str(bundled_map_path()),
        out_dir=str(tmp_path / "out" / "f1"),
        telemetry="{stem}.SRT",
    )
    outcome = batch.run_flight(job)
    assert outcome.status is batch.FlightStatus.FAILED and not outcome.internal
    assert "no telemetry file DJI_0001.SRT beside it" in outcome.message


def test_the_telemetry_is_in_the_fingerprint(tmp_path):
    (tmp_path / "v.SRT").write_text("1\n")
    job = batch.FlightJob("v", str(tmp_path / "v.mp4"), str(bundled_map_path()), str(tmp_path))
    plain = batch._fingerprint(job)
    fused = batch._fingerprint(batch.replace(job, telemetry="{stem}.SRT"))
    (tmp_path / "v.SRT").write_text("2\n")
    changed = batch._fingerprint(batch.replace(job, telemetry="{stem}.SRT"))
    offset = batch._fingerprint(batch.replace(job, telemetry="{stem}.SRT", telemetry_offset_s=0.1))
    assert len({plain, fused, changed, offset}) == 4


def test_batch_fuses_each_flight(tmp_path):
    sim = tmp_path / "flights" / "f1"
    assert (
        main(["simulate", "--out", str(sim), *TINY, "--telemetry", "--clock-offset", "0.25"]) == 0
    )
    out = tmp_path / "out"
    args = ["batch", str(sim / "video.mp4"), "--map", str(sim / "map.yaml"), "--out", str(out)]
    args += ["--telemetry", "telemetry.csv", "--telemetry-offset", "0.25", "--no-plots", "-q"]
    assert main(args) == 0
    summary = (out / batch.SUMMARY_NAME).read_text().splitlines()
    header, row = summary[0].split(","), summary[1].split(",")
    assert float(row[header.index("coverage_fused")]) > 0.9
    assert (out / "video" / "trajectory_wgs84.csv").exists()


def test_the_focal_sigma_reaches_each_flight_and_its_fingerprint(tmp_path):
    job = batch.FlightJob("v", str(tmp_path / "v.mp4"), str(bundled_map_path()), str(tmp_path))
    plain = batch._fingerprint(job)
    assert batch._fingerprint(batch.replace(job, focal_sigma_rel=0.0)) == plain
    assert batch._fingerprint(batch.replace(job, focal_sigma_rel=0.01)) != plain
    seen = []

    def runner(j):
        seen.append(j.focal_sigma_rel)
        return batch.FlightOutcome(j.flight, batch.FlightStatus.OK)

    (tmp_path / "v.mp4").write_bytes(b"\x00")
    out = tmp_path / "out"
    batch.run_batch(
        [tmp_path / "v.mp4"], bundled_map_path(), out, progress=False, runner=runner,
        focal_sigma_rel=0.02,
    )  # fmt: skip
    assert seen == [0.02]
    args = ["batch", str(tmp_path / "v.mp4"), "--map", str(bundled_map_path()), "--out", str(out)]
    assert main([*args, "--focal-sigma", "-1", "-q"]) == 2
