"""scripts/eval_setup_faults.py's mistakes: each changes exactly what it says, in the files.

Every faulty map and camera is written and read back through signpose's own
loaders (``load_map``, ``load_camera``), then compared field by field with the
correct one: the mistake must be there, and nothing else may differ.
"""

from __future__ import annotations

import logging
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from signpose.estimator.camera import CameraModel
from signpose.maps.loader import bundled_map_path, load_map, write_map

from signpose import pipeline
from signpose.io.camera_file import load_camera, write_camera_info

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


@pytest.fixture(scope="module")
def faults():
    sys.path.insert(0, str(SCRIPTS))
    try:
        import eval_setup_faults
    finally:
        sys.path.remove(str(SCRIPTS))
    return eval_setup_faults


@pytest.fixture()
def camera() -> CameraModel:
    K = np.array([[1108.5, 0.0, 639.5], [0.0, 1108.5, 359.5], [0.0, 0.0, 1.0]])
    return CameraModel(1280, 720, K, np.array([-0.25, 0.07, 0.0004, -0.0002, 0.0]))


def _map_round_trip(tmp_path: Path, sign_map):
    write_map(tmp_path / "map.yaml", sign_map)
    return load_map(tmp_path / "map.yaml")


def _camera_round_trip(tmp_path: Path, camera: CameraModel) -> CameraModel:
    write_camera_info(tmp_path / "camera.yaml", camera)
    return load_camera(tmp_path / "camera.yaml")


def _same_sign(a, b, *, but: tuple[str, ...] = ()) -> None:
    if "code" not in but:
        assert a.code == b.code
    for name in ("center_m", "normal", "up", "diameter_m", "sigma_m"):
        if name not in but:
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=1e-6, err_msg=name)


def test_swapped_codes_differ_only_in_the_two_codes(faults, tmp_path):
    good = load_map(bundled_map_path())
    a, b = good.codes[1], good.codes[4]
    bad = _map_round_trip(tmp_path, faults.swapped_codes(good, a, b))
    assert len(bad.signs) == len(good.signs)
    for g, s in zip(good.signs, bad.signs, strict=True):
        if g.code in (a, b):
            assert s.code == (b if g.code == a else a)
            _same_sign(g, s, but=("code",))
        else:
            _same_sign(g, s)


def test_moved_sign_moves_one_centre_along_its_face(faults, tmp_path):
    good = load_map(bundled_map_path())
    sign = good.signs[2]
    offset = faults.along_face(sign, 1.0)
    assert np.linalg.norm(offset) == pytest.approx(1.0)
    assert abs(offset @ sign.normal) < 1e-9  # in the face's plane
    bad = _map_round_trip(tmp_path, faults.moved_sign(good, sign.code, offset))
    for g, s in zip(good.signs, bad.signs, strict=True):
        if g.code == sign.code:
            np.testing.assert_allclose(s.center_m - g.center_m, offset, atol=1e-6)
            _same_sign(g, s, but=("center_m",))
        else:
            _same_sign(g, s)


def test_map_wide_mistakes(faults, tmp_path):
    good = load_map(bundled_map_path())
    bigger = _map_round_trip(tmp_path, faults.scaled_diameters(good, 1.1))
    tight = _map_round_trip(tmp_path, faults.with_survey_sigma(good, 0.001))
    for g, b, t in zip(good.signs, bigger.signs, tight.signs, strict=True):
        assert b.diameter_m == pytest.approx(1.1 * g.diameter_m)
        _same_sign(g, b, but=("diameter_m",))
        assert t.sigma_m == 0.001
        _same_sign(g, t, but=("sigma_m",))
    code = good.codes[0]
    fewer = _map_round_trip(tmp_path, faults.without_sign(good, code))
    assert fewer.codes == tuple(c for c in good.codes if c != code)


def test_turned_sign_turns_up_about_its_normal(faults, tmp_path):
    good = load_map(bundled_map_path())
    sign = next(s for s in good.signs if s.oriented)
    bad = _map_round_trip(tmp_path, faults.turned_sign(good, sign.code, 15.0))
    turned = bad.sign(sign.code)
    assert np.degrees(np.arccos(np.clip(turned.up @ sign.up, -1, 1))) == pytest.approx(15.0)
    assert turned.up @ turned.normal == pytest.approx(0.0, abs=1e-8)
    _same_sign(sign, turned, but=("up",))
    for g in good.signs:
        if g.code != sign.code:
            _same_sign(g, bad.sign(g.code))


