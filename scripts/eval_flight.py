#!/usr/bin/env python
"""End to end on flights signpose's simulator did not draw, through a real lens.

Why: the frontend, the keypoint sigmas and the pose sigmas were all tuned on
frames of ``signpose.sim`` (or crops of ``scripts/independent_scene.py``). A
user's flight is neither. This script draws flights with
``scripts/independent_flight.py`` (photographs behind the pylon, members and
conductors in front, gain drift, blur bursts, noise, and here also a
plumb_bob lens with k1 -0.25..-0.35, JPEG 70-90, camera vibration, a slow pan
that sweeps the signs to the image's edges, other trajectories and a map with
signs on two pylon faces), runs ``signpose run ... --gt`` on each as a user
would (the map it is given is the drawn one with every centre moved by
N(0, sigma_m), as a survey would leave it) and grades every output against
the truth the drawing kept (``truth.jsonl``: each sign drawn, its centre and
box in raw pixels through the lens, the share of its disc hidden):

* poses, per method: position RMSE and max error, status shares (ok / weak /
  bridged / suspect, of all frames), coverage;
* pose sigma honesty: rms(error / sigma) per world axis, and the share of
  ``ok`` poses beyond 3 sigma on some axis (Gaussian: 0.8 %);
* codes: every observation of observations.jsonl whose code has no drawn sign
  with its centre inside the observation's box (a wrong or false code, or the
  right sign with a box beside it), and recall: drawn signs >= 18 px, whole in
  the image, seen at most 60 deg off their normal, with no observation (by the
  share of the disc an occluder hides);
* keypoint honesty: rms(error / keypoint_sigma_px) of the centre keypoints
  against their true raw-pixel projections, per image axis;
* report.json's ``pixel_noise_scale``;
* with ``--surveys K``: the same observations estimated (``signpose estimate``)
  against K more survey draws of the map, pooled: every frame of a flight
  shares its map's error, so only several draws say whether the sigmas carry
  the survey's share;
* with ``--drop-lens-model``: the same observations estimated with camera.yaml's
  distortion dropped (a wrong calibration): does signpose notice?
* with ``--why-missed``: each unhidden sign the run missed decoded alone on its
  true box: the detector / tracker lost it, or the decoder refuses it (why);
* with ``--oracle``: the same observations with every keypoint moved to its
  true pixel, estimated against the same map: the estimator's share of an error;
* with ``--survey-response``: the smoothed positions' response to each sign
  centre (oracle keypoints, 3 estimates per sign, ~4 min for 12 signs and 240
  frames): the survey's share of each pose's sigma, and the chance of a survey
  draw as bad as the flight's (``survey_response``).

    nice -n 5 .venv/bin/python scripts/eval_flight.py [--quick] [--work DIR] [--json PATH]
        [--flights NAME ...] [--wide] [--without lens jpeg vibration pan members] [--surveys K]
        [--drop-lens-model] [--oracle] [--why-missed] [--survey-response] [--rerun]

``--wide`` (or ``--flights fisheye hd_fisheye_orbit action_cam``) adds three
flights through wide-angle lenses: two fisheyes (the equidistant model,
camera.yaml a ROS camera_info with ``distortion_model: equidistant``, drawn by
independent_flight.py's own model, not cv2.fisheye), 120 deg across at
1280x720 (lawnmower at 7 m) and 125 deg at 1920x1080 (orbit at 8 m), and a
cheap action camera (plumb_bob k1 -0.28 with k2, k3 and p1, p2 of 1e-3, 100 deg
across at 1280x720); not in the default set, as the fisheyes' pinhole canvases
are 2-3x the image's (the three with ``--drop-lens-model``: 9.7 min wall drawn
and run at load ~8, 2.7 min once drawn). Besides the recall by hidden share,
each flight prints the unhidden signs' recall and keypoint rms(e/sigma) per
off-axis angle (the camera's axis to the sign's centre, from the ground truth),
where a wide lens's edges show.

The default set (4 flights of 240 frames at 1280x720 and one of 150 at
1920x1080) took 12 min wall, 4.3 min CPU, on the shared 2-core machine at
load 9 (about 5 min unloaded); ``--surveys 3 --oracle --drop-lens-model`` add
as much again; ``--quick`` (2 flights of 60 frames) 40 s CPU. Flights and runs
are kept in ``--work`` and reused when their commands (and, for runs,
signpose's source files) are unchanged (``--rerun`` redoes them). Every
flight prints the commands that reproduce it.
"""

from __future__ import annotations

import argparse
import csv
import functools
import hashlib
import json
import math
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
from eval_pose_sigma import surveyed_map
from independent_flight import FlightOptions
from independent_flight import main as draw_flight
from signpose.estimator.trajectory import rotation_from_quat_xyzw
from signpose.frontend.decoder import decode_region
from signpose.maps.loader import MapSign, SignMap, bundled_map_path, load_map, write_map

from signpose.core.fileio import atomic_write, ensure_dir
from signpose.io.camera_file import load_camera, write_camera_info

SCRIPTS = Path(__file__).resolve().parent
MIN_RECALL_PX = 18.0  # signs at least this wide count for the recall
MAX_RECALL_INCIDENCE_DEG = 60.0  # ... and seen at most this far off their normal
GAUSS_BEYOND_3 = 1 - (1 - 0.0027) ** 3  # share of 3-D Gaussian errors beyond 3 sigma on some axis
STATUSES = ("ok", "weak", "bridged", "suspect")
AXES = "xyz"
SIZE_BINS_PX = (18.0, 30.0, 60.0, math.inf)
ORACLE_NAME = "observations_oracle.jsonl"
SURVEY_KEYS = ("surveys", "surveys_oracle")
# Share of a sign's disc an occluder hides: (name, above, at most).
HIDDEN_BINS = (("none", -1.0, 0.0), ("<=10%", 0.0, 0.1), ("10-25%", 0.1, 0.25), (">25%", 0.25, 1.0))
# Angle between the camera's axis and the ray to a sign's centre [deg] (a wide lens's
# edges): the unhidden signs' recall and keypoint honesty per bin (lo < angle <= hi).
OFF_AXIS_BINS_DEG = (0.0, 30.0, 45.0, 55.0, 90.0)


@dataclass(frozen=True)
class FlightSpec:
    """One evaluation flight: what independent_flight.py draws and which map it uses."""

    name: str
    frames: int
    width: int
    height: int
    options: FlightOptions
    two_faces: bool = False
    note: str = ""


def _lens(k1: float, k2: float, p1: float, p2: float) -> tuple[float, ...]:
    return (k1, k2, p1, p2)


