"""Flight simulator: rendered geometry, outputs, determinism, errors, CLI."""

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest
from conftest import clean_sim_options, white_centroid_px
from signpose.estimator.camera import pixel_from_world_point
from signpose.frontend.sign import LOCATION_SIDE_R, all_slot_keypoints, fill_polygon_aa
from signpose.maps.loader import load_map

from signpose.cli import main
from signpose.core.errors import InputError, OutputError
from signpose.io.boxes import (
    FrameConditions,
    FrameTruth,
    SignTruth,
    read_boxes,
    read_frame_truths,
    write_boxes,
)
from signpose.io.camera_file import load_camera
from signpose.io.frames_csv import FrameStamp, read_frames_csv, write_frames_csv
from signpose.io.tum import read_tum
from signpose.sim import scene as scene_module
from signpose.sim.flight import (
    FORMATS,
    SimSettings,
    lighting_at,
    pose_at,
    simulate,
    simulated_camera,
)
from signpose.sim.frame import render_frame
from signpose.sim.photos import available_photos
from signpose.sim.pylon import LATTICE_BGR
from signpose.sim.render import SIGN_BLACK, SIGN_WHITE, line_kernel
from signpose.sim.scene import SceneOptions, build_scene
from signpose.sim.trajectories import make_trajectory
from signpose.sim.writers import make_frame_writer

NO_BACKGROUND = SceneOptions(background=False)

SMALL = SimSettings(frames=4, width=480, height=270, hfov_deg=20.0)


def _outputs(result) -> dict[str, bytes]:
    files = [p for p in result.paths() if p.is_file()]
    if result.frames_path.is_dir():
        files += sorted(result.frames_path.iterdir())
    return {str(p.relative_to(result.out_dir)): p.read_bytes() for p in files}


def _window_radius(camera, pose, scene, code) -> float | None:
    """Radius around the centre holding the whole location square but no other white part."""
    sign = next(s for s in scene.signs if s.code == code)
    c, _ = pixel_from_world_point(camera, pose, sign.center_m[None])
    dists = [
        np.linalg.norm(pixel_from_world_point(camera, pose, poly)[0] - c, axis=1)
        for poly in sign.white_m
    ]
    inner, outer = dists[0].max(), min(d.min() for d in dists[1:])
    # Seen obliquely the square's corner can come within a pixel of the directional
    # rectangle; their anti-aliased edges then mix and the measurement is not clean.
    return 0.5 * (inner + outer) if outer - inner > 1.5 else None


@pytest.mark.parametrize(
    "trajectory,frames", [("climb-hover-depart", (0, 60, 130)), ("orbit", (5, 150))]
)
def test_location_square_centre_matches_projected_map_centre(demo_map, trajectory, frames):
    """Clean 1080p renders through the distorted lens: white-square centroid vs truth."""
    settings = SimSettings()  # 1920x1080, 60 deg, k1 = -0.05
    camera = simulated_camera(settings)
    assert camera.dist[0] == -0.05
    scene = build_scene(demo_map, camera, seed=0, options=NO_BACKGROUND)
    traj = make_trajectory(trajectory, demo_map, n_frames=210, fps=30.0)
    poses = traj.world_T_cam()
    checked = 0
    for i in frames:
        image, truths = render_frame(
            scene, poses[i], np.random.default_rng(0), options=clean_sim_options()
        )
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        assert len(truths) == len(demo_map.signs)
        for t in truths:
            sign = demo_map.sign(t.code)
            px, _ = pixel_from_world_point(camera, poses[i], sign.center_m[None])
            np.testing.assert_allclose(t.center_px, px[0], atol=1e-9)
            assert t.diameter_px > 30  # big enough for a clean measurement
            radius = _window_radius(camera, poses[i], scene, t.code)
            if radius is None:
                continue
            measured = white_centroid_px(gray, t.center_px, radius)
            err = np.linalg.norm(measured - np.asarray(t.center_px))
            assert err < 0.5, f"frame {i} sign {t.code}: centre off by {err:.3f} px"
            checked += 1
    assert checked >= 10


