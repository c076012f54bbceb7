"""Simulator length by duration (issue 16 #4): --frames / --duration shorten a flight at its
speed, --speed sets the cruise speed, the flight's mean and peak speed are reported."""

import numpy as np
import pytest

from signpose.cli import main
from signpose.core.errors import InputError
from signpose.io.tum import read_tum
from signpose.sim.flight import SimSettings, frames_for_duration
from signpose.sim.trajectories import (
    DEFAULT_SPEED_MPS,
    TRAJECTORIES,
    make_trajectory,
    path_length_m,
    speed_stats,
)

TINY = ["--width", "32", "--height", "18", "--format", "png", "--no-blur", "--no-noise"]


def _simulate(tmp_path, name, *options) -> tuple[str, str]:
    """Run ``signpose simulate`` into tmp_path/name; (groundtruth.tum's header, its path)."""
    out = tmp_path / name
    assert main(["simulate", "--out", str(out), *TINY, "-q", *options]) == 0
    header = (out / "groundtruth.tum").read_text().splitlines()[0]
    return header, str(out / "groundtruth.tum")


def _distance_m(traj) -> float:
    return float(np.linalg.norm(np.diff(traj.world_t_cam, axis=0), axis=1).sum())


@pytest.mark.parametrize("name", TRAJECTORIES)
def test_fewer_frames_fly_the_start_of_the_flight_at_its_speed(demo_map, name):
    speed = DEFAULT_SPEED_MPS[name]
    full = make_trajectory(name, demo_map, 210, 30.0, speed_mps=speed)  # simulate's default
    short = make_trajectory(name, demo_map, 60, 30.0, speed_mps=speed)  # --frames 60
    np.testing.assert_allclose(short.world_T_cam(), full.world_T_cam()[:60], atol=1e-9)
    mean_short, peak_short = speed_stats(short)
    steps = np.linalg.norm(np.diff(full.world_t_cam[:60], axis=0), axis=1) * 30.0
    assert mean_short == pytest.approx(steps.mean(), rel=0.05)
    # The old behaviour squeezed the whole path into the 60 frames: 3.5x faster.
    squeezed, _ = speed_stats(make_trajectory(name, demo_map, 60, 30.0))
    assert squeezed > 1.5 * mean_short
    # Every flight stays at inspection speeds; the peak never exceeds 8 m/s by default.
    assert 2.0 * speed_stats(full)[0] > speed and peak_short <= speed_stats(full)[1] <= 8.0


def test_default_flight_is_the_one_simulate_always_flew(demo_map):
    """210 frames of climb-hover-depart at its default speed: the old squeezed flight to 1 cm."""
    name = "climb-hover-depart"
    now = make_trajectory(name, demo_map, 210, 30.0, speed_mps=DEFAULT_SPEED_MPS[name])
    old = make_trajectory(name, demo_map, 210, 30.0)
    assert np.abs(now.world_t_cam - old.world_t_cam).max() < 0.012
    assert speed_stats(now)[0] == pytest.approx(speed_stats(old)[0], rel=0.01)


@pytest.mark.parametrize("name", TRAJECTORIES)
def test_speed_doubles_the_distance_and_long_flights_keep_flying(demo_map, name):
    length = path_length_m(name, demo_map)
    n = 240  # 8 s: one pass at `speed`, two at twice it
    speed = length * 30.0 / n
    one = make_trajectory(name, demo_map, n + 1, 30.0, speed_mps=speed)
    two = make_trajectory(name, demo_map, n + 1, 30.0, speed_mps=2 * speed)
    assert _distance_m(one) == pytest.approx(length, rel=0.01)
    assert _distance_m(two) == pytest.approx(2 * _distance_m(one), rel=0.01)
    # The peak too (sampled at 30 fps, so it misses a little more of a sharper peak).
    assert speed_stats(two)[1] == pytest.approx(2 * speed_stats(one)[1], rel=0.05)
    # Past one pass: no jump where the path turns back (or starts again, for the orbit).
    long = make_trajectory(name, demo_map, 3 * n, 30.0, speed_mps=speed)
    assert speed_stats(long)[1] <= 1.02 * speed_stats(one)[1]
    ends = long.world_t_cam[[0, n, 2 * n]]
    if name == "orbit":  # repeats: back at the start after each pass
        np.testing.assert_allclose(ends[1], ends[0], atol=1e-6)
    else:  # back and forth: at the far end after one pass, home after two
        assert np.linalg.norm(ends[1] - ends[0]) > 1.0
        np.testing.assert_allclose(ends[2], ends[0], atol=1e-6)


def test_cli_duration_frames_and_speed(demo_map, tmp_path, capsys):
    h_frames, tum_frames = _simulate(tmp_path, "frames", "--frames", "6")
    h_duration, tum_duration = _simulate(tmp_path, "duration", "--duration", "0.2")
    assert h_duration == h_frames and "frames=6 " in h_frames
    assert read_tum(tum_duration).world_t_cam.tolist() == read_tum(tum_frames).world_t_cam.tolist()
    # --frames 12 is --frames 6 flown on: the default speed does not depend on the length.
    _, tum_longer = _simulate(tmp_path, "longer", "--frames", "12")
    np.testing.assert_allclose(
        read_tum(tum_longer).world_t_cam[:6], read_tum(tum_frames).world_t_cam
    )
    # The summary line and the ground truth's header give the same mean and peak speed.
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("simulated 6 frames (0.20 s, climb-hover-depart, mean ")
    fields = dict(kv.split("=") for kv in h_frames.split()[3:])
    assert f"mean {float(fields['mean_speed_mps']):.2f} m/s" in lines[0]
    assert f"peak {float(fields['peak_speed_mps']):.2f} m/s" in lines[0]
    assert fields["speed_mps"] == f"{DEFAULT_SPEED_MPS['climb-hover-depart']:g}"
    # --speed: at twice the speed, twice the distance over the same whole pass.
    n = 30
    speed = path_length_m("climb-hover-depart", demo_map) * 30.0 / n
    _, slow = _simulate(tmp_path, "slow", "--frames", str(n + 1), "--speed", f"{speed:.6f}")
    _, fast = _simulate(tmp_path, "fast", "--frames", str(n + 1), "--speed", f"{2 * speed:.6f}")
    assert _distance_m(read_tum(fast)) == pytest.approx(2 * _distance_m(read_tum(slow)), rel=0.01)


@pytest.mark.parametrize(
    "option,value",
    [
        ("--frames", "0"),
        ("--duration", "0"),
        ("--duration", "-1"),
        ("--duration", "nan"),
        ("--speed", "0"),
        ("--speed", "30.5"),
        ("--speed", "-3"),
        ("--speed", "nan"),
        ("--speed", "inf"),
    ],
)
def test_bad_length_or_speed_exits_2_with_one_line(tmp_path, capsys, option, value):
    out = tmp_path / "never"
    assert main(["simulate", "--out", str(out), *TINY, option, value]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"signpose simulate: error: {option} must be")
    assert not out.exists()


def test_library_validation_and_duration_rounding():
    assert SimSettings(speed_mps=30.0).validate().speed_mps == 30.0
    for bad in (0.0, -1.0, 30.01, float("nan"), float("inf")):
        with pytest.raises(InputError, match="--speed"):
            SimSettings(speed_mps=bad).validate()
    assert frames_for_duration(7.0, 30.0) == 210
    assert frames_for_duration(0.001, 30.0) == 1  # a positive duration has a frame
    with pytest.raises(InputError, match="--duration"):
        frames_for_duration(float("inf"), 30.0)
