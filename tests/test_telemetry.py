"""Telemetry in: DJI SRT (both layouts), the telemetry CSV, the dispatcher, bad input."""

from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from signpose.estimator.telemetry import GnssFixes, Telemetry

from signpose.core.errors import InputError
from signpose.io.telemetry import check_overlap, read_telemetry
from signpose.io.telemetry_srt import read_srt, subtitle_fields

DATA = Path(__file__).parent / "data" / "telemetry"


def _one_line(exc: pytest.ExceptionInfo, path, *parts: str) -> None:
    msg = str(exc.value)
    assert msg.startswith(str(path)), msg
    assert "\n" not in msg
    for part in parts:
        assert part in msg, msg


def _no_nan(t: Telemetry) -> None:
    for stream in (t.gnss, t.imu, t.gimbal):
        if stream is None:
            continue
        for value in vars(stream).values():
            assert np.all(np.isfinite(value))
        assert np.all(np.diff(stream.t_s) > 0)


def test_current_dji_layout_gives_fixes_heights_and_gimbal_on_the_video_clock():
    t = read_telemetry(DATA / "dji_current.SRT", video_start_s=1000.0)
    assert len(t.gnss) == 6 and t.skipped == {}
    np.testing.assert_allclose(t.gnss.t_s, 1000.0 + 0.1 * np.arange(6))
    np.testing.assert_allclose(t.gnss.lat_deg, 47.3769 + 1e-5 * np.arange(6), atol=1e-9)
    np.testing.assert_allclose(t.gnss.lon_deg, 8.5417 + 5e-6 * np.arange(6), atol=1e-9)
    np.testing.assert_allclose(t.gnss.height_m, 542.1 + 0.5 * np.arange(6))  # abs_alt, not rel_alt
    np.testing.assert_allclose(t.gimbal.yaw_deg, -10.0 + np.arange(6))
    np.testing.assert_allclose(t.gimbal.pitch_deg, -30.0)
    _no_nan(t)


def test_older_dji_layout_with_longtitude_and_altitude():
    t = read_srt(DATA / "dji_older.SRT")
    assert len(t.gnss) == 5 and t.gimbal is None
    np.testing.assert_allclose(t.gnss.t_s, 0.033 * np.arange(5))
    assert t.gnss.lon_deg[0] == pytest.approx(151.21529)  # the misspelt key
    assert t.gnss.lat_deg[0] == pytest.approx(-33.85678)
    np.testing.assert_allclose(t.gnss.height_m, 48.25 + 0.1 * np.arange(5))


def test_garbled_subtitles_are_skipped_and_counted_never_nan():
    t = read_srt(DATA / "dji_garbled.SRT")
    # 7 subtitles: 2 good; bad number, no longitude, no abs_alt; one (0, 0); one nan.
    assert len(t.gnss) == 2
    assert t.skipped == {"garbled": 3, "no_fix": 1, "non_finite": 1}
    np.testing.assert_allclose(t.gnss.t_s, [0.0, 0.5])
    _no_nan(t)


def test_an_srt_with_only_garbled_subtitles_is_one_line(tmp_path):
    p = tmp_path / "bad.SRT"
    p.write_text("1\n00:00:00,000 --> 00:00:00,033\n[latitude: x] [longitude: y]\n\n" * 3)
    with pytest.raises(InputError) as exc:
        read_telemetry(p)
    _one_line(exc, p, "none of its 3 subtitles has a readable fix", "3 garbled")
    q = tmp_path / "words.srt"
    q.write_text("hello\nworld\n")
    with pytest.raises(InputError) as exc:
        read_telemetry(q)
    _one_line(exc, q, "not an SRT sidecar")


def test_grouped_gimbal_fields_and_pairs_in_one_group():
    f = subtitle_fields("[rel_alt: 1.3 abs_alt: 132.8] [Gimbal: Yaw:10.0, Pitch:-45.0, Roll:0.5]")
    assert f == {
        "rel_alt": "1.3",
        "abs_alt": "132.8",
        "gimbal_yaw": "10.0",
        "gimbal_pitch": "-45.0",
        "gimbal_roll": "0.5",
    }