DEFAULT_SET = (
    FlightSpec(
        "lens", 240, 1280, 720,
        FlightOptions(seed=11, dist=_lens(-0.25, 0.07, 0.0004, -0.0002), pan_deg=20.0,
                      speed_mps=1.55, wobble_seed=11),
        note="climb-hover-depart, lens k1 -0.25, pan 20 deg",
    ),
    FlightSpec(
        "lens_jpeg_vib", 240, 1280, 720,
        FlightOptions(seed=12, dist=_lens(-0.30, 0.10, 0.0005, -0.0003), jpeg=(70, 90),
                      vibration_deg=0.3, pan_deg=22.0, trajectory="orbit", speed_mps=4.0,
                      wobble_seed=12),
        note="orbit 4 m/s, k1 -0.30, JPEG 70-90, vibration 0.3 deg, pan 22 deg",
    ),
    FlightSpec(
        "two_faces", 240, 1280, 720,
        FlightOptions(seed=13, dist=_lens(-0.33, 0.12, -0.0004, 0.0003), jpeg=(70, 90),
                      pan_deg=15.0, trajectory="orbit", speed_mps=4.0, wobble_seed=13),
        two_faces=True,
        note="two pylon faces (12 signs), orbit, k1 -0.33, JPEG, pan 15 deg",
    ),
    FlightSpec(
        "members", 240, 1280, 720,
        FlightOptions(seed=14, dist=_lens(-0.28, 0.08, 0.0003, 0.0004), jpeg=(70, 90),
                      vibration_deg=0.2, pan_deg=15.0, member_share=0.7,
                      trajectory="lawnmower", speed_mps=3.0, distance_m=20.0, wobble_seed=14),
        note="lawnmower at 20 m, members across 70 % of signs, k1 -0.28, JPEG, vibration 0.2",
    ),
    FlightSpec(
        "hd_lens_jpeg_vib", 150, 1920, 1080,
        FlightOptions(seed=15, dist=_lens(-0.35, 0.13, 0.0005, -0.0005), jpeg=(70, 90),
                      vibration_deg=0.3, pan_deg=22.0, speed_mps=1.55, wobble_seed=15),
        note="1920x1080 climb-hover-depart, k1 -0.35, JPEG, vibration 0.3, pan 22 deg",
    ),
)  # fmt: skip
# Wide-angle lenses: two fisheyes (the equidistant model of Kalibr's and ROS's
# files, coefficients of the magnitudes real calibrations write) and a cheap action
# camera (plumb_bob with k3 and decentring p1, p2): not in the default set (the
# fisheyes' canvases are 2-3x the image's), run with --wide or by name.
WIDE_SET = (
    FlightSpec(
        "fisheye", 240, 1280, 720,
        FlightOptions(seed=21, dist=(-0.012, 0.021, -0.019, 0.0072), lens="equidistant",
                      hfov_deg=120.0, jpeg=(70, 90), vibration_deg=0.2, pan_deg=50.0,
                      trajectory="lawnmower", speed_mps=2.0, distance_m=7.0, wobble_seed=21),
        note="equidistant lens, 120 deg across, lawnmower at 7 m, JPEG, vibration 0.2, pan 50 deg",
    ),
    FlightSpec(
        "hd_fisheye_orbit", 150, 1920, 1080,
        FlightOptions(seed=22, dist=(0.028, -0.011, 0.002, -0.0003), lens="equidistant",
                      hfov_deg=125.0, jpeg=(70, 90), vibration_deg=0.3, pan_deg=55.0,
                      trajectory="orbit", speed_mps=3.0, distance_m=8.0, wobble_seed=22),
        note="1920x1080 equidistant lens, 125 deg across, orbit 3 m/s at 8 m, JPEG, pan 55 deg",
    ),
    FlightSpec(
        "action_cam", 240, 1280, 720,
        FlightOptions(seed=23, dist=(-0.28, 0.085, 0.0012, -0.0009, -0.011), hfov_deg=100.0,
                      jpeg=(60, 85), vibration_deg=0.4, pan_deg=22.0, speed_mps=1.55,
                      distance_m=9.0, wobble_seed=23),
        note="cheap action camera: plumb_bob k1 -0.28 k2 0.085 k3 -0.011, p1 0.0012 p2 -0.0009, "
        "100 deg across, climb-hover-depart at 9 m, JPEG 60-85, vibration 0.4, pan 22",
    ),
)  # fmt: skip
ALL_SETS = DEFAULT_SET + WIDE_SET
QUICK_SET = (replace(DEFAULT_SET[1], frames=60), replace(DEFAULT_SET[2], frames=60))
# What --without takes off every flight (to see which condition a defect needs).
ABLATIONS = {
    "lens": {"dist": (), "lens": "plumb_bob"},
    "jpeg": {"jpeg": None},
    "vibration": {"vibration_deg": 0.0},
    "pan": {"pan_deg": 0.0},
    "members": {"member_share": 0.0},
}


def without(spec: FlightSpec, names: list[str]) -> FlightSpec:
    """``spec`` with the conditions ``names`` taken off (its name says which)."""
    if not names:
        return spec
    changes = {k: v for n in names for k, v in ABLATIONS[n].items()}
    name = spec.name + "".join(f"-no_{n}" for n in names)
    note = f"{spec.note} (without: {', '.join(names)})"
    return replace(spec, name=name, note=note, options=replace(spec.options, **changes))


# --------------------------------------------------------------------------- flights


def two_face_map() -> SignMap:
    """The bundled map's six upper signs on the face y = 0 and six more on a second
    face x = 2.6 of the same pylon (normal +x), some hung rotated."""
    bundled = load_map(bundled_map_path())
    face_a = bundled.signs[:6]
    codes_b = ("1001", "1010", "1100", "1110", "0011", "0111")
    places_b = ((-0.6, 17.6), (-2.4, 17.0), (-1.2, 14.8), (-3.0, 14.2), (-0.8, 12.0), (-2.6, 11.6))
    ups = ((0, 0, 1), (0, 0.5, 0.866025), (0, 0, 1), (0, -1, 0), (0, 0, 1), (0, 0.258819, 0.965926))
    face_b = tuple(
        MapSign(code, np.array([2.6, y, z]), np.array([1.0, 0, 0]), np.array(up, float), 0.8, 0.01)
        for code, (y, z), up in zip(codes_b, places_b, ups, strict=True)
    )
    return SignMap("two_faces", face_a + face_b)


def draw_argv(spec: FlightSpec, out: Path, map_path: Path) -> list[str]:
    """independent_flight.py's arguments for ``spec``."""
    o = spec.options
    argv = [str(out), "--frames", str(spec.frames), "--width", str(spec.width)]
    argv += ["--height", str(spec.height), "--seed", str(o.seed), "--truth"]
    argv += ["--map", str(map_path), "--trajectory", o.trajectory]
    argv += ["--members", str(o.member_share), "--wobble-seed", str(o.wobble_seed)]
    argv += ["--distance", str(o.distance_m)]
    if o.dist:
        argv += ["--distortion", *(str(v) for v in o.dist)]
    if o.lens != "plumb_bob":
        argv += ["--lens", o.lens]
    if o.hfov_deg is not None:
        argv += ["--hfov", str(o.hfov_deg)]
    if o.jpeg:
        argv += ["--jpeg", str(o.jpeg[0]), str(o.jpeg[1])]
    if o.vibration_deg:
        argv += ["--vibration", str(o.vibration_deg)]
    if o.pan_deg:
        argv += ["--pan", str(o.pan_deg)]
    if o.speed_mps is not None:
        argv += ["--speed", str(o.speed_mps)]
    return argv


def run_argv(flight: Path, given_map: Path, out: Path) -> list[str]:
    """``signpose run``'s arguments for a drawn flight."""
    return [
        "run", str(flight / "video.mp4"), "--map", str(given_map),
        "--camera", str(flight / "camera.yaml"), "--out", str(out),
        "--gt", str(flight / "groundtruth.tum"), "--workers", "1", "-q",
    ]  # fmt: skip


def _stamped(path: Path, key: list[str]) -> bool:
    return path.is_file() and json.loads(path.read_text()) == key


def prepare(spec: FlightSpec, work: Path, rerun: bool) -> tuple[Path, list[str], list[str]]:
    """Draw the flight (unless drawn with these arguments) and write its surveyed map.

    Returns (flight folder, drawing argv, ``signpose run`` argv).
    """
    d = ensure_dir(work / spec.name)
    flight = d / "flight"
    true_map = d / "map_true.yaml"
    write_map(true_map, two_face_map() if spec.two_faces else load_map(bundled_map_path()))
    argv = draw_argv(spec, flight, true_map)
    if rerun or not _stamped(d / "drawn.json", argv):
        draw_flight(argv)
        with atomic_write(d / "drawn.json") as f:
            json.dump(argv, f)
    given = d / "map_surveyed.yaml"
    surveyed_map(true_map, given, spec.options.seed)
    return flight, argv, run_argv(flight, given, d / "out")


@functools.cache
def code_digest() -> str:
    """sha256 of signpose's own source files: a cached run made by other code is run again."""
    root = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    for sub in ("signpose", "frontend", "estimator", "maps"):
        for path in sorted((root / sub).rglob("*")):
            if path.suffix in (".py", ".yaml", ".xml", ".json") and path.is_file():
                digest.update(str(path.relative_to(root)).encode())
                digest.update(path.read_bytes())
    return digest.hexdigest()


def run_signpose(argv: list[str], stamp: Path, rerun: bool) -> dict:
    """Run ``signpose`` unless it finished with these arguments and this code: exit, stderr."""
    key = [*argv, f"code:{code_digest()}"]
    if not rerun and _stamped(stamp, key) and stamp.with_suffix(".log").is_file():
        return json.loads(stamp.with_suffix(".log").read_text())
    exe = Path(sys.executable).with_name("signpose")
    proc = subprocess.run([str(exe), *argv], capture_output=True, text=True)
    result = {"exit": proc.returncode, "stderr": proc.stderr, "stdout": proc.stdout}
    with atomic_write(stamp.with_suffix(".log")) as f:
        json.dump(result, f)
    with atomic_write(stamp) as f:
        json.dump(key, f)
    return result