def test_motion_blur_keeps_the_location_square_centre(demo_map):
    """Blur is the symmetric exposure segment around the stamp: the centroid stays put."""
    camera = simulated_camera(SimSettings())
    scene = build_scene(demo_map, camera, options=NO_BACKGROUND)
    traj = make_trajectory("lawnmower", demo_map, 210, 30.0)
    poses, stamps = traj.world_T_cam(), traj.stamps_s
    opts = replace(clean_sim_options(), blur=True)
    half = 0.5 / 30.0 / 2
    checked, moved = 0, 0.0
    for i in (30, 100):
        exposure = (
            pose_at(poses, stamps, stamps[i] - half),
            pose_at(poses, stamps, stamps[i] + half),
        )
        sharp, _ = render_frame(
            scene, poses[i], np.random.default_rng(0), options=clean_sim_options()
        )
        image, truths = render_frame(
            scene, poses[i], np.random.default_rng(0), options=opts, exposure_poses=exposure
        )
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        moved = max(moved, np.abs(image.astype(int) - sharp.astype(int)).max())
        for t in truths:
            radius = _window_radius(camera, poses[i], scene, t.code)
            if radius is None or t.truncated:
                continue
            err = np.linalg.norm(white_centroid_px(gray, t.center_px, radius) - t.center_px)
            assert err < 0.5, f"frame {i} sign {t.code}: centre off by {err:.3f} px"
            checked += 1
    assert checked >= 10
    assert moved > 50  # the blur is real


def test_truth_keypoints_are_on_white_and_black_slots_dark(demo_map):
    camera = simulated_camera(SimSettings())
    scene = build_scene(demo_map, camera, options=NO_BACKGROUND)
    pose = make_trajectory("orbit", demo_map, 60, 30.0).world_T_cam()[10]
    image, truths = render_frame(scene, pose, np.random.default_rng(0), options=clean_sim_options())
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(float)
    mid = 0.5 * (SIGN_BLACK + SIGN_WHITE)
    checked = 0
    for t in truths:
        sign = demo_map.sign(t.code)
        R = sign.world_R_sign()
        for name, p in all_slot_keypoints(sign.diameter_m).items():
            px, _ = pixel_from_world_point(camera, pose, (sign.center_m + R @ p)[None])
            u, v = px[0]
            value = gray[int(round(v)), int(round(u))]
            if name in t.keypoints_px:
                assert value > mid, f"{t.code} {name} is not white ({value})"
                np.testing.assert_allclose(t.keypoints_px[name], (u, v), atol=1e-6)
            else:
                assert value < mid, f"{t.code} black {name} is not dark ({value})"
            checked += 1
    assert checked >= 50


def test_location_square_size_in_image(demo_map):
    camera = simulated_camera(SimSettings())
    scene = build_scene(demo_map, camera, options=NO_BACKGROUND)
    pose = make_trajectory("climb-hover-depart", demo_map, 30, 30.0).world_T_cam()[15]
    image, truths = render_frame(scene, pose, np.random.default_rng(0), options=clean_sim_options())
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(float)
    t = truths[0]
    r = 0.31 * t.diameter_px / 2
    u, v = np.round(t.center_px).astype(int)
    patch = gray[v - int(r) : v + int(r) + 1, u - int(r) : u + int(r) + 1]
    lo, hi = patch.min(), patch.max()
    area_px = ((patch - lo) / (hi - lo)).sum()
    expected = (LOCATION_SIDE_R * t.diameter_px / 2) ** 2
    assert area_px == pytest.approx(expected, rel=0.15)


def test_truth_fields_are_consistent(demo_map):
    scene = build_scene(demo_map, simulated_camera(SimSettings()), options=NO_BACKGROUND)
    pose = make_trajectory("lawnmower", demo_map, 40, 30.0).world_T_cam()[20]
    _, truths = render_frame(scene, pose, np.random.default_rng(0), options=clean_sim_options())
    assert truths
    for t in truths:
        x, y, w, h = t.bbox_px
        assert w > 0 and h > 0
        assert t.keypoints_px["center"] == pytest.approx(t.center_px)
        for u, v in t.keypoints_px.values():
            assert x <= u <= x + w and y <= v <= y + h
        assert max(w, h) == pytest.approx(t.diameter_px, rel=0.1)
        assert 20.0 < t.distance_m < 40.0