def test_camera_mistakes_change_only_what_they_say(faults, camera, tmp_path):
    focal = _camera_round_trip(tmp_path, faults.scaled_focal(camera, 1.08))
    assert (focal.fx, focal.fy) == pytest.approx((1.08 * camera.fx, 1.08 * camera.fy))
    assert (focal.cx, focal.cy, focal.width, focal.height) == (639.5, 359.5, 1280, 720)
    np.testing.assert_array_equal(focal.dist, camera.dist)

    shifted = _camera_round_trip(tmp_path, faults.shifted_principal_point(camera, 15.0, 0.0))
    assert (shifted.cx, shifted.cy, shifted.fx) == (654.5, 359.5, camera.fx)
    np.testing.assert_array_equal(shifted.dist, camera.dist)

    lens = (-0.33, 0.12, -0.0004, 0.0003)
    other = _camera_round_trip(tmp_path, faults.other_lens(camera, lens))
    np.testing.assert_allclose(other.dist[:4], lens)
    np.testing.assert_array_equal(other.K, camera.K)

    label = _camera_round_trip(tmp_path, faults.relabelled_model(camera))
    assert label.model == "equidistant"
    np.testing.assert_array_equal(label.dist, camera.dist[:4])
    np.testing.assert_array_equal(label.K, camera.K)

    hd = _camera_round_trip(tmp_path, faults.resized_calibration(camera, 1920, 1080))
    assert (hd.width, hd.height) == (1920, 1080)
    assert (hd.fx, hd.cx) == pytest.approx((1.5 * camera.fx, 1.5 * camera.cx))
    np.testing.assert_array_equal(hd.dist, camera.dist)


def test_most_seen_breaks_ties_by_code(faults):
    seen = Counter({"1001": 120, "0110": 120, "0101": 120, "1100": 87, "0011": 200})
    assert faults.most_seen(seen, ("0101", "0110", "1001", "1100")) == (
        "0101", "0110", "1001", "1100",
    )  # fmt: skip


def test_verdicts(faults):
    ref = {"exit": 0, "stderr_warnings": [], "methods": {"smoothed": _m(0.1, 100, 0)}}
    assert faults.verdict(ref, ref) == "harmless"
    wrong = {"exit": 0, "stderr_warnings": [], "methods": {"smoothed": _m(0.1, 100, 2)}}
    assert faults.verdict(wrong, ref) == "SILENT"
    far = {"exit": 0, "stderr_warnings": [], "methods": {"smoothed": _m(0.31, 100, 0)}}
    assert faults.verdict(far, ref) == "SILENT"
    assert faults.verdict(far | {"stderr_warnings": ["warning: x"]}, ref) == "told*"
    assert faults.verdict(far | {"exit": 2}, ref) == "refused"
    # far off but every pose weak: no accuracy claimed (the statuses tell)
    weak = {"exit": 0, "stderr_warnings": [], "methods": {"smoothed": _m(0.31, 0, 0)}}
    assert faults.verdict(weak, ref) == "weak"


def _m(rmse: float, ok: int, beyond: int) -> dict:
    return {"rmse_m": rmse, "ok": ok, "ok_beyond_3sigma": beyond}


def test_run_warnings_reach_the_user_without_echo(caplog):
    """pipeline._warn: the estimator's warnings go to the logger (the CLI's stderr) when
    ``signpose run`` passes no echo; reading problems stay the caller's to print."""
    with caplog.at_level(logging.WARNING, logger=pipeline.log.name):
        pipeline._warn(None, ["the camera file does not fit"], where="flight.mp4")
        pipeline._warn(None, ["frame 3 unreadable"])
    assert [r.getMessage() for r in caplog.records] == ["flight.mp4: the camera file does not fit"]
    said: list[str] = []
    caplog.clear()
    pipeline._warn(said.append, ["x"], where="flight.mp4")
    assert said == ["warning: x"] and not caplog.records


@pytest.mark.parametrize(
    ("name", "extra"),
    [("principal_15px", ()), ("principal_15px_stated", ("--principal-sigma", "15"))],
)
def test_the_principal_point_scenarios(faults, camera, tmp_path, name, extra):
    """Both move the principal point 15 px in u; the stated one says so with its option."""
    flight = faults.Flight(
        spec=None,
        folder=tmp_path,
        video=tmp_path / "video.mp4",
        camera_path=tmp_path / "camera.yaml",
        gt=tmp_path / "groundtruth.tum",
        sign_map=load_map(bundled_map_path()),
        camera=camera,
    )
    scenario = next(s for s in faults.SCENARIOS if s.name == name)
    setup = scenario.build(flight, tmp_path)
    written = load_camera(setup.camera_path)
    assert (written.cx, written.cy) == (camera.cx + 15.0, camera.cy)
    assert setup.extra == extra
    argv = faults._run_argv(setup, tmp_path / "out")
    assert ("--principal-sigma" in argv) == bool(extra)
    assert argv[len(argv) - len(extra) :] == list(extra)