# --------------------------------------------------------------------------- reading


def read_jsonl(path: Path) -> list[dict]:
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def read_gt(path: Path) -> np.ndarray:
    """(N, 8) rows of the TUM ground truth (t x y z qx qy qz qw)."""
    return np.loadtxt(path, comments="#", ndmin=2)


# --------------------------------------------------------------------------- metrics


def _inside(uv, bbox) -> bool:
    x, y, w, h = bbox
    return x <= uv[0] <= x + w and y <= uv[1] <= y + h


@dataclass
class CodeCheck:
    """Observed codes and keypoints against the drawn signs.

    Attributes:
        observed: observations read.
        wrong: (frame, code, box width [px], what it was) of each observation
            whose code has no drawn sign with its centre in its box; ``what``
            names the drawn sign whose centre is there ("misread 0101"), "false",
            or "box off its sign" (its centre keypoint on the drawn sign of its
            code, its box beside it: a right code with a wrong box; its
            keypoints are graded).
        visible: drawn signs >= MIN_RECALL_PX, whole in the image, seen at most
            MAX_RECALL_INCIDENCE_DEG off their normal (when the truth says).
        oblique: drawn signs >= MIN_RECALL_PX, whole in the image, seen further
            off their normal (not counted in the recall).
        visible_unhidden: those of them no occluder touches.
        visible_hidden: the share of the disc hidden of each visible sign.
        missed: (frame, code, diameter [px], hidden share, off-axis angle [deg]) of
            those not observed.
        visible_off_axis: the off-axis angle [deg] of each visible sign (the angle
            between the camera's axis and the ray to its centre; 0 unless the
            truth says).
        keypoints: kind ("center", "direction", "slot") -> rows of (error / its
            sigma u, v, error u, v [px], hidden share of the sign, error along
            the radius from the image centre [px], that radius over the half
            diagonal, the sign's off-axis angle [deg]) of the right codes'
            keypoints, raw pixels.
    """

    observed: int = 0
    wrong: list[tuple] = field(default_factory=list)
    visible: int = 0
    visible_unhidden: int = 0
    visible_hidden: list[float] = field(default_factory=list)
    visible_off_axis: list[float] = field(default_factory=list)
    oblique: int = 0
    missed: list[tuple] = field(default_factory=list)
    keypoints: dict[str, list] = field(default_factory=dict)


def _kind(name: str) -> str:
    return "slot" if name.startswith("slot") else name


def _keypoint_rows(o: dict, t: dict, size: tuple[int, int], check: CodeCheck) -> None:
    centre = (np.asarray(size, float) - 1) / 2
    half_diagonal = float(np.hypot(*centre))
    sigmas = o.get("keypoint_sigma_px", {})
    for name, uv in o["keypoints_px"].items():
        true = t.get("keypoints_px", {}).get(name, t["center_px"] if name == "center" else None)
        if true is None:
            continue
        err = np.asarray(uv, float) - true
        sigma = np.asarray(sigmas.get(name, [o["sigma_px"]] * 2), float)
        r = np.asarray(true, float) - centre
        r_len = float(np.hypot(*r))
        radial = float(err @ r / r_len) if r_len > 0 else 0.0
        row = (*(err / sigma), *err, t.get("hidden", 0.0), radial, r_len / half_diagonal)
        row = (*row, t.get("off_axis_deg", 0.0))
        check.keypoints.setdefault(_kind(name), []).append(row)


def _on_sign(o: dict, t: dict) -> bool:
    """The observation's centre keypoint lies on the drawn sign ``t`` (within a quarter
    of its diameter of the true centre)."""
    d = np.subtract(o["keypoints_px"]["center"], t["center_px"])
    return bool(np.hypot(*d) <= 0.25 * t["diameter_px"])


def check_frame(obs: dict, truth: dict, check: CodeCheck) -> None:
    """Grade one observations.jsonl line against its drawn signs (``truth.jsonl`` line)."""
    drawn = {s["code"]: s for s in truth["signs"]}
    seen = set()
    for o in obs["signs"]:
        check.observed += 1
        t = drawn.get(o["code"])
        if t is None or not _inside(t["center_px"], o["bbox_px"]):
            there = [s["code"] for s in truth["signs"] if _inside(s["center_px"], o["bbox_px"])]
            what = f"misread {there[0]}" if there else "false"
            if t is not None and _on_sign(o, t):
                what = "box off its sign"  # the right sign's keypoints, a box beside it
            check.wrong.append((obs["frame"], o["code"], round(float(o["bbox_px"][2]), 1), what))
            if t is None or not _on_sign(o, t):
                continue
        seen.add(o["code"])
        _keypoint_rows(o, t, tuple(obs["image_size"]), check)
    for t in truth["signs"]:
        if t.get("incidence_deg", 0.0) > MAX_RECALL_INCIDENCE_DEG:
            check.oblique += t["inside"] and t["diameter_px"] >= MIN_RECALL_PX
        elif t["inside"] and t["diameter_px"] >= MIN_RECALL_PX:
            check.visible += 1
            check.visible_unhidden += t["hidden"] == 0.0
            check.visible_hidden.append(t["hidden"])
            check.visible_off_axis.append(t.get("off_axis_deg", 0.0))
            if t["code"] not in seen:
                check.missed.append(
                    (
                        obs["frame"],
                        t["code"],
                        t["diameter_px"],
                        t["hidden"],
                        t.get("off_axis_deg", 0.0),
                    )
                )


def with_incidence(truth: list[dict], sign_map: SignMap, gt: np.ndarray) -> list[dict]:
    """``truth`` with each sign's ``incidence_deg``: the angle between its normal and the
    line from its centre to the camera, and ``off_axis_deg``: the angle between the
    camera's axis and that line (frames by index into the ground truth)."""
    signs = {s.code: s for s in sign_map.signs}
    out = []
    for t in truth:
        centre = gt[t["frame"], 1:4]
        axis = rotation_from_quat_xyzw(gt[t["frame"], 4:8])[0][:, 2]
        seen = []
        for s in t["signs"]:
            sign = signs[s["code"]]
            ray = centre - sign.center_m
            cos = float(ray @ sign.normal / np.linalg.norm(ray))
            cos_axis = float(-ray @ axis / np.linalg.norm(ray))
            seen.append(
                s
                | {
                    "incidence_deg": math.degrees(math.acos(min(max(cos, -1), 1))),
                    "off_axis_deg": math.degrees(math.acos(min(max(cos_axis, -1), 1))),
                }
            )
        out.append(t | {"signs": seen})
    return out


def check_codes(observations: list[dict], truth: list[dict]) -> CodeCheck:
    """Every frame's observations graded against ``truth.jsonl`` (frames by index)."""
    by_frame = {t["frame"]: t for t in truth}
    check = CodeCheck()
    for obs in observations:
        t = by_frame.get(obs["frame"])
        if t is None:
            raise ValueError(f"observations name frame {obs['frame']}, the truth has none")
        check_frame(obs, t, check)
    return check


def keypoint_summary(check: CodeCheck) -> dict[str, dict]:
    """Per keypoint kind: rms(error / sigma) u v (all, unhidden signs), rms error [px],
    share beyond 3 sigma, and the mean error along the radius [px] of the keypoints
    in the outer half of the image (a lens model's bias shows there)."""
    out = {}
    for kind, rows in sorted(check.keypoints.items()):
        a = np.asarray(rows, float).reshape(-1, 8)
        z, e, clear, outer = a[:, :2], a[:, 2:4], a[:, 4] == 0.0, a[:, 6] > 0.5
        by_angle = {}
        for lo, hi in zip(OFF_AXIS_BINS_DEG, OFF_AXIS_BINS_DEG[1:], strict=False):
            sel = clear & (a[:, 7] > lo) & (a[:, 7] <= hi) if hi < 90 else clear & (a[:, 7] > lo)
            rms = np.sqrt(np.mean(z[sel] ** 2, axis=0)).round(3).tolist() if sel.any() else None
            by_angle[f"{lo:g}-{hi:g}deg"] = [int(sel.sum()), rms]
        out[kind] = {
            "n": len(a),
            "rms_z_uv": np.sqrt(np.mean(z**2, axis=0)).round(3).tolist(),
            "rms_z_uv_unhidden": (
                np.sqrt(np.mean(z[clear] ** 2, axis=0)).round(3).tolist() if clear.any() else None
            ),
            "rms_err_px_uv": np.sqrt(np.mean(e**2, axis=0)).round(4).tolist(),
            "beyond_3sigma": round(float((np.abs(z) > 3).any(axis=1).mean()), 4),
            "n_outer": int(outer.sum()),
            "radial_bias_outer_px": round(float(a[outer, 5].mean()), 4) if outer.any() else None,
            "rms_z_uv_unhidden_by_off_axis": by_angle,
        }
    return out