def test_simulate_writes_everything_and_is_deterministic(demo_map, tmp_path):
    settings = SimSettings(
        frames=4, width=480, height=270, hfov_deg=20.0, dirt=True, occlusion=True
    )
    a = simulate(demo_map, tmp_path / "a", settings, progress=False)
    b = simulate(demo_map, tmp_path / "b", settings, progress=False)
    out_a, out_b = _outputs(a), _outputs(b)
    assert sorted(out_a) == [
        "boxes.jsonl",
        "camera.yaml",
        "groundtruth.tum",
        "map.yaml",
        "video.mp4",
    ]
    assert out_a == out_b  # same seed, same bytes (mp4v included)
    assert sorted(p.name for p in a.out_dir.iterdir()) == sorted(out_a)  # no temp files left
    # The video decodes to the right number and size of frames.
    cap = cv2.VideoCapture(str(a.frames_path))
    n = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        assert frame.shape == (270, 480, 3)
        n += 1
    cap.release()
    assert n == 4
    c = simulate(
        demo_map, tmp_path / "c", SimSettings(**{**settings.__dict__, "seed": 1}), progress=False
    )
    assert _outputs(c)["video.mp4"] != out_a["video.mp4"]


def test_simulate_png_outputs_and_ground_truth_files(demo_map, tmp_path):
    settings = SimSettings(frames=3, width=480, height=270, hfov_deg=20.0, format="png", fps=25.0)
    res = simulate(demo_map, tmp_path / "png", settings, progress=False)
    frames = sorted(p for p in res.frames_path.iterdir() if p.suffix == ".png")
    assert [p.name for p in frames] == ["000000.png", "000001.png", "000002.png"]
    assert cv2.imread(str(frames[0])).shape == (270, 480, 3)
    # frames.csv makes the folder an input that needs no --fps.
    from signpose.io.sources import open_source

    stamps = [f.stamp_ns for f in open_source(res.frames_path)]
    assert stamps == [0, 40_000_000, 80_000_000]
    again = simulate(demo_map, tmp_path / "png2", settings, progress=False)
    assert _outputs(res) == _outputs(again)
    cam = load_camera(res.camera_path)
    assert (cam.width, cam.height) == (480, 270) and cam.dist[0] == pytest.approx(-0.05)
    gt = read_tum(res.groundtruth_path)
    np.testing.assert_allclose(gt.stamps_s, [0.0, 0.04, 0.08])
    np.testing.assert_allclose(gt.world_t_cam, res.trajectory.world_t_cam, atol=1e-6)
    assert load_map(res.map_path).codes == demo_map.codes
    boxes = read_boxes(res.boxes_path)
    assert [b["frame"] for b in boxes] == [0, 1, 2]
    assert [b["stamp_ns"] for b in boxes] == [0, 40_000_000, 80_000_000]
    for line in boxes:
        for s in line["signs"]:
            assert set(s) >= {"code", "bbox_px", "center_px", "diameter_px", "keypoints_px"}
            assert isinstance(s["occluded"], bool)
            # The boxes hold the truth of the written camera: re-project the map centre.
            pose = gt.world_T_cam()[line["frame"]]
            px, _ = pixel_from_world_point(cam, pose, demo_map.sign(s["code"]).center_m[None])
            np.testing.assert_allclose(s["center_px"], px[0], atol=1e-3)


def test_occlusion_and_dirt_change_the_signs(demo_map):
    camera = simulated_camera(SMALL)
    clean = build_scene(demo_map, camera, seed=3, options=NO_BACKGROUND)
    dirty = build_scene(
        demo_map, camera, seed=3, options=SceneOptions(dirt=True, occlusion=True, background=False)
    )
    assert any(s.occluders_m for s in dirty.signs) and any(s.dirt_m for s in dirty.signs)
    pose = make_trajectory("climb-hover-depart", demo_map, 10, 30.0).world_T_cam()[5]
    opts = clean_sim_options()
    img_c, truth_c = render_frame(clean, pose, np.random.default_rng(0), options=opts)
    img_d, truth_d = render_frame(dirty, pose, np.random.default_rng(0), options=opts)
    assert not np.array_equal(img_c, img_d)
    occluded = {t.code for t in truth_d if t.occluded}
    assert occluded == {s.code for s in dirty.signs if s.occluders_m}
    assert not any(t.occluded for t in truth_c)


