"""``signpose batch`` passes the estimator's options to each flight as ``signpose run`` uses them.

--solver, --no-sigmas, --map-fixed, --focal-sigma and --principal-sigma: the
same options give the same ``EstimatorSettings`` and the same files, and a
rerun with other values redoes the flight (its fingerprint), while the
defaults leave the fingerprint of runs from before the options as it was.
"""

from __future__ import annotations

import json

import pytest
from conftest import simulate_tiny, truth_detector
from signpose.maps.loader import bundled_map_path

from signpose import batch, pipeline
from signpose.cli import batch as batch_cli
from signpose.cli import build_parser, main
from signpose.cli import run as run_cli

MAP = str(bundled_map_path())
OPTIONS = [
    [],
    ["--solver", "isam2"],
    ["--no-sigmas"],
    ["--map-fixed"],
    ["--focal-sigma", "0.01"],
    ["--principal-sigma", "4"],
    ["--solver", "isam2", "--map-fixed", "--principal-sigma", "2.5", "--focal-sigma", "0.002"],
]


@pytest.mark.parametrize("options", OPTIONS, ids=lambda o: " ".join(o) or "defaults")
def test_the_same_options_make_the_same_settings(tmp_path, monkeypatch, options):
    run_args = build_parser().parse_args(["run", "v.mp4", "--map", MAP, "--out", "o", *options])
    expected = run_cli.estimator_settings(run_args)
    passed = {}
    monkeypatch.setattr(batch_cli, "run_batch", lambda *a, **kw: passed.update(kw) or [])
    args = ["batch", str(tmp_path / "v.mp4"), "--map", MAP, "--out", str(tmp_path / "o")]
    assert main([*args, *options, "-q"]) == 0
    fields = {k: passed[k] for k in batch._ESTIMATOR_DEFAULTS}
    job = batch.FlightJob("v", "v.mp4", MAP, "o", **fields)
    assert batch.estimator_settings(job) == expected
    if options:  # not the defaults: the run is not the default run
        assert expected != run_cli.estimator_settings(
            build_parser().parse_args(["run", "v.mp4", "--map", MAP, "--out", "o"])
        )


def test_the_options_are_in_the_fingerprint_only_when_set(tmp_path):
    job = batch.FlightJob("v", str(tmp_path / "v.mp4"), MAP, str(tmp_path))
    plain = batch._fingerprint(job)
    defaults = batch.replace(job, **batch._ESTIMATOR_DEFAULTS)
    assert batch._fingerprint(defaults) == plain  # runs from before the options stay done
    changed = {
        batch._fingerprint(batch.replace(job, **{k: v}))
        for k, v in [
            ("solver", "isam2"),
            ("map_fixed", True),
            ("sigmas", False),
            ("principal_sigma_px", 3.0),
            ("focal_sigma_rel", 0.01),
        ]
    }
    assert len(changed) == 5 and plain not in changed


def test_the_options_reach_each_flight(tmp_path):
    seen = []

    def runner(j):
        seen.append((j.solver, j.map_fixed, j.sigmas, j.principal_sigma_px))
        return batch.FlightOutcome(j.flight, batch.FlightStatus.OK)

    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "v.mp4").write_bytes(b"\x00")
    batch.run_batch(
        [tmp_path / "a" / "v.mp4", tmp_path / "b" / "v.mp4"], MAP, tmp_path / "out",
        progress=False, runner=runner, solver="isam2", map_fixed=True, sigmas=False,
        principal_sigma_px=2.0,
    )  # fmt: skip
    assert seen == [("isam2", True, False, 2.0)] * 2


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    return simulate_tiny(tmp_path_factory.mktemp("flight") / "f1", frames=16)


@pytest.fixture
def replay(tiny, monkeypatch):
    """The flight's detector replays its truth (fast, and the same for run and batch)."""
    real_observe = pipeline.observe

    def observe(source, *args, **kw):
        kw["detector"] = truth_detector(tiny)
        return real_observe(source, *args, **kw)

    monkeypatch.setattr(pipeline, "observe", observe)


def _report_settings(folder) -> dict:
    return json.loads((folder / "report.json").read_text())["settings"]


def test_a_batch_flight_is_the_run_with_the_same_options(tmp_path, tiny, replay):
    options = ["--solver", "isam2", "--map-fixed", "--principal-sigma", "3"]
    video, camera, gt = (
        str(p) for p in (tiny.frames_path, tiny.camera_path, tiny.groundtruth_path)
    )
    ran = tmp_path / "run"
    args = ["run", video, "--map", MAP, "--camera", camera, "--gt", gt, "--out", str(ran)]
    assert main([*args, "--no-plots", "-q", *options]) == 0
    out = tmp_path / "batch"
    assert (
        main(["batch", video, "--map", MAP, "--out", str(out), "--no-plots", "-q", *options]) == 0
    )
    flight = out / batch.flight_names([video])[0]
    settings = _report_settings(flight)
    assert settings == _report_settings(ran)
    assert settings["solver"] == "isam2"
    assert settings["smoother"]["landmarks"] == "fixed"
    assert settings["principal_sigma_px"] == 3.0
    for name in ("trajectory.csv", "smoothed.tum", "pnp.tum", "causal.tum"):
        assert (flight / name).read_bytes() == (ran / name).read_bytes(), name
    # the same batch without the options is another run: redone, other results
    assert main(["batch", video, "--map", MAP, "--out", str(out), "--no-plots", "-q"]) == 0
    plain = _report_settings(flight)
    assert plain["solver"] == "batch" and "principal_sigma_px" not in plain
    assert not (flight / "causal.tum").exists()
    assert (flight / "trajectory.csv").read_bytes() != (ran / "trajectory.csv").read_bytes()