@pytest.fixture(scope="module")
def scratch(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("srt") / "x.SRT"


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(text=st.text(alphabet=st.sampled_from("[]:-.,0123456789 latiudeongbs_x\n>"), max_size=300))
def test_srt_reader_never_raises_anything_but_input_error_nor_yields_nan(scratch, text):
    scratch.write_text("1\n00:00:00,000 --> 00:00:00,033\n" + text)
    try:
        t = read_srt(scratch)
    except InputError:
        return
    _no_nan(t)


def test_csv_mixes_gnss_and_imu_rows_with_defaults_and_garbled_cells():
    t = read_telemetry(DATA / "flight.csv")
    np.testing.assert_allclose(t.gnss.t_s, [100.0, 100.1, 100.3])
    np.testing.assert_allclose(t.gnss.sigma_h_m, [1.5, 2.0, 1.5])  # empty -> default
    assert len(t.imu) == 7  # 100.12 has an empty gyro_z
    np.testing.assert_allclose(t.imu.accel_m_s2[0], [0.10, 0.0, 9.81])
    np.testing.assert_allclose(t.imu.gyro_rad_s[-1], [0.017, -0.027, 0.037])
    assert t.skipped == {"garbled": 1, "garbled_imu": 1}
    assert t.span_s() == (100.0, 100.3)
    _no_nan(t)


@pytest.mark.parametrize(
    ("text", "expect"),
    [
        ("t_s,lat_deg,lon_deg,height,x\n1,2,3,4,5\n", "unknown column 'height'"),
        ("lat_deg,lon_deg,height_m\n1,2,3\n", "no 't_s' column"),
        ("t_s,lat_deg\n1,2\n", "needs the GNSS columns"),
        ("# only a comment\n", "empty telemetry CSV"),
        ("t_s,lat_deg,lon_deg,height_m\n1,a,b,c\n2,nan,8,9\n", "no usable GNSS or IMU row"),
    ],
)
def test_bad_csvs_are_one_line_naming_the_file(tmp_path, text, expect):
    p = tmp_path / "tel.csv"
    p.write_text(text)
    with pytest.raises(InputError) as exc:
        read_telemetry(p)
    _one_line(exc, p, expect)


def test_the_dispatcher_tells_formats_by_content_and_refuses_the_rest(tmp_path):
    srt = tmp_path / "clip.txt"
    srt.write_bytes((DATA / "dji_older.SRT").read_bytes())
    assert len(read_telemetry(srt).gnss) == 5
    csv = tmp_path / "tel.log"
    csv.write_bytes((DATA / "flight.csv").read_bytes())
    assert len(read_telemetry(csv).gnss) == 3
    other = tmp_path / "notes.txt"
    other.write_text("nothing here\n")
    with pytest.raises(InputError) as exc:
        read_telemetry(other)
    _one_line(exc, other, "not a telemetry file")
    with pytest.raises(InputError) as exc:
        read_telemetry(tmp_path / "missing.srt")
    _one_line(exc, tmp_path / "missing.srt", "not found")
    with pytest.raises(InputError) as exc:
        read_telemetry(DATA / "flight.csv", topic="/fix")
    _one_line(exc, DATA / "flight.csv", "--telemetry-topic applies to MCAP")


def _telemetry(t0: float, t1: float) -> Telemetry:
    t = np.linspace(t0, t1, 5)
    one = np.ones(5)
    return Telemetry("tel.csv", gnss=GnssFixes(t, 47 * one, 8 * one, 500 * one, one, one))


def test_telemetry_that_does_not_overlap_the_video_is_refused():
    frames = np.arange(10.0, 20.0, 0.1)
    check_overlap(_telemetry(15.0, 30.0), frames)  # overlaps
    check_overlap(_telemetry(21.0, 30.0), frames)  # within the unknown offset's reach
    with pytest.raises(InputError) as exc:
        check_overlap(_telemetry(1e9, 1e9 + 10), frames)
    _one_line(exc, "tel.csv", "no overlap", "--telemetry-offset")
    with pytest.raises(InputError):
        check_overlap(_telemetry(21.0, 30.0), frames, clock_offset_s=0.0)  # given: no slack
    check_overlap(_telemetry(1e9, 1e9 + 10), frames, clock_offset_s=1e9 - 12.0)