def _recall(hidden: list[float], missed: list[tuple], lo: float, hi: float) -> list:
    """[visible, found, recall] of the signs whose hidden share h has lo < h <= hi."""
    n = sum(lo < h <= hi for h in hidden)
    found = n - sum(lo < m[3] <= hi for m in missed)
    return [n, found, round(found / n, 3) if n else None]


def _recall_off_axis(check: CodeCheck) -> dict[str, list]:
    """[visible, found, recall] of the unhidden signs per off-axis bin."""
    out = {}
    for lo, hi in zip(OFF_AXIS_BINS_DEG, OFF_AXIS_BINS_DEG[1:], strict=False):
        n = sum(
            h == 0.0 and lo < a <= hi
            for h, a in zip(check.visible_hidden, check.visible_off_axis, strict=True)
        )
        found = n - sum(m[3] == 0.0 and lo < m[4] <= hi for m in check.missed)
        out[f"{lo:g}-{hi:g}deg"] = [n, found, round(found / n, 3) if n else None]
    return out


def code_summary(check: CodeCheck) -> dict:
    missed_clear = [m for m in check.missed if m[3] == 0.0]
    bins = {}
    for lo, hi in zip(SIZE_BINS_PX, SIZE_BINS_PX[1:], strict=False):
        n_miss = sum(lo <= m[2] < hi for m in check.missed)
        bins[f"{lo:g}-{hi:g}px"] = n_miss
    box_off = sum(w[3] == "box off its sign" for w in check.wrong)
    return {
        "observed": check.observed,
        "wrong": len(check.wrong),
        "box_off_its_sign": box_off,
        "wrong_codes": len(check.wrong) - box_off,
        "wrong_list": check.wrong,
        "visible": check.visible,
        "missed": len(check.missed),
        "missed_unhidden": len(missed_clear),
        "recall": round(1 - len(check.missed) / check.visible, 4) if check.visible else None,
        "missed_by_size": bins,
        "recall_by_hidden": {
            name: _recall(check.visible_hidden, check.missed, lo, hi)
            for name, lo, hi in HIDDEN_BINS
        },
        "visible_unhidden": check.visible_unhidden,
        "recall_unhidden_by_off_axis": _recall_off_axis(check),
        "oblique": check.oblique,
    }


def pose_metrics(trajectory_csv: Path, gt: np.ndarray, n_frames: int) -> dict[str, dict]:
    """Per method: RMSE / max error [m], status shares of all frames, sigma honesty.

    Rows match the ground truth by frame index; their ``t_s`` must be the truth's.
    """
    return {
        m: _method_metrics(rs, gt, n_frames) for m, rs in _rows_by_method(trajectory_csv).items()
    }


def _method_metrics(rows: list[dict], gt: np.ndarray, n_frames: int) -> dict:
    errs, z, ok, clock, ok_err = [], [], [], 0.0, []
    status = dict.fromkeys(STATUSES, 0)
    for r in rows:
        status[r["status"]] = status.get(r["status"], 0) + 1
        if r["x_m"] == "":
            continue
        g = gt[int(r["frame"])]
        clock = max(clock, abs(float(r["t_s"]) - g[0]))
        e = np.array([float(r[f"{a}_m"]) for a in AXES]) - g[1:4]
        errs.append(e)
        if r["status"] == "ok":
            ok_err.append(float(np.linalg.norm(e)))
        if r["sigma_x_m"] != "":
            z.append(e / np.array([float(r[f"sigma_{a}_m"]) for a in AXES]))
            ok.append(r["status"] == "ok")
    e = np.asarray(errs, float).reshape(-1, 3)
    norm = np.linalg.norm(e, axis=1)
    zz, okk = np.asarray(z, float).reshape(-1, 3), np.asarray(ok, bool)
    bad = okk & (np.abs(zz) > 3).any(axis=1)
    return {
        "posed": len(e),
        "coverage": round(len(e) / n_frames, 4),
        "rmse_m": round(float(np.sqrt(np.mean(norm**2))), 4) if len(e) else None,
        "max_m": round(float(norm.max()), 4) if len(e) else None,
        "status": {k: round(v / n_frames, 4) for k, v in status.items()},
        "with_sigma": len(zz),
        "rms_z_xyz": np.sqrt(np.mean(zz**2, axis=0)).round(3).tolist() if len(zz) else None,
        "ok": int(okk.sum()),
        "ok_beyond_3sigma": int(bad.sum()),
        "ok_max_m": round(max(ok_err), 4) if ok_err else None,
        "ok_worst_z": round(float(np.abs(zz[okk]).max()), 2) if okk.any() else None,
        "clock_diff_s": clock,
    }


def estimate_argv(flight: Path, observations: Path, given_map: Path, out: Path) -> list[str]:
    """``signpose estimate``'s arguments: the same observations against another map."""
    return [
        "estimate", str(observations), "--map", str(given_map),
        "--camera", str(flight / "camera.yaml"), "--out", str(out), "--method", "all", "-q",
    ]  # fmt: skip


def survey_draws(
    spec: FlightSpec, work: Path, draws: int, rerun: bool, observations: str = "out"
) -> dict:
    """The flight's observations estimated against ``draws`` more survey draws of its map
    (``observations``: "out", the frontend's, or "oracle", ``oracle_observations``).

    All frames of one flight share its map's error, so one draw says little about
    whether the sigmas carry the survey's share; pooled over draws it does.
    Returns method -> {"z": (N, 3) error / sigma, "ok": (N,) status ok, "mean_err_m": per draw}.
    """
    d = work / spec.name
    flight, gt = d / "flight", read_gt(d / "flight" / "groundtruth.tum")
    pooled: dict[str, dict[str, list]] = {}
    for j in range(draws):
        given = d / f"map_survey_{j}.yaml"
        surveyed_map(d / "map_true.yaml", given, 1000 * spec.options.seed + j)
        tag = "" if observations == "out" else f"{observations}_"
        out = d / f"survey_{tag}{j}"
        source = {"out": d / "out" / "observations.jsonl", "oracle": d / ORACLE_NAME}
        argv = estimate_argv(flight, source[observations], given, out)
        ran = run_signpose(argv, d / f"survey_{tag}{j}.json", rerun)
        if ran["exit"] != 0:
            raise SystemExit(f"signpose {' '.join(argv)} exited {ran['exit']}: {ran['stderr']}")
        for method, rows in _rows_by_method(out / "trajectory.csv").items():
            z, ok, e = _normalised(rows, gt)
            p = pooled.setdefault(method, {"z": [], "ok": [], "mean_err_m": []})
            p["z"].append(z)
            p["ok"].append(ok)
            p["mean_err_m"].append(np.round(e.mean(axis=0), 4).tolist() if len(e) else None)
    return {
        m: {
            "z": np.concatenate(v["z"]),
            "ok": np.concatenate(v["ok"]),
            "mean_err_m": v["mean_err_m"],
        }
        for m, v in pooled.items()
    }


def _rows_by_method(trajectory_csv: Path) -> dict[str, list[dict]]:
    rows: dict[str, list[dict]] = {}
    with open(trajectory_csv, newline="") as f:
        for r in csv.DictReader(f):
            rows.setdefault(r["method"], []).append(r)
    return rows


