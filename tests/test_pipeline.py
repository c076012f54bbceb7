"""The pipeline on a tiny simulated flight, with a detector that replays the simulator's truth."""

from __future__ import annotations

import io
import json
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from conftest import simulate_tiny, truth_detector
from signpose.frontend.detector import PredictedSign
from signpose.frontend.observations import FrameObservations, SignObservation
from signpose.maps.loader import bundled_map_path, load_map

from signpose import pipeline
from signpose.cli.run import print_result
from signpose.io import mcap as mcap_io
from signpose.io.observations import read_observations
from signpose.io.sources import open_source
from signpose.plots import PlotData, plot_errors, write_plots

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def tiny_flight(tmp_path_factory):
    return simulate_tiny(tmp_path_factory.mktemp("flight"))


def test_observe_streams_and_tracks(tiny_flight, tmp_path):
    sign_map = load_map(bundled_map_path())
    det = truth_detector(tiny_flight)
    out = tmp_path / "obs.jsonl"
    result = pipeline.observe(
        open_source(tiny_flight.frames_path),
        sign_map,
        tiny_flight.camera,
        progress=False,
        out_path=out,
        detector=det,
    )
    assert len(result.frames) == 16
    assert read_observations(out) == list(result.frames)
    # First frame full, then the running estimate predicts the signs.
    assert det.calls[0] == "full"
    assert det.calls[1:].count("track") >= 12
    assert result.tracked_frames == det.calls.count("track")
    assert [p.name for p in tmp_path.iterdir()] == ["obs.jsonl"]  # no temp file left
    assert set(result.timing_s) == {"decode_video", "wait_video", "detect", "decode", "track"}


def test_predictions_match_the_truth(tiny_flight):
    """predict_signs from the true pose lands on the true centres."""
    from signpose.io.boxes import read_boxes

    sign_map = load_map(bundled_map_path())
    boxes = read_boxes(tiny_flight.boxes_path)
    T = tiny_flight.trajectory.world_T_cam()[5]
    pred = pipeline.predict_signs(sign_map, tiny_flight.camera, T, sign_map.codes, margin=0.0)
    truth = {s["code"]: s for s in boxes[5]["signs"] if not s["truncated"]}
    assert truth and set(truth) <= {code for code, _, _ in pred}
    for code, (u, v), d in pred:
        if code in truth:
            np.testing.assert_allclose((u, v), truth[code]["center_px"], atol=0.05)
            assert d == pytest.approx(truth[code]["diameter_px"], rel=0.1)


def test_ctrl_c_keeps_complete_frames(tiny_flight, tmp_path):
    sign_map = load_map(bundled_map_path())
    out = tmp_path / "obs.jsonl"
    with pytest.raises(KeyboardInterrupt):
        pipeline.observe(
            open_source(tiny_flight.frames_path),
            sign_map,
            tiny_flight.camera,
            progress=False,
            out_path=out,
            detector=truth_detector(tiny_flight, interrupt_at=5),
        )
    frames = read_observations(out)
    assert [f.frame for f in frames] == [0, 1, 2, 3, 4]
    assert [p.name for p in tmp_path.iterdir()] == ["obs.jsonl"]


