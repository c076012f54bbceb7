"""scripts/eval_flight.py's grading and scripts/independent_flight.py's lens, on a tiny flight.

The flight (20 frames at 640x360, plumb_bob k1 -0.33, 14 m from the signs) is
drawn once per module; every check compares the drawing's own truth with an
independent reading of it: signpose's camera model for the lens, signpose's
frontend for the centres, and copies of the frontend's observations with a
code swapped for the wrong-code counter.
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import numpy as np
import pytest
from signpose.estimator.camera import pixel_from_cam_point, pixel_from_world_point, undistort_px
from signpose.estimator.trajectory import rotation_from_quat_xyzw
from signpose.maps.loader import bundled_map_path, load_map

from signpose.cli import main as signpose
from signpose.io.camera_file import load_camera, write_camera_info

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
LENS = (-0.33, 0.12, -0.0004, 0.0003)
SIZE = (640, 360)


@pytest.fixture(scope="module")
def scripts():
    sys.path.insert(0, str(SCRIPTS))
    try:
        import eval_flight
        import independent_flight
    finally:
        sys.path.remove(str(SCRIPTS))
    return independent_flight, eval_flight


@pytest.fixture(scope="module")
def flight(scripts, tmp_path_factory):
    """(folder, observations.jsonl) of the tiny distorted flight, drawn and observed once."""
    independent_flight, _ = scripts
    out = tmp_path_factory.mktemp("eval_flight")
    options = independent_flight.FlightOptions(
        dist=LENS, jpeg=(70, 90), pan_deg=20.0, distance_m=14.0, truth=True
    )
    independent_flight.write_flight(out, 20, *SIZE, seed=5, options=options)
    obs = out / "observations.jsonl"
    code = signpose(
        ["observe", str(out / "video.mp4"), "--map", str(bundled_map_path()),
         "--camera", str(out / "camera.yaml"), "--out", str(obs), "--workers", "1", "-q"]
    )  # fmt: skip
    assert code == 0
    return out, obs


def _read(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines() if line]


def test_the_lens_round_trips_through_the_camera_model(scripts, flight):
    """A pinhole pixel distorted by the drawing and undistorted by signpose comes back,
    and each raw pixel of the drawing samples the canvas where signpose says it should."""
    independent_flight, _ = scripts
    camera = load_camera(flight[0] / "camera.yaml")
    assert np.allclose(camera.dist[:4], LENS)
    vv, uu = np.mgrid[0 : SIZE[1] : 7, 0 : SIZE[0] : 7]
    ideal = np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)
    raw = independent_flight.raw_from_pinhole_px(camera.K, LENS, ideal)
    assert np.abs(raw - ideal).max() > 20  # the lens bends by tens of pixels at the edges
    assert np.abs(undistort_px(camera, raw) - ideal).max() < 0.05
    lens = independent_flight.make_lens(camera.K, LENS, *SIZE)
    offset = lens.canvas_K[:2, 2] - camera.K[:2, 2]
    sampled = np.stack([lens.map_x[vv, uu].ravel(), lens.map_y[vv, uu].ravel()], axis=1)
    assert np.abs(sampled - offset - undistort_px(camera, ideal)).max() < 0.05


def test_the_truth_is_where_signpose_projects_the_map(flight):
    """truth.jsonl's keypoints are the map's, projected by signpose through camera.yaml."""
    out, _ = flight
    camera = load_camera(out / "camera.yaml")
    gt = np.loadtxt(out / "groundtruth.tum", comments="#", ndmin=2)
    signs = {s.code: s for s in load_map(bundled_map_path()).signs}
    worst, n = 0.0, 0
    for line in _read(out / "truth.jsonl"):
        world_T_cam = np.eye(4)
        world_T_cam[:3, :3] = rotation_from_quat_xyzw(gt[line["frame"], 4:8])[0]
        world_T_cam[:3, 3] = gt[line["frame"], 1:4]
        for t in line["signs"]:
            names, points = zip(*signs[t["code"]].keypoints_world().items(), strict=True)
            px, _ = pixel_from_world_point(camera, world_T_cam, np.array(points))
            truth = np.array([t["keypoints_px"][name] for name in names])
            worst, n = max(worst, float(np.abs(px - truth).max())), n + len(names)
    assert n > 100
    assert worst < 0.05


def test_the_frontends_centres_lie_on_the_truth(scripts, flight):
    """Every right code's centre within 1 px of the truth (a lens the truth got wrong
    would put the signs near the edges tens of pixels off)."""
    _, eval_flight = scripts
    out, obs = flight
    check = eval_flight.check_codes(_read(obs), _read(out / "truth.jsonl"))
    centres = np.asarray(check.keypoints["center"], float)
    assert len(centres) >= 20
    assert np.abs(centres[:, 2:4]).max() < 1.0
    assert (centres[:, 6] > 0.5).any()  # some of them in the outer half of the image


def test_a_swapped_code_a_false_sign_and_a_moved_box_are_told_apart(scripts, flight, tmp_path):
    _, eval_flight = scripts
    out, obs = flight
    truth = _read(out / "truth.jsonl")
    frames = _read(obs)
    before = eval_flight.check_codes(frames, truth)
    i, j, k = [n for n, f in enumerate(frames) if f["signs"]][:3]
    changed = json.loads(json.dumps(frames))
    # Frame i: one observation's code swapped for another code drawn in that frame.
    victim = changed[i]["signs"][0]
    other = next(
        s["code"] for s in truth[frames[i]["frame"]]["signs"] if s["code"] != victim["code"]
    )
    true_code, victim["code"] = victim["code"], other
    # Frame j: an observation moved, box and keypoints, into the corner where no sign is.
    changed[j]["signs"][0]["bbox_px"] = [0.0, 0.0, 3.0, 3.0]
    changed[j]["signs"][0]["keypoints_px"] = {"center": [1.5, 1.5]}
    # Frame k: only the box moved off the sign its keypoints are on.
    changed[k]["signs"][0]["bbox_px"] = [0.0, 0.0, 3.0, 3.0]
    copy = tmp_path / "observations.jsonl"
    copy.write_text("".join(json.dumps(f) + "\n" for f in changed))
    after = eval_flight.check_codes(_read(copy), truth)
    new = {w[0]: w[3] for w in set(after.wrong) - set(before.wrong)}
    assert len(after.wrong) == len(before.wrong) + 3
    assert new == {
        frames[i]["frame"]: f"misread {true_code}",
        frames[j]["frame"]: "false",
        frames[k]["frame"]: "box off its sign",
    }
    summary = eval_flight.code_summary(after)
    assert summary["wrong_codes"] == eval_flight.code_summary(before)["wrong_codes"] + 2


def test_ok_poses_beyond_3_sigma_are_counted(scripts, flight, tmp_path):
    """A trajectory.csv equal to the truth but for one ok frame 4 sigma off in y."""
    _, eval_flight = scripts
    gt = np.loadtxt(flight[0] / "groundtruth.tum", comments="#", ndmin=2)
    path = tmp_path / "trajectory.csv"
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["method", "frame", "t_s", "x_m", "y_m", "z_m", "sigma_x_m", "sigma_y_m",
                    "sigma_z_m", "status"])  # fmt: skip
        for k, row in enumerate(gt):
            y = row[2] + (0.04 if k == 3 else 0.0)
            w.writerow(["smoothed", k, row[0], row[1], y, row[3], 0.01, 0.01, 0.01, "ok"])
        w.writerow(["smoothed", len(gt), len(gt) / 30, "", "", "", "", "", "", "bridged"])
    m = eval_flight.pose_metrics(path, gt, len(gt) + 1)["smoothed"]
    assert (m["ok"], m["ok_beyond_3sigma"], m["posed"]) == (len(gt), 1, len(gt))
    assert m["max_m"] == pytest.approx(0.04)
    assert m["status"]["bridged"] == pytest.approx(1 / (len(gt) + 1), abs=1e-4)


def test_a_dropped_unhidden_sign_is_missed_and_decodes_on_its_true_box(scripts, flight):
    _, eval_flight = scripts
    out, obs = flight
    truth = _read(out / "truth.jsonl")
    frames = _read(obs)
    before = eval_flight.check_codes(frames, truth)
    # Drop the first observation of a sign no occluder touches.
    i, code = next(
        (n, s["code"])
        for n, f in enumerate(frames)
        for s in f["signs"]
        if next(t for t in truth[f["frame"]]["signs"] if t["code"] == s["code"])["hidden"] == 0
    )
    frames[i]["signs"] = [s for s in frames[i]["signs"] if s["code"] != code]
    after = eval_flight.check_codes(frames, truth)
    assert len(after.missed) == len(before.missed) + 1
    reasons = eval_flight.missed_reasons(out, truth, after, load_map(bundled_map_path()).codes)
    assert reasons.get("decoded on its true box", 0) >= 1
    assert sum(reasons.values()) == sum(m[3] == 0.0 for m in after.missed)


# --------------------------------------------------------------------------- a fisheye lens

FISHEYE = (-0.012, 0.021, -0.019, 0.0072)  # eval_flight's "fisheye" flight's lens
FISHEYE_SIZE = (1280, 720)
FISHEYE_HFOV_DEG = 120.0


@pytest.fixture(scope="module")
def fisheye_camera(scripts, tmp_path_factory):
    """(camera as drawn, camera read back by signpose from the camera.yaml written for it)."""
    independent_flight, _ = scripts
    options = independent_flight.FlightOptions(
        dist=FISHEYE, lens="equidistant", hfov_deg=FISHEYE_HFOV_DEG
    )
    drawn = independent_flight.flight_camera(options, *FISHEYE_SIZE)
    path = tmp_path_factory.mktemp("fisheye") / "camera.yaml"
    write_camera_info(path, drawn)
    return drawn, load_camera(path)


def _raw_grid(size: tuple[int, int], step: int) -> np.ndarray:
    """Raw pixels every ``step`` px, the four corner pixels included."""
    w, h = size
    uu, vv = np.meshgrid([*range(0, w, step), w - 1], [*range(0, h, step), h - 1])
    return np.stack([uu.ravel(), vv.ravel()], axis=1).astype(float)


def test_the_fisheye_lens_round_trips_through_signposts_reader_to_the_corners(
    scripts, fisheye_camera
):
    """A pinhole pixel distorted by the drawing's own equidistant model and undistorted by
    signpose (cv2.fisheye, the camera.yaml read back) comes back within 0.05 px, corners too."""
    independent_flight, _ = scripts
    drawn, camera = fisheye_camera
    assert camera.model == "equidistant"
    assert np.allclose(camera.dist, FISHEYE) and np.allclose(camera.K, drawn.K)
    raw_grid = _raw_grid(FISHEYE_SIZE, 40)
    ideal = independent_flight.pinhole_from_raw_px(camera.K, FISHEYE, raw_grid, "equidistant")
    raw = independent_flight.raw_from_pinhole_px(camera.K, FISHEYE, ideal, "equidistant")
    assert np.abs(raw - raw_grid).max() < 1e-6  # the drawing's own inverse
    assert np.abs(ideal - raw).max() > 500  # the corners move by hundreds of pixels
    back = undistort_px(camera, raw)
    err = np.linalg.norm(back - ideal, axis=1)
    corners = (raw_grid[:, 0] % (FISHEYE_SIZE[0] - 1) == 0) & (
        raw_grid[:, 1] % (FISHEYE_SIZE[1] - 1) == 0
    )
    assert corners.sum() == 4
    assert err[corners].max() < 0.05
    assert err.max() < 0.05
    # ... and signpose's projection of the undistorted point lands on the raw pixel.
    cam = np.column_stack([(ideal - camera.K[:2, 2]) / camera.K[0, 0], np.ones(len(ideal))])
    assert np.abs(pixel_from_cam_point(camera, cam) - raw).max() < 0.05


def test_the_fisheye_spans_the_field_of_view_asked_for(fisheye_camera):
    """The rays signpose undistorts the principal row's end pixels to are hfov apart; the
    corners see beyond 65 deg (a real wide-angle lens, not a pinhole)."""
    _, camera = fisheye_camera
    w, h = FISHEYE_SIZE
    ends = np.array([[0.0, camera.cy], [w - 1.0, camera.cy]])
    x = (undistort_px(camera, ends)[:, 0] - camera.cx) / camera.fx
    assert np.degrees(np.arctan(x[1]) - np.arctan(x[0])) == pytest.approx(
        FISHEYE_HFOV_DEG, abs=0.01
    )
    corner = (undistort_px(camera, np.array([[0.0, 0.0]]))[0] - camera.K[:2, 2]) / camera.fx
    assert np.degrees(np.arctan(np.hypot(*corner))) > 65.0


def test_the_fisheye_canvas_is_sampled_where_signpose_undistorts(scripts, fisheye_camera):
    """Each raw pixel of a fisheye frame samples the pinhole canvas where signpose's
    undistortion puts it (the drawing's remap map against cv2.fisheye)."""
    independent_flight, _ = scripts
    _, camera = fisheye_camera
    lens = independent_flight.make_lens(camera.K, FISHEYE, *FISHEYE_SIZE, lens="equidistant")
    raw = _raw_grid(FISHEYE_SIZE, 23).astype(int)
    offset = lens.canvas_K[:2, 2] - camera.K[:2, 2]
    sampled = np.stack([lens.map_x[raw[:, 1], raw[:, 0]], lens.map_y[raw[:, 1], raw[:, 0]]], 1)
    assert np.abs(sampled - offset - undistort_px(camera, raw.astype(float))).max() < 0.05


def test_a_lens_the_drawing_cannot_hold_is_refused(scripts):
    """Coefficients of the wrong count, or a fisheye whose corners see past 85 deg: an error,
    not a silently wrong drawing (the script exits 2 with one line)."""
    independent_flight, _ = scripts
    wrong = independent_flight.FlightOptions(dist=(0.1, 0.2), lens="equidistant", hfov_deg=120)
    with pytest.raises(ValueError, match="4 coefficients"):
        independent_flight.flight_camera(wrong, *FISHEYE_SIZE)
    wide = independent_flight.FlightOptions(dist=FISHEYE, lens="equidistant", hfov_deg=170)
    camera = independent_flight.flight_camera(wide, *FISHEYE_SIZE)
    with pytest.raises(ValueError, match="85 deg"):
        independent_flight.make_lens(camera.K, FISHEYE, *FISHEYE_SIZE, lens="equidistant")
    argv = ["/nonexistent", "--lens", "equidistant", "--distortion", "0.1", "0.2"]
    assert independent_flight.main(argv) == 2


def test_the_action_cams_lens_round_trips_and_spans_its_field_of_view(scripts, tmp_path):
    """The cheap action camera's plumb_bob (k1..k3 and p1, p2) at 100 deg across: drawn and
    undistorted by signpose within 0.05 px to the corners, the principal row ~100 deg."""
    independent_flight, eval_flight = scripts
    spec = next(s for s in eval_flight.WIDE_SET if s.name == "action_cam")
    dist = spec.options.dist
    drawn = independent_flight.flight_camera(spec.options, spec.width, spec.height)
    write_camera_info(tmp_path / "camera.yaml", drawn)
    camera = load_camera(tmp_path / "camera.yaml")
    assert camera.model == "plumb_bob" and np.allclose(camera.dist, dist)
    raw_grid = _raw_grid((spec.width, spec.height), 40)
    ideal = independent_flight.pinhole_from_raw_px(camera.K, dist, raw_grid)
    raw = independent_flight.raw_from_pinhole_px(camera.K, dist, ideal)
    assert np.abs(raw - raw_grid).max() < 1e-6
    assert np.abs(ideal - raw).max() > 200
    assert np.abs(undistort_px(camera, raw) - ideal).max() < 0.05
    ends = np.array([[0.0, camera.cy], [spec.width - 1.0, camera.cy]])
    x = (undistort_px(camera, ends)[:, 0] - camera.cx) / camera.fx
    assert np.degrees(np.arctan(x[1]) - np.arctan(x[0])) == pytest.approx(100.0, abs=0.5)


def test_the_off_axis_angle_is_where_the_lens_puts_the_sign(scripts, flight):
    """Each drawn sign's off-axis angle (from the ground-truth pose and the map) is the angle
    of the ray signpose undistorts its true raw centre to; the unhidden recall's bins hold
    every unhidden visible sign."""
    _, eval_flight = scripts
    out, obs = flight
    camera = load_camera(out / "camera.yaml")
    gt = eval_flight.read_gt(out / "groundtruth.tum")
    truth = eval_flight.with_incidence(_read(out / "truth.jsonl"), load_map(bundled_map_path()), gt)
    signs = [s for t in truth for s in t["signs"]]
    und = undistort_px(camera, np.array([s["center_px"] for s in signs]))
    ray = np.column_stack([(und - camera.K[:2, 2]) / camera.fx, np.ones(len(und))])
    angle = np.degrees(np.arccos(ray[:, 2] / np.linalg.norm(ray, axis=1)))
    assert angle.max() > 20
    assert np.abs(angle - [s["off_axis_deg"] for s in signs]).max() < 0.05
    summary = eval_flight.code_summary(eval_flight.check_codes(_read(obs), truth))
    by_angle = summary["recall_unhidden_by_off_axis"].values()
    assert sum(n for n, _, _ in by_angle) == summary["visible_unhidden"]
    assert sum(n - f for n, f, _ in by_angle) == summary["missed_unhidden"]


def test_a_fisheye_flights_truth_is_where_signpose_projects_the_map(scripts, tmp_path):
    """truth.jsonl of a tiny fisheye flight (4 frames at 640x360, 120 deg across, panned
    toward the edges) gives raw pixels: the map's keypoints projected by signpose
    (cv2.fisheye) through the camera.yaml the drawing wrote, within 0.05 px."""
    independent_flight, _ = scripts
    options = independent_flight.FlightOptions(
        dist=FISHEYE, lens="equidistant", hfov_deg=FISHEYE_HFOV_DEG, pan_deg=50.0,
        distance_m=7.0, trajectory="lawnmower", speed_mps=2.0, truth=True,
    )  # fmt: skip
    independent_flight.write_flight(tmp_path, 4, 640, 360, seed=3, options=options)
    camera = load_camera(tmp_path / "camera.yaml")
    assert camera.model == "equidistant"
    gt = np.loadtxt(tmp_path / "groundtruth.tum", comments="#", ndmin=2)
    signs = {s.code: s for s in load_map(bundled_map_path()).signs}
    worst, far, n = 0.0, 0.0, 0
    for line in _read(tmp_path / "truth.jsonl"):
        world_T_cam = np.eye(4)
        world_T_cam[:3, :3] = rotation_from_quat_xyzw(gt[line["frame"], 4:8])[0]
        world_T_cam[:3, 3] = gt[line["frame"], 1:4]
        for t in line["signs"]:
            names, points = zip(*signs[t["code"]].keypoints_world().items(), strict=True)
            px, _ = pixel_from_world_point(camera, world_T_cam, np.array(points))
            truth = np.array([t["keypoints_px"][name] for name in names])
            worst, n = max(worst, float(np.abs(px - truth).max())), n + len(names)
            far = max(far, float(np.hypot(*(truth[0] - camera.K[:2, 2]))))
    assert n > 30
    assert far > 200  # signs well off the axis (~37 deg; the half diagonal is 367 px)
    assert worst < 0.05