def test_full_render_is_deterministic_per_rng_and_textured(demo_map):
    camera = simulated_camera(SMALL)
    scene = build_scene(demo_map, camera, seed=0)
    traj = make_trajectory("orbit", demo_map, 30, 30.0)
    poses = traj.world_T_cam()
    exposure = (pose_at(poses, traj.stamps_s, 0.49), pose_at(poses, traj.stamps_s, 0.51))
    kw = dict(exposure_poses=exposure, gain=1.1, offset=-4.0)
    a, _ = render_frame(scene, poses[15], np.random.default_rng(5), **kw)
    b, _ = render_frame(scene, poses[15], np.random.default_rng(5), **kw)
    c, _ = render_frame(scene, poses[15], np.random.default_rng(6), **kw)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)  # the noise differs
    # Not a flat background: sky and ground differ, and there is texture.
    assert a.std() > 20
    assert np.abs(a[5].astype(float).mean(axis=0) - a[-5].astype(float).mean(axis=0)).max() > 20


def test_motion_blur_kernel_is_normalised_and_centred():
    assert line_kernel(np.array([0.2, 0.1])) is None
    for motion in ([4.0, 0.0], [3.0, -2.5], [0.0, 7.3]):
        k = line_kernel(np.array(motion)).astype(float)
        assert k.sum() == pytest.approx(1.0)
        ys, xs = np.mgrid[: k.shape[0], : k.shape[1]]
        c = (k.shape[0] - 1) / 2
        assert (k * xs).sum() == pytest.approx(c, abs=1e-6)
        assert (k * ys).sum() == pytest.approx(c, abs=1e-6)
        # Spread along the motion: second moment ~ L^2 / 12.
        m = np.asarray(motion)
        d = ((xs - c) * m[0] + (ys - c) * m[1]) / np.linalg.norm(m)
        assert (k * d**2).sum() == pytest.approx(np.dot(m, m) / 12, rel=0.3, abs=0.2)