def test_observation_stream_gets_the_usual_file_mode(tmp_path):
    """observations.jsonl is readable like every other output (not mkstemp's 0600)."""
    stream = pipeline.ObservationStream(tmp_path / "obs.jsonl")
    stream.append(FrameObservations(0, 0, (8, 6), ()))
    path = stream.finish()
    mask = os.umask(0)
    os.umask(mask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~mask
    assert len(read_observations(path)) == 1


def test_run_writes_everything(tiny_flight, tmp_path):
    sign_map = load_map(bundled_map_path())
    out = tmp_path / "run"
    result = pipeline.run(
        tiny_flight.frames_path,
        sign_map,
        out,
        camera=tiny_flight.camera,
        gt_path=tiny_flight.groundtruth_path,
        settings=pipeline.RunSettings(with_images=True),
        progress=False,
        detector=truth_detector(tiny_flight),
    )
    assert result.n_frames == 16
    assert result.problems == ()
    for name in ("observations.jsonl", "result.mcap", "report.json", "trajectory_3d.png"):
        assert (out / name).is_file(), name
    for png in ("trajectory_3d.png", "views.png", "signs_per_frame.png", "errors.png"):
        assert (out / png).read_bytes()[:8] == PNG_MAGIC
    assert result.coverage["smoothed"] == pytest.approx(1.0)
    # Truth keypoints: the per-frame PnP is exact up to the simulator's rounding.
    assert result.position_rmse_m["pnp"] < 0.05
    report = json.loads((out / "report.json").read_text())
    assert report["pipeline"]["frames"] == 16
    for stage in ("decode_video", "detect", "decode", "track", "estimate", "outputs", "total"):
        assert report["pipeline"]["timing_s"][stage] >= 0.0
    assert set(report["metrics"]["methods"]) >= {"baseline", "pnp", "smoothed"}  # compare ran
    assert "smoothed" in result.comparison_table
    log = mcap_io.McapLog(out / "result.mcap")
    topics = {c.topic: c.message_count for c in log.channels}
    assert topics[mcap_io.IMAGE_TOPIC] == 16
    assert topics["/signpose/smoothed/pose"] == 16
    assert topics[mcap_io.ANNOTATIONS_TOPIC] == 16


def test_map_codes_never_seen(tiny_flight, tmp_path):
    from signpose.maps.loader import parse_map

    other = parse_map(
        {
            "frame": "elsewhere",
            "signs": [{"code": "1111", "center_m": [0, 0, 10], "diameter_m": 0.8, "sigma_m": 0.01}],
        },
        "other.yaml",
    )
    with pytest.raises(pipeline.InputError, match=r"other.yaml: none of the map's codes \(1111\)"):
        pipeline.run(
            tiny_flight.frames_path,
            other,
            tmp_path / "run",
            camera=tiny_flight.camera,
            progress=False,
            detector=truth_detector(tiny_flight),
        )
    # The observations are still there to look at.
    assert len(read_observations(tmp_path / "run" / "observations.jsonl")) == 16


def test_plots_from_fake_data(tmp_path):
    from signpose.estimator.trajectory import Trajectory

    from signpose.sim.trajectories import make_trajectory

    rng = np.random.default_rng(0)
    sign_map = load_map(bundled_map_path())
    gt = make_trajectory("orbit", sign_map, 40, 10.0)
    noisy = gt.world_t_cam + rng.normal(0, 0.05, (40, 3))
    noisy[10:14] = np.nan
    baseline = Trajectory(gt.stamps_s, noisy, gt.quat_xyzw)
    data = PlotData(
        sign_map,
        {"baseline": baseline, "smoothed": gt},
        {"smoothed": np.full((40, 3), 0.03)},
        gt,
        gt.stamps_s,
        rng.integers(0, 6, 40),
    )
    written = write_plots(tmp_path, data)
    assert sorted(p.name for p in written) == [
        "errors.png",
        "signs_per_frame.png",
        "trajectory_3d.png",
        "views.png",
    ]
    for p in written:
        assert p.read_bytes()[:8] == PNG_MAGIC
    assert not list(tmp_path.glob(".*"))  # no temp files
    assert plot_errors(tmp_path / "none.png", PlotData(sign_map, {"smoothed": gt})) is None
    assert not (tmp_path / "none.png").exists()


@pytest.fixture(scope="module")
def real_flight(tmp_path_factory):
    """A few 960x540 frames, big enough for the trained cascade and the decoder."""
    return simulate_tiny_size(tmp_path_factory.mktemp("real"), frames=8, width=960, height=540)


def test_observations_are_byte_identical_for_any_worker_count(real_flight, tmp_path):
    """Chunks of 3 frames (issue 14): inline with 1 worker, in 2 or 3 worker processes."""
    sign_map = load_map(bundled_map_path())
    written = {}
    for workers in (1, 2, 3):
        out = tmp_path / f"w{workers}.jsonl"
        result = pipeline.observe(
            open_source(real_flight.frames_path),
            sign_map,
            real_flight.camera,
            pipeline.ObserveSettings(workers=workers, chunk_frames=3),
            progress=False,
            out_path=out,
        )
        written[workers] = out.read_bytes()
        # Tracking ran (the lag between a pose and the frame it predicts matters) and
        # started again with a full-frame search in each of the 3 chunks.
        assert result.tracked_frames >= 2
        assert result.full_frames >= 3
        assert [f.frame for f in result.frames] == list(range(8))
    assert written[1] == written[2] == written[3]


def _sign(code: str, u: float, v: float) -> SignObservation:
    return SignObservation(code, {"center": (u, v)}, (u - 20, v - 20, 40, 40))


def test_another_code_at_a_tracked_signs_place_is_refused():
    predictions = (
        PredictedSign("0101", (100.0, 100.0), 40.0),
        PredictedSign("0011", (300.0, 100.0), 40.0),
        PredictedSign("1100", (200.0, 300.0), 40.0),
    )
    # The image moved by (30, -20) px since the pose that predicted it.
    frame = FrameObservations(
        3,
        0,
        (640, 480),
        (
            _sign("0111", 132.0, 79.0),  # where 0101 is: a slot misread
            _sign("0011", 330.0, 80.0),
            _sign("1100", 230.0, 280.0),
            _sign("1001", 500.0, 300.0),  # nobody predicted it: kept
        ),
    )
    kept, refused = pipeline.refuse_changed_codes(frame, predictions)
    assert [s.code for s in kept.signs] == ["0011", "1100", "1001"]
    assert [(r.reason, r.observation.code, r.other_code) for r in refused] == [
        (pipeline.RefusalReason.CODE_CHANGED, "0111", "0101")
    ]
    assert refused[0].to_json()["reason"] == "code_changed"
    assert refused[0].other_px == (130.0, 80.0)  # the prediction moved onto the frame
    # Predictions the frame's readings do not confirm are not used to refuse anything.
    scattered = FrameObservations(
        3, 0, (640, 480), (frame.signs[0], _sign("0011", 331.0, 81.0), _sign("1100", 150.0, 330.0))
    )
    assert pipeline.refuse_changed_codes(scattered, predictions)[1] == []


def test_a_code_seen_twice_keeps_the_reading_the_frames_pose_agrees_with(tiny_flight):
    sign_map = load_map(bundled_map_path())
    frame = truth_detector(tiny_flight).detect(None, sign_map.codes)
    signs = sorted(frame.detections, key=lambda s: s.code)
    assert len(signs) >= 4
    true, elsewhere = signs[0], signs[-1]
    # A misreading: the last sign read with the first sign's code.
    fake = SignObservation(true.code, elsewhere.keypoints_px, elsewhere.bbox_px)
    obs = FrameObservations(0, 0, (320, 240), (fake, *signs[:-1]))
    kept, refused = pipeline.settle_duplicate_codes(obs, sign_map, tiny_flight.camera)
    assert [s.code for s in kept.signs] == [s.code for s in signs[:-1]]
    assert true in kept.signs and fake not in kept.signs
    assert [(r.reason, r.observation) for r in refused] == [
        (pipeline.RefusalReason.DUPLICATE_CODE, fake)
    ]
    assert refused[0].other_px == true.center_px  # both places are reported
    # Without a map there is no pose to ask: both readings are refused.
    kept, refused = pipeline.settle_duplicate_codes(obs, None, None)
    assert true.code not in {s.code for s in kept.signs}
    assert len(refused) == 2 and all(r.other_px is None for r in refused)


def test_run_with_the_real_detector(real_flight, tmp_path):
    """End to end with the trained cascade and the decoder on a few 960x540 frames."""
    sim = real_flight
    sign_map = load_map(bundled_map_path())
    result = pipeline.run(
        sim.frames_path,
        sign_map,
        tmp_path / "run",
        camera=sim.camera,
        gt_path=sim.groundtruth_path,
        settings=pipeline.RunSettings(plots=False),
        progress=False,
    )
    frames = read_observations(tmp_path / "run" / "observations.jsonl")
    assert len(frames) == 8
    assert all(len(f.signs) >= 3 for f in frames)
    assert all(s.code in sign_map.codes for f in frames for s in f.signs)
    assert result.coverage["pnp"] == pytest.approx(1.0)
    assert result.position_rmse_m["pnp"] < 1.0


def simulate_tiny_size(out: Path, frames: int, width: int, height: int):
    from signpose.sim.flight import SimSettings, simulate

    settings = SimSettings(frames=frames, width=width, height=height)
    return simulate(load_map(bundled_map_path()), out, settings, progress=False)


class _MisreadingDetector:
    """The truth, plus on frame 3 the last sign read a second time with the first sign's code."""

    def __init__(self, truth):
        self.truth = truth
        self.frames = 0

    def _misread(self, result):
        self.frames += 1
        if self.frames != 4:
            return result
        signs = sorted(result.detections, key=lambda s: s.code)
        fake = SignObservation(signs[0].code, signs[-1].keypoints_px, signs[-1].bbox_px)
        return replace(result, detections=(*result.detections, fake))

    def detect(self, image, codes=None, mode="fast"):
        return self._misread(self.truth.detect(image, codes, mode))

    def detect_tracked(self, image, predictions, codes=None, refresh=False):
        return self._misread(self.truth.detect_tracked(image, predictions, codes, refresh))


@pytest.mark.parametrize(
    ("tracking", "reason"),
    [(True, "code_changed"), (False, "duplicate_code")],  # the track sees it first
)
def test_run_refuses_a_misread_code_and_says_so(tiny_flight, tmp_path, tracking, reason):
    sign_map = load_map(bundled_map_path())
    out = tmp_path / "run"
    result = pipeline.run(
        tiny_flight.frames_path,
        sign_map,
        out,
        camera=tiny_flight.camera,
        settings=pipeline.RunSettings(
            observe=pipeline.ObserveSettings(tracking=tracking), plots=False, mcap=False
        ),
        progress=False,
        detector=_MisreadingDetector(truth_detector(tiny_flight)),
    )
    assert result.refused == {"duplicate_code": 0, "code_changed": 0, "code_not_in_map": 0} | {
        reason: 1
    }
    refused = json.loads((out / "report.json").read_text())["pipeline"]["refused"]
    assert refused["counts"] == result.refused
    assert [(r["frame"], r["reason"]) for r in refused["observations"]] == [(3, reason)]
    frame3 = read_observations(out / "observations.jsonl")[3]
    codes = [s.code for s in frame3.signs]
    assert len(codes) == len(set(codes))
    printed = io.StringIO()
    print_result(result, printed)
    assert "refused 1 decoded readings" in printed.getvalue()