def _normalised(rows: list[dict], gt: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """((N, 3) error / sigma, (N,) ok, (M, 3) errors [m] of every posed row)."""
    z, ok, errs = [], [], []
    for r in rows:
        if r["x_m"] == "":
            continue
        e = np.array([float(r[f"{a}_m"]) for a in AXES]) - gt[int(r["frame"]), 1:4]
        errs.append(e)
        if r["sigma_x_m"] != "":
            z.append(e / np.array([float(r[f"sigma_{a}_m"]) for a in AXES]))
            ok.append(r["status"] == "ok")
    return (
        np.asarray(z, float).reshape(-1, 3),
        np.asarray(ok, bool),
        np.asarray(errs, float).reshape(-1, 3),
    )


def survey_summary(pooled: dict) -> dict:
    out = {}
    for m, v in pooled.items():
        z, ok = v["z"], v["ok"]
        bad = ok & (np.abs(z) > 3).any(axis=1) if len(z) else ok
        out[m] = {
            "n": len(z),
            "rms_z_xyz": np.sqrt(np.mean(z**2, axis=0)).round(3).tolist() if len(z) else None,
            "ok": int(ok.sum()),
            "ok_beyond_3sigma": int(bad.sum()),
            "mean_err_m_per_draw": v["mean_err_m"],
        }
    return out


def oracle_observations(observations: list[dict], truth: list[dict]) -> list[dict]:
    """The frontend's observations with every keypoint of a right code moved to its true
    raw pixel (same signs, keypoints and sigmas; wrong codes dropped): what the estimator
    makes of the flight when the frontend's only error is its choice of what it saw."""
    by_frame = {t["frame"]: {s["code"]: s for s in t["signs"]} for t in truth}
    out = []
    for obs in observations:
        drawn, signs = by_frame[obs["frame"]], []
        for o in obs["signs"]:
            t = drawn.get(o["code"])
            if t is None or not _on_sign(o, t):
                continue
            kp = {k: t["keypoints_px"][k] for k in o["keypoints_px"] if k in t["keypoints_px"]}
            signs.append(o | {"keypoints_px": kp})
        out.append(obs | {"signs": signs})
    return out


def oracle(flight: Path, d: Path, rerun: bool) -> dict:
    """The flight estimated from ``oracle_observations`` against the same surveyed map."""
    path = d / ORACLE_NAME
    frames = oracle_observations(
        read_jsonl(d / "out" / "observations.jsonl"), read_jsonl(flight / "truth.jsonl")
    )
    with atomic_write(path) as f:
        f.writelines(json.dumps(o) + "\n" for o in frames)
    argv = estimate_argv(flight, path, d / "map_surveyed.yaml", d / "oracle")
    ran = run_signpose(argv, d / "oracle.json", rerun)
    if ran["exit"] != 0:
        return {"exit": ran["exit"], "stderr": ran["stderr"].strip(), "command": argv}
    gt = read_gt(flight / "groundtruth.tum")
    return {
        "command": "nice -n 5 .venv/bin/signpose " + " ".join(argv),
        "methods": pose_metrics(d / "oracle" / "trajectory.csv", gt, len(frames)),
    }


def without_lens(flight: Path, d: Path, rerun: bool) -> dict | None:
    """The flight's observations estimated with camera.yaml's distortion dropped (a user's
    wrong calibration): does signpose notice, or label wrong poses ``ok``?"""
    camera = load_camera(flight / "camera.yaml")
    if not camera.has_distortion:
        return None
    pinhole = d / "camera_without_lens.yaml"
    write_camera_info(pinhole, replace(camera, dist=np.zeros_like(camera.dist)))
    out = d / "without_lens"
    argv = estimate_argv(flight, d / "out" / "observations.jsonl", d / "map_surveyed.yaml", out)
    argv[argv.index("--camera") + 1] = str(pinhole)
    ran = run_signpose(argv, d / "without_lens.json", rerun)
    if ran["exit"] != 0:
        return {"exit": ran["exit"], "stderr": ran["stderr"].strip(), "command": argv}
    report = json.loads((out / "report.json").read_text())
    n = len(read_jsonl(d / "out" / "observations.jsonl"))
    return {
        "command": "nice -n 5 .venv/bin/signpose " + " ".join(argv),
        "pixel_noise_scale": report.get("pixel_noise_scale"),
        "methods": pose_metrics(out / "trajectory.csv", read_gt(flight / "groundtruth.tum"), n),
    }


def missed_reasons(flight: Path, truth: list[dict], check: CodeCheck, codes) -> dict[str, int]:
    """Each unhidden sign the run missed, decoded alone on its true box: "decoded on its
    true box" (the detector or the tracker lost it) or the decoder's reason to refuse it."""
    want: dict[int, list[str]] = {}
    for frame, code, _, hidden, _ in check.missed:
        if hidden == 0.0:
            want.setdefault(frame, []).append(code)
    reasons: dict[str, int] = {}
    cap = cv2.VideoCapture(str(flight / "video.mp4"))
    try:
        for i, t in enumerate(truth):
            ok, image = cap.read()
            if not ok:
                break
            if i not in want:
                continue
            gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
            boxes = {s["code"]: s["box_px"] for s in t["signs"]}
            for code in want[i]:
                x0, y0, x1, y1 = boxes[code]
                r = decode_region(gray, (x0, y0, x1 - x0, y1 - y0), codes)
                key = (
                    "decoded on its true box"
                    if r.code == code
                    else (f"refused: {r.reason}" if r.code is None else f"read {r.code}")
                )
                reasons[key] = reasons.get(key, 0) + 1
    finally:
        cap.release()
    return reasons


# --------------------------------------------------------------------------- survey response

# Each sign centre is moved by this along each world axis to measure the smoothed
# positions' response to it [m]; the solve is linear in the survey at this scale
# (two_faces: the response predicts the smoothed error on the surveyed map within 0.2 mm).
RESPONSE_STEP_M = 0.01
# Survey draws simulated through the measured response.
RESPONSE_DRAWS = 100_000
# The flight's ok poses beyond 3 sigma with its sigmas times these: how close to the
# threshold its errors sit (one survey draw moves them all together).
SIGMA_FACTORS = (0.95, 0.97, 1.0, 1.03, 1.05)


def _smoothed_rows(trajectory_csv: Path) -> dict[int, dict]:
    """frame -> the smoothed row of a trajectory.csv, for the rows with a position."""
    rows = _rows_by_method(trajectory_csv).get("smoothed", [])
    return {int(r["frame"]): r for r in rows if r["x_m"] != ""}


def _positions(rows: dict[int, dict], frames: list[int]) -> np.ndarray:
    return np.array([[float(rows[i][f"{a}_m"]) for a in AXES] for i in frames]).reshape(-1, 3)


def _moved_map(src: Path, dst: Path, k: int, axis: int) -> None:
    m = load_map(src)
    signs = list(m.signs)
    centre = np.asarray(signs[k].center_m, float).copy()
    centre[axis] += RESPONSE_STEP_M
    signs[k] = replace(signs[k], center_m=centre)
    write_map(dst, replace(m, signs=tuple(signs)))


def simulated_draws(
    noise_m: np.ndarray,
    J: np.ndarray,
    sigma_xyz_m: np.ndarray,
    ok: np.ndarray,
    sigma_m: np.ndarray,
    draws: int,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Survey draws through a flight's linear response, graded like the flight.

    Args:
        noise_m: (N, 3) the positions' error on the exact map (the keypoints' share) [m].
        J: (N, 3, P) the positions' response to the P survey coordinates [m / m].
        sigma_xyz_m: (N, 3) the claimed sigmas [m]; ok: (N,) the ``ok`` statuses.
        sigma_m: (P,) each survey coordinate's sigma [m].

    Returns:
        ((draws,) ``ok`` poses beyond 3 sigma on some axis, (draws,) worst axis's
        rms(e/sigma), (3,) rms(e/sigma) pooled over draws and poses).
    """
    bad, rms_max, sq = [], [], np.zeros(3)
    for chunk in np.array_split(rng.normal(size=(draws, len(sigma_m))) * sigma_m, 100):
        z = (noise_m[None] + np.einsum("nij,kj->kni", J, chunk)) / sigma_xyz_m[None]
        bad.append((ok[None] & (np.abs(z) > 3).any(axis=2)).sum(axis=1))
        rms_max.append(np.sqrt(np.mean(z**2, axis=1)).max(axis=1))
        sq += np.sum(z**2, axis=(0, 1))
    pooled = np.sqrt(sq / (draws * len(noise_m)))
    return np.concatenate(bad), np.concatenate(rms_max), pooled


def survey_response(spec: FlightSpec, work: Path, rerun: bool) -> dict:
    """How much of the smoothed poses' error and sigma the survey's draw explains.

    The oracle's observations (true keypoints) estimated against the true map, then
    against it with each sign centre moved by ``RESPONSE_STEP_M`` along each axis: the
    smoothed positions' linear response ``J`` (N, 3, 3K) to the K centres. From it:
    the survey's share of each pose's sd, ``sqrt(diag(J Sigma_m J^T))`` (Sigma_m: each
    centre N(0, sigma_m^2 I), as ``surveyed_map`` draws), against the smoothed sigma;
    the error the flight's own draw predicts against the oracle's on it; and
    ``RESPONSE_DRAWS`` survey draws simulated as the flight's observations' error on the
    true map plus ``J delta``, graded like the flight (its sigmas and ``ok`` statuses):
    the chance of a draw as bad as the flight's. All frames of a flight share one
    draw, so one flight's count of ``ok`` poses beyond 3 sigma says little alone.
    """
    d = work / spec.name
    flight, gt = d / "flight", read_gt(d / "flight" / "groundtruth.tum")
    true_map, resp = d / "map_true.yaml", ensure_dir(d / "response")
    oracle_obs = d / ORACLE_NAME
    if not oracle_obs.is_file():
        frames = oracle_observations(
            read_jsonl(d / "out" / "observations.jsonl"), read_jsonl(flight / "truth.jsonl")
        )
        with atomic_write(oracle_obs) as f:
            f.writelines(json.dumps(o) + "\n" for o in frames)

    def smoothed(observations: Path, given: Path, name: str) -> dict[int, dict]:
        argv = estimate_argv(flight, observations, given, resp / name)
        argv[argv.index("all")] = "smoothed"
        ran = run_signpose(argv, resp / f"{name}.json", rerun)
        if ran["exit"] != 0:
            raise SystemExit(f"signpose {' '.join(argv)} exited {ran['exit']}: {ran['stderr']}")
        return _smoothed_rows(resp / name / "trajectory.csv")

    real = _smoothed_rows(d / "out" / "trajectory.csv")
    base = smoothed(oracle_obs, true_map, "oracle_true")
    noise_rows = smoothed(d / "out" / "observations.jsonl", true_map, "true")
    frames = sorted(i for i in real if real[i]["sigma_x_m"] != "" and i in base and i in noise_rows)
    p0 = _positions(base, frames)
    signs = load_map(true_map).signs
    J = np.zeros((len(frames), 3, 3 * len(signs)))
    for k in range(len(signs)):
        for axis in range(3):
            given = resp / f"map_{k}_{axis}.yaml"
            _moved_map(true_map, given, k, axis)
            p = _positions(smoothed(oracle_obs, given, f"moved_{k}_{axis}"), frames)
            J[:, :, 3 * k + axis] = (p - p0) / RESPONSE_STEP_M
    sigma_m = np.repeat([s.sigma_m for s in signs], 3)
    share = np.sqrt(np.einsum("nij,nij->ni", J * sigma_m, J * sigma_m))
    sigma = np.array([[float(real[i][f"sigma_{a}_m"]) for a in AXES] for i in frames])
    ok = np.array([real[i]["status"] == "ok" for i in frames])
    truth = gt[frames, 1:4]
    surveyed = {
        s.code: np.asarray(s.center_m, float) for s in load_map(d / "map_surveyed.yaml").signs
    }
    delta = np.concatenate([surveyed[s.code] - np.asarray(s.center_m, float) for s in signs])
    predicted = p0 - truth + J @ delta
    out: dict = {
        "frames": len(frames),
        "share_sd_m_median": np.median(share, axis=0).round(4).tolist(),
        "sigma_m_median": np.median(sigma, axis=0).round(4).tolist(),
        "sigma_over_share_min_median_max": [
            np.min(sigma / share, axis=0).round(3).tolist(),
            np.median(sigma / share, axis=0).round(3).tolist(),
            np.max(sigma / share, axis=0).round(3).tolist(),
        ],
        "draw_offsets_sigmas_max": round(float(np.max(np.abs(delta / sigma_m))), 2),
        "draw_predicted_mean_err_m": predicted.mean(axis=0).round(4).tolist(),
    }
    oracle_csv = d / "oracle" / "trajectory.csv"
    if oracle_csv.is_file():
        o = _smoothed_rows(oracle_csv)
        if all(i in o for i in frames):
            actual = _positions(o, frames) - truth
            out["draw_oracle_mean_err_m"] = actual.mean(axis=0).round(4).tolist()
            out["draw_predicted_vs_oracle_max_m"] = round(
                float(np.abs(actual - predicted).max()), 4
            )
    on_true = {
        name: _method_metrics(list(rows.values()), gt, spec.frames)
        for name, rows in (("frontend", noise_rows), ("oracle", base))
    }
    out["true_map"] = {
        name: {k: m[k] for k in ("rmse_m", "rms_z_xyz", "ok", "ok_beyond_3sigma")}
        for name, m in on_true.items()
    }
    z_real = (_positions(real, frames) - truth) / sigma
    out["flight_ok_beyond_3sigma_sigmas_times"] = {
        f: int((ok & (np.abs(z_real / f) > 3).any(axis=1)).sum()) for f in SIGMA_FACTORS
    }
    noise = _positions(noise_rows, frames) - truth
    z_flight = (noise + J @ delta) / sigma
    flight_bad = int((ok & (np.abs(z_flight) > 3).any(axis=1)).sum())
    rng = np.random.default_rng(spec.options.seed)
    bad, rms_max, pooled_rms = simulated_draws(noise, J, sigma, ok, sigma_m, RESPONSE_DRAWS, rng)
    rms_flight = float(np.sqrt(np.mean(z_flight**2, axis=0)).max())
    out |= {
        "ok": int(ok.sum()),
        "flight_ok_beyond_3sigma": flight_bad,
        "flight_rms_z_max_axis": round(rms_flight, 2),
        "draws": RESPONSE_DRAWS,
        "pooled_rms_z_xyz": pooled_rms.round(3).tolist(),
        "pooled_ok_beyond_3sigma_share": round(float(bad.sum() / (RESPONSE_DRAWS * ok.sum())), 5),
        "p_any_ok_beyond_3sigma": round(float(np.mean(bad >= 1)), 5),
        "p_as_many_ok_beyond_3sigma": round(float(np.mean(bad >= max(flight_bad, 1))), 6),
        "p_rms_z_max_axis_as_large": round(float(np.mean(rms_max >= rms_flight)), 6),
        "rms_z_max_axis_percentiles_50_90_99": np.percentile(rms_max, [50, 90, 99])
        .round(2)
        .tolist(),
    }
    return out


# --------------------------------------------------------------------------- one flight


def evaluate(
    spec: FlightSpec,
    work: Path,
    rerun: bool,
    draws: int = 0,
    lensless: bool = False,
    use_oracle: bool = False,
    why_missed: bool = False,
    response: bool = False,
) -> dict:
    """Draw, run and grade one flight (and estimate it against ``draws`` more surveys,
    with ``lensless`` without its lens model, with ``use_oracle`` from true keypoints,
    with ``response`` the survey's share of its smoothed poses: ``survey_response``)."""
    flight, draw, run = prepare(spec, work, rerun)
    d = work / spec.name
    out = d / "out"
    ran = run_signpose(run, work / spec.name / "ran.json", rerun)
    result = {
        "name": spec.name,
        "note": spec.note,
        "size": f"{spec.width}x{spec.height}",
        "frames": spec.frames,
        "commands": [
            "nice -n 5 .venv/bin/python scripts/independent_flight.py " + " ".join(draw),
            "nice -n 5 .venv/bin/signpose " + " ".join(run),
        ],
        "exit": ran["exit"],
        "stderr": ran["stderr"].strip(),
    }
    if ran["exit"] != 0 or not (out / "report.json").is_file():
        return result
    report = json.loads((out / "report.json").read_text())
    gt = read_gt(flight / "groundtruth.tum")
    truth = with_incidence(read_jsonl(flight / "truth.jsonl"), load_map(d / "map_true.yaml"), gt)
    check = check_codes(read_jsonl(out / "observations.jsonl"), truth)
    result |= {
        "pixel_noise_scale": report.get("pixel_noise_scale"),
        "intrinsics_check": report.get("intrinsics_check"),
        "report_status": {m: c.get("status") for m, c in report.get("coverage", {}).items()},
        "codes": code_summary(check),
        "keypoints": keypoint_summary(check),
        "methods": pose_metrics(out / "trajectory.csv", gt, spec.frames),
    }
    if why_missed:
        true_map = load_map(d / "map_true.yaml")
        result["missed_unhidden_why"] = missed_reasons(flight, truth, check, true_map.codes)
    if draws:
        result["surveys"] = survey_summary(survey_draws(spec, work, draws, rerun))
    if lensless:
        result["without_lens"] = without_lens(flight, d, rerun)
    if use_oracle:
        result["oracle"] = oracle(flight, d, rerun)
        if draws:
            pooled = survey_draws(spec, work, draws, rerun, "oracle")
            result["surveys_oracle"] = survey_summary(pooled)
    if response:
        result["survey_response"] = survey_response(spec, work, rerun)
    return result


# --------------------------------------------------------------------------- printing


def _fmt(v, spec: str = ".3f") -> str:
    return "-" if v is None else format(v, spec)


def _print_methods(methods: dict) -> None:
    print(
        f"  {'method':<9}{'RMSE m':>8}{'max m':>8}{'cover':>7}"
        + "".join(f"{s:>8}" for s in STATUSES)
        + f"  {'rms(e/sig) x y z':<20}ok beyond 3 sig (Gauss {100 * GAUSS_BEYOND_3:.1f}%)"
    )
    for m, r in methods.items():
        shares = "".join(f"{100 * r['status'].get(s, 0):7.1f}%" for s in STATUSES)
        rz = " ".join(f"{v:.2f}" for v in r["rms_z_xyz"]) if r["rms_z_xyz"] else "-"
        frac = f" ({100 * r['ok_beyond_3sigma'] / r['ok']:.1f}%)" if r["ok"] else ""
        print(
            f"  {m:<9}{_fmt(r['rmse_m']):>8}{_fmt(r['max_m']):>8}{100 * r['coverage']:6.1f}%"
            f"{shares}  {rz:<20}{r['ok_beyond_3sigma']} of {r['ok']}{frac}"
            f"  worst ok {_fmt(r['ok_worst_z'], '.1f')} sig, {_fmt(r['ok_max_m'])} m"
        )


def intrinsics_line(c: dict | None) -> str:
    """report.json's ``intrinsics_check`` in one line: the video's change of the camera
    file's focal length and principal point, in sigmas, and whether it was acted on."""
    if not c:
        return "intrinsics check: none (no smoother, or too little seen)"
    d, s = c["change_px"], c["sigma_px"]
    acted = [k for k in ("focal_off", "principal_off") if c.get(k)]
    return (
        f"intrinsics check: focal {100 * c['focal_rel']:+.2f} % (sigma "
        f"{100 * c['focal_rel_sigma']:.2f} %, {c['focal_rel'] / c['focal_rel_sigma']:+.1f} "
        f"sigma), principal point ({d['cx']:+.1f}, {d['cy']:+.1f}) px (sigma {s['cx']:.1f}, "
        f"{s['cy']:.1f}; {d['cx'] / s['cx']:+.1f}, {d['cy'] / s['cy']:+.1f} sigma); "
        + (f"ACTED ON: {', '.join(acted)}" if acted else "not acted on")
        + ("" if c.get("settled", True) else " (fit not settled)")
    )


def print_flight(r: dict) -> None:
    print(f"\n== {r['name']}: {r['note']}; {r['frames']} frames at {r['size']}")
    for c in r["commands"]:
        print(f"  $ {c}")
    if r["exit"] != 0 or "methods" not in r:
        print(f"  signpose run exited {r['exit']}: {r['stderr']}")
        return
    c, k = r["codes"], r["keypoints"]
    print(
        f"  pixel_noise_scale {r['pixel_noise_scale']}; observed {c['observed']}, no drawn sign "
        f"of the code in the box {c['wrong']} (wrong codes {c['wrong_codes']}, right sign with "
        f"the box beside it {c['box_off_its_sign']});\n  visible >= {MIN_RECALL_PX:g} px "
        f"{c['visible']} (at most {MAX_RECALL_INCIDENCE_DEG:g} deg off their normal; "
        f"{c['oblique']} more further off, not counted; unhidden "
        f"{c['visible_unhidden']}), missed {c['missed']}, recall {_fmt(c['recall'], '.1%')}; "
        f"missed by size {c['missed_by_size']};\n  recall by hidden share [visible, found, "
        f"recall] {c['recall_by_hidden']}\n  unhidden recall by off-axis angle [visible, found, "
        f"recall] {c.get('recall_unhidden_by_off_axis')}"
    )
    print(f"  {intrinsics_line(r.get('intrinsics_check'))}")
    for w in c["wrong_list"][:10]:
        print(f"    wrong: frame {w[0]} code {w[1]} box {w[2]} px: {w[3]}")
    for kind, v in k.items():
        print(
            f"  {kind:<9} keypoints: n {v['n']}, rms(e/sigma) u v {v['rms_z_uv']} (unhidden "
            f"{v['rms_z_uv_unhidden']}), rms error {v['rms_err_px_uv']} px, beyond 3 sigma "
            f"{100 * v['beyond_3sigma']:.1f}%, radial bias (outer half, n {v['n_outer']}) "
            f"{_fmt(v['radial_bias_outer_px'], '+.3f')} px"
        )
        print(
            f"    unhidden by off-axis angle [n, rms(e/sigma) u v] "
            f"{v.get('rms_z_uv_unhidden_by_off_axis')}"
        )
    _print_methods(r["methods"])
    if "missed_unhidden_why" in r:
        print(
            f"  unhidden signs missed, decoded alone on their true box: {r['missed_unhidden_why']}"
        )
    orc = r.get("oracle")
    if orc and "methods" in orc:
        print(
            f"  the frontend's observations with true keypoints (oracle):\n    $ {orc['command']}"
        )
        _print_methods(orc["methods"])
    wl = r.get("without_lens")
    if wl and "methods" in wl:
        print(f"  the same observations with camera.yaml's distortion dropped: pixel_noise_scale "
              f"{wl['pixel_noise_scale']:.3f}\n    $ {wl['command']}")  # fmt: skip
        _print_methods(wl["methods"])
    elif wl:
        print(f"  without the lens model: exited {wl['exit']}: {wl['stderr']}")
    if "survey_response" in r:
        _print_response(r["survey_response"])
    for key, m, v in [(k, m, v) for k in SURVEY_KEYS for m, v in r.get(k, {}).items()]:
        if v["n"]:
            print(
                f"  {m:<9}over {len(v['mean_err_m_per_draw'])} more survey draws"
                f"{' (oracle keypoints)' if key == 'surveys_oracle' else ''}: rms(e/sigma) "
                f"x y z {v['rms_z_xyz']}, ok beyond 3 sigma {v['ok_beyond_3sigma']} of "
                f"{v['ok']}; mean error per draw [m] {v['mean_err_m_per_draw']}"
            )


def _print_response(v: dict) -> None:
    lo, med, hi = v["sigma_over_share_min_median_max"]
    print(
        f"  smoothed, the survey's share (response to each centre, oracle keypoints, "
        f"{v['frames']} frames): sd x y z median {v['share_sd_m_median']} m, sigma median "
        f"{v['sigma_m_median']} m, sigma / share min {lo} median {med} max {hi};\n"
        f"    this draw (largest offset {v['draw_offsets_sigmas_max']} sigma_m): predicted "
        f"mean error {v['draw_predicted_mean_err_m']} m (oracle on it "
        f"{v.get('draw_oracle_mean_err_m', '-')}, max diff "
        f"{v.get('draw_predicted_vs_oracle_max_m', '-')} m); the flight through the response: "
        f"ok beyond 3 sigma {v['flight_ok_beyond_3sigma']} of {v['ok']}, rms(e/sigma) worst "
        f"axis {v['flight_rms_z_max_axis']};\n    over {v['draws']} simulated draws: pooled "
        f"rms(e/sigma) x y z {v['pooled_rms_z_xyz']}, ok beyond 3 sigma "
        f"{100 * v['pooled_ok_beyond_3sigma_share']:.2f}%; P(any ok beyond 3 sigma) "
        f"{v['p_any_ok_beyond_3sigma']}, P(as many as this draw) "
        f"{v['p_as_many_ok_beyond_3sigma']}, P(worst-axis rms(e/sigma) as large) "
        f"{v['p_rms_z_max_axis_as_large']}; per-draw worst-axis rms(e/sigma) 50/90/99 % "
        f"{v['rms_z_max_axis_percentiles_50_90_99']};\n    the flight's ok beyond 3 sigma "
        f"with its sigmas times {list(v['flight_ok_beyond_3sigma_sigmas_times'])}: "
        f"{list(v['flight_ok_beyond_3sigma_sigmas_times'].values())}; on the true map "
        f"(smoothed RMSE m, rms(e/sigma) x y z, ok beyond 3 sigma): "
        + "; ".join(
            f"{name} {m['rmse_m']}, {m['rms_z_xyz']}, {m['ok_beyond_3sigma']} of {m['ok']}"
            for name, m in v["true_map"].items()
        )
    )


def pooled(results: list[dict]) -> dict:
    """Sums over the flights that ran."""
    ran = [r for r in results if "methods" in r]
    out = {
        "flights": len(results),
        "failed": [r["name"] for r in results if "methods" not in r],
        "no_sign_in_box": sum(r["codes"]["wrong"] for r in ran),
        "wrong_codes": sum(r["codes"]["wrong_codes"] for r in ran),
        "box_off_its_sign": sum(r["codes"]["box_off_its_sign"] for r in ran),
        "observed": sum(r["codes"]["observed"] for r in ran),
        "visible": sum(r["codes"]["visible"] for r in ran),
        "missed": sum(r["codes"]["missed"] for r in ran),
        "missed_unhidden": sum(r["codes"]["missed_unhidden"] for r in ran),
        "visible_unhidden": sum(r["codes"]["visible_unhidden"] for r in ran),
        "noise_scales": [r["pixel_noise_scale"] for r in ran],
        "intrinsics_acted_on": [
            r["name"]
            for r in ran
            if any((r.get("intrinsics_check") or {}).get(k) for k in ("focal_off", "principal_off"))
        ],
        "recall_by_hidden": {},
        "missed_unhidden_why": {},
    }
    for r in ran:
        for k, v in r.get("missed_unhidden_why", {}).items():
            out["missed_unhidden_why"][k] = out["missed_unhidden_why"].get(k, 0) + v
    for name, _, _ in HIDDEN_BINS:
        n = sum(r["codes"]["recall_by_hidden"][name][0] for r in ran)
        found = sum(r["codes"]["recall_by_hidden"][name][1] for r in ran)
        out["recall_by_hidden"][name] = [n, found, round(found / n, 3) if n else None]
    for m in ("baseline", "pnp", "smoothed"):
        rs = [r["methods"][m] for r in ran if m in r["methods"]]
        out[m] = {
            "rmse_m": [x["rmse_m"] for x in rs],
            "ok": sum(x["ok"] for x in rs),
            "ok_beyond_3sigma": sum(x["ok_beyond_3sigma"] for x in rs),
            "ok_max_m": max((x["ok_max_m"] for x in rs if x["ok_max_m"] is not None), default=None),
        }
        for key in SURVEY_KEYS:
            sv = [r[key][m] for r in ran if m in r.get(key, {}) and r[key][m]["n"]]
            if sv:
                n = sum(v["n"] for v in sv)
                ms = sum(v["n"] * np.square(v["rms_z_xyz"]) for v in sv) / n
                out[m][key] = {
                    "n": n,
                    "rms_z_xyz": np.sqrt(ms).round(3).tolist(),
                    "ok": sum(v["ok"] for v in sv),
                    "ok_beyond_3sigma": sum(v["ok_beyond_3sigma"] for v in sv),
                }
    return out


def print_summary(s: dict) -> None:
    print(f"\n== summary over {s['flights']} flights (failed: {s['failed'] or 'none'})")
    print(
        f"  no drawn sign of the code in the box: {s['no_sign_in_box']} of {s['observed']} "
        f"observations (wrong codes {s['wrong_codes']}, right sign with the box beside it "
        f"{s['box_off_its_sign']}); missed "
        f"{s['missed']} of {s['visible']} visible signs >= {MIN_RECALL_PX:g} px "
        f"(unhidden: {s['missed_unhidden']} of {s['visible_unhidden']}); pixel_noise_scale "
        f"{s['noise_scales']}"
    )
    print(f"  recall by hidden share [visible, found, recall] {s['recall_by_hidden']}")
    print(
        "  intrinsics check acted on (correct camera files: a false alarm): "
        f"{s.get('intrinsics_acted_on') or 'none'}"
    )
    if s["missed_unhidden_why"]:
        print(
            f"  unhidden signs missed, decoded alone on their true box: {s['missed_unhidden_why']}"
        )
    for m in ("baseline", "pnp", "smoothed"):
        r = s[m]
        frac = 100 * r["ok_beyond_3sigma"] / r["ok"] if r["ok"] else 0.0
        print(
            f"  {m:<9} RMSE m {r['rmse_m']}; ok beyond 3 sigma {r['ok_beyond_3sigma']} of "
            f"{r['ok']} ({frac:.1f}%, Gaussian {100 * GAUSS_BEYOND_3:.1f}%); worst ok "
            f"{_fmt(r['ok_max_m'])} m"
        )
        for key in (k for k in SURVEY_KEYS if k in r):
            v = r[key]
            print(
                f"  {'':<9} more survey draws{' (oracle keypoints)' if key != 'surveys' else ''}"
                f", pooled: rms(e/sigma) x y z {v['rms_z_xyz']}, ok beyond 3 sigma "
                f"{v['ok_beyond_3sigma']} of {v['ok']}"
            )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="2 flights of 60 frames (~1 min)")
    ap.add_argument(
        "--flights", nargs="+", default=None, choices=[s.name for s in ALL_SETS],
        metavar="NAME", help="run these flights: " + ", ".join(s.name for s in ALL_SETS),
    )  # fmt: skip
    ap.add_argument(
        "--wide", action="store_true",
        help="add the wide-angle flights (" + ", ".join(s.name for s in WIDE_SET) + ")",
    )  # fmt: skip
    ap.add_argument("--work", type=Path, default=None, help="keep the flights here (reused)")
    ap.add_argument("--rerun", action="store_true", help="draw and run again even if cached")
    ap.add_argument(
        "--without", nargs="+", choices=tuple(ABLATIONS), default=[],
        help="take these conditions off every flight (names get -no_X)",
    )  # fmt: skip
    ap.add_argument(
        "--surveys", type=int, default=0,
        help="also estimate each flight against this many more survey draws of its map",
    )  # fmt: skip
    ap.add_argument(
        "--drop-lens-model", action="store_true",
        help="also estimate each distorted flight with camera.yaml's distortion dropped",
    )  # fmt: skip
    ap.add_argument(
        "--oracle", action="store_true",
        help="also estimate each flight from its observations with true keypoints",
    )  # fmt: skip
    ap.add_argument(
        "--why-missed", action="store_true",
        help="decode each unhidden sign the run missed on its true box (detector or decoder?)",
    )  # fmt: skip
    ap.add_argument(
        "--survey-response", action="store_true",
        help="measure the smoothed poses' response to each sign centre (3 estimates per "
        "sign): the survey's share of their sigma and how likely the flight's draw is",
    )  # fmt: skip
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    specs = QUICK_SET if args.quick else DEFAULT_SET
    if args.wide:
        specs = specs + WIDE_SET
    if args.flights:
        pool = {s.name: s for s in ALL_SETS} | {s.name: s for s in specs}
        specs = tuple(pool[n] for n in dict.fromkeys(args.flights))
    specs = tuple(without(s, args.without) for s in specs)
    work = args.work or Path(tempfile.mkdtemp(prefix="signpose_eval_flight_"))
    print(f"flights in {work}")
    results = []
    for spec in specs:
        results.append(
            evaluate(
                spec,
                work,
                args.rerun,
                args.surveys,
                args.drop_lens_model,
                args.oracle,
                args.why_missed,
                args.survey_response,
            )  # fmt: skip
        )
        print_flight(results[-1])
    summary = pooled(results)
    print_summary(summary)
    if args.json is not None:
        with atomic_write(args.json) as f:
            json.dump({"flights": results, "summary": summary}, f, indent=1, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