def test_pose_interpolation_and_lighting_are_smooth(demo_map):
    traj = make_trajectory("orbit", demo_map, 20, 10.0)
    poses = traj.world_T_cam()
    np.testing.assert_allclose(pose_at(poses, traj.stamps_s, traj.stamps_s[7]), poses[7], atol=1e-9)
    mid = pose_at(poses, traj.stamps_s, 0.5 * (traj.stamps_s[7] + traj.stamps_s[8]))
    np.testing.assert_allclose(mid[:3, 3], 0.5 * (poses[7][:3, 3] + poses[8][:3, 3]), atol=1e-9)
    R = mid[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
    gains = [lighting_at(t, 0)[0] for t in np.arange(0, 10, 1 / 30)]
    assert 0.75 < min(gains) < max(gains) < 1.25
    assert np.abs(np.diff(gains)).max() < 0.01


def test_unwritable_out_dir_raises_output_error(demo_map, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(OutputError, match="file"):
        simulate(demo_map, blocker / "out", SMALL, progress=False)


def test_bad_settings_raise_input_error(demo_map, tmp_path):
    for bad in (
        SimSettings(frames=0),
        SimSettings(trajectory="loop"),
        SimSettings(format="avi"),
        SimSettings(jpeg_quality=0),
    ):
        with pytest.raises(InputError):
            simulate(demo_map, tmp_path / "x", bad, progress=False)


@pytest.mark.parametrize("fmt", ["mp4", "png"])
def test_frame_writer_leaves_nothing_on_failure(tmp_path, fmt):
    frame = np.zeros((64, 96, 3), np.uint8)
    camera = simulated_camera(SimSettings(width=96, height=64))
    with pytest.raises(RuntimeError), make_frame_writer(fmt, tmp_path, 30.0, camera) as w:
        w.write(0, 0, frame)
        raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_cli_simulate(tmp_path, capsys):
    out = tmp_path / "sim"
    args = ["simulate", "--out", str(out), "--frames", "2", "--width", "320", "--height", "180"]
    assert main(args + ["--format", "png", "--dirt", "--occlusion"]) == 0
    printed = capsys.readouterr().out
    for name in ("frames", "camera.yaml", "groundtruth.tum", "boxes.jsonl", "map.yaml"):
        assert str(out / name) in printed
    lines = (out / "boxes.jsonl").read_text().splitlines()
    assert len(lines) == 2 and json.loads(lines[1])["frame"] == 1
    with pytest.raises(SystemExit) as info:
        main(args + ["--trajectory", "nowhere"])
    assert info.value.code == 2


def test_every_format_writes_its_frames(demo_map, tmp_path):
    names = {"mp4": "video.mp4", "png": "frames", "mcap": "flight.mcap"}
    for fmt in FORMATS:
        settings = SimSettings(frames=2, width=160, height=90, format=fmt)
        res = simulate(demo_map, tmp_path / fmt, settings, progress=False)
        assert res.frames_path == tmp_path / fmt / names[fmt]
        assert res.frames_path.exists()


def test_frames_csv_round_trip_and_errors(tmp_path):
    rows = [FrameStamp("000000.png", 0), FrameStamp("000001.png", 33_333_333)]
    path = write_frames_csv(tmp_path / "frames.csv", rows)
    assert path.read_text(encoding="utf-8").splitlines()[0] == "filename,stamp_ns"
    back = read_frames_csv(path)
    assert [(r.filename, r.stamp_ns) for r in back] == [(r.filename, r.stamp_ns) for r in rows]
    assert [r.line for r in back] == [2, 3]
    for text, message in (
        ("name,time\na.png,0\n", "header"),
        ("filename,stamp_ns\na.png,1.5\n", "line 2: stamp_ns '1.5' is not an integer"),
        ("filename,stamp_ns\na.png\n", "line 2: expected"),
        ("filename,stamp_ns\n\n", "lists no frames"),
    ):
        (tmp_path / "bad.csv").write_text(text, encoding="utf-8")
        with pytest.raises(InputError, match=message):
            read_frames_csv(tmp_path / "bad.csv")


def test_boxes_round_trip_keeps_every_field(tmp_path):
    sign = SignTruth(
        code="0101",
        bbox_px=(10.0, 20.5, 30.25, 31.0),
        center_px=(25.1234, 36.0),
        diameter_px=30.5,
        keypoints_px={"center": (25.1234, 36.0), "slot2": (30.0, 40.0)},
        occluded=True,
        truncated=False,
        distance_m=27.25,
        covered_slots=(2,),
        part_cover={"center": 0.0, "slot2": 0.5},
        occluders=("member",),
        fade=0.25,
        dirty=True,
        glare_dn=40.0,
    )
    frames = [
        FrameTruth(0, 0, (sign,), FrameConditions(80, 1.1, -2.0, (1.5, 0.0), "photo:rocket")),
        FrameTruth(1, 33_333_333, ()),
    ]
    path = write_boxes(tmp_path / "boxes.jsonl", frames)
    assert read_frame_truths(path) == frames
    assert read_boxes(path)[0]["signs"][0]["covered_slots"] == [2]
    # Files from before the occlusion truth existed still read, with defaults.
    old = {
        "frame": 0,
        "stamp_ns": 0,
        "signs": [{k: v for k, v in sign.to_json().items() if k not in ("covered_slots", "fade")}],
    }
    (tmp_path / "old.jsonl").write_text(json.dumps(old) + "\n", encoding="utf-8")
    assert read_frame_truths(tmp_path / "old.jsonl")[0].signs[0].covered_slots == ()
    (tmp_path / "bad.jsonl").write_text("{not json\n", encoding="utf-8")
    with pytest.raises(InputError, match="line 1"):
        read_boxes(tmp_path / "bad.jsonl")


def _slot_means(image, camera, pose, sign):
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(float)
    out = {}
    for name, poly_m in sign.parts_m.items():
        mask = np.zeros(gray.shape, float)
        fill_polygon_aa(mask, pixel_from_world_point(camera, pose, poly_m)[0], 1.0, 4)
        out[name] = (float((mask * gray).sum() / mask.sum()), float(mask.sum()))
    return out


def test_members_in_front_mark_the_slots_they_cover_and_darken_them(demo_map):
    """The covered-part truth against the pixels: a member over part p darkens it by its share."""
    camera = simulated_camera(SimSettings())
    options = SceneOptions(background=False, members=1.0)
    scene = build_scene(demo_map, camera, seed=1, options=options)
    assert len(scene.members) == len(demo_map.signs)
    bare = replace(scene, members=())
    traj = make_trajectory("orbit", demo_map, 60, 30.0)
    member_grey = float(np.mean(LATTICE_BGR))  # a grey: B, G and R nearly equal
    checked = covered = 0
    for pose in traj.world_T_cam()[::12]:
        image, truths = render_frame(
            scene, pose, np.random.default_rng(0), options=clean_sim_options()
        )
        clean, _ = render_frame(bare, pose, np.random.default_rng(0), options=clean_sim_options())
        for t in truths:
            if t.truncated:
                continue
            sign = next(s for s in scene.signs if s.code == t.code)
            before = _slot_means(clean, camera, pose, sign)
            after = _slot_means(image, camera, pose, sign)
            for k in range(1, 5):
                assert (k in t.covered_slots) == (t.part_cover[f"slot{k}"] >= 0.2)
            for name, share in t.part_cover.items():
                (mean_before, area_px), (mean_after, _) = before[name], after[name]
                if area_px < 40:
                    continue  # anti-aliased edges dominate a part this small
                expected = share * (mean_before - member_grey)
                assert mean_before - mean_after == pytest.approx(expected, abs=8.0), name
                checked += 1
            covered += len(t.covered_slots)
            assert ("member" in t.occluders) == t.occluded
    assert checked > 100 and covered > 3


def test_real_pylon_conditions_are_recorded(demo_map, tmp_path):
    settings = replace(
        SimSettings(frames=12, width=480, height=270, hfov_deg=20.0, format="png").hard(),
        vibration=5.0,
        exposure_steps=3.0,
        faded=1.0,
        glare=1.0,
    )
    res = simulate(demo_map, tmp_path / "hard", settings, progress=False)
    frames = read_frame_truths(res.boxes_path)
    qualities = {f.conditions.jpeg_quality for f in frames}
    assert qualities <= set(range(70, 91)) and len(qualities) > 1
    assert any(np.hypot(*f.conditions.vibration_px) > 0 for f in frames)
    assert any(f.conditions.vibration_px == (0.0, 0.0) for f in frames)
    lighting = [lighting_at(i / settings.fps, settings.seed)[0] for i in range(len(frames))]
    assert (
        max(abs(f.conditions.gain / g - 1.0) for f, g in zip(frames, lighting, strict=True)) > 0.05
    )
    signs = [s for f in frames for s in f.signs]
    assert all(0.15 <= s.fade <= 0.5 for s in signs) and any(s.dirty for s in signs)
    assert any(s.glare_dn > 0 for s in signs)
    if available_photos():
        assert frames[0].conditions.background.startswith("photo:")
    assert any(
        isinstance(ln.widths_m, np.ndarray)
        for ln in build_scene(demo_map, res.camera, options=settings.scene_options()).lines_behind
    )


def test_photo_backgrounds_fall_back_to_procedural(demo_map, monkeypatch):
    camera = simulated_camera(SMALL)
    monkeypatch.setattr(scene_module, "available_photos", lambda names=(): ())
    scene = build_scene(demo_map, camera, options=SceneOptions(photo=True))
    assert scene.background == "procedural"
    image, _ = render_frame(
        scene,
        make_trajectory("orbit", demo_map, 5, 30.0).world_T_cam()[2],
        np.random.default_rng(0),
    )
    assert image.shape == (270, 480, 3)


def test_bad_condition_settings_raise_input_error(demo_map, tmp_path):
    for bad in (
        SimSettings(members=1.5),
        SimSettings(conductors=-1),
        SimSettings(jpeg_range=(90, 70)),
        SimSettings(vibration=-0.1),
    ):
        with pytest.raises(InputError):
            bad.validate()


def test_cli_simulate_conditions(tmp_path, capsys):
    out = tmp_path / "hard"
    args = ["simulate", "--out", str(out), "--frames", "2", "--width", "320", "--height", "180"]
    assert main(args + ["--format", "png", "--quiet", "--hard", "--jpeg-range", "75,76"]) == 0
    frames = read_frame_truths(out / "boxes.jsonl")
    assert {f.conditions.jpeg_quality for f in frames} <= {75, 76}
    with pytest.raises(SystemExit) as info:
        main(args + ["--jpeg-range", "high"])
    assert info.value.code == 2
    assert main(args + ["--members", "2"]) == 2  # InputError: a share is at most 1
    assert "members" in capsys.readouterr().err
