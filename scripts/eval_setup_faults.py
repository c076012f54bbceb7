#!/usr/bin/env python
"""What ``signpose run`` says when the user's set-up is wrong: is any mistake silent?

Why: trust first. A wrong answer that says so can be acted on; a wrong answer
that is silent is the worst defect. signpose already catches a camera file with
the lens left out (``estimate.distrusted``), a sign surveyed 0.5 m off and bad
files; this script measures the other slips a user makes with the set-up. It
draws one or two flights with ``scripts/independent_flight.py`` (through a real
lens, as ``scripts/eval_flight.py`` draws them, 120 frames at 1280x720, the map
given as a survey leaves it: every centre moved by N(0, sigma_m)), runs
``signpose run --gt`` with the correct set-up and with each mistake below, and
grades every run by frame index against the drawing's ground truth:

* correct: the reference row;
* ``focal_3pct`` / ``focal_8pct``: camera.yaml's fx, fy 3 % / 8 % too large (a
  calibration made at another zoom or focus); ``focal_3pct_stated``: the same 3 %
  with ``--focal-sigma 0.03`` (the user stating the calibration's uncertainty);
* ``principal_15px``: the principal point 15 px off in u;
  ``principal_15px_stated``: the same with ``--principal-sigma 15``;
* ``codes_swapped``: the two most seen signs' codes swapped in the map (a survey
  record mix-up);
* ``sign_0.2m`` / ``sign_1m``: the most seen sign 0.2 m / 1 m off in the map,
  along its face; ``sign_1m_2nd``: the second most seen sign 1 m off (which
  sign is off decides the outcome: ties in frames seen go by code);
* ``diameter_10pct``: every sign's diameter 10 % too large in the map (signs
  printed smaller than recorded);
* ``sign_missing``: the most seen sign left out of the map (seen, unknown);
* ``other_lens``: the same intrinsics with another lens's distortion (the other
  flight's plumb_bob coefficients: a camera.yaml of another copy of the camera);
* ``lens_model_label``: the plumb_bob coefficients labelled equidistant (a
  conversion that kept the numbers and changed the model);
* ``calibration_1080p``: the calibration of the same camera at 1920x1080 for a
  1280x720 video (signpose must refuse it);
* ``survey_sigma_1mm``: the map claims sigma_m 1 mm for a 1 cm survey;
* ``sign_turned_15deg``: the most seen oriented sign hung 15 deg about its
  normal from the map's ``up``;
* ``frames_folder`` / ``fps_25``: the video's frames as a folder of PNGs, with
  ``--fps 30`` (its true rate: the control) and ``--fps 25`` (a PAL setting),
  without ``--gt`` (a user with the wrong rate has no ground truth on its clock;
  grading is by frame index).

Per run: exit code, smoothed / PnP position RMSE [m], share of frames ``ok``,
``ok`` poses beyond 3 sigma on some axis (the run's own sigma columns), every
``*noise_scale`` in report.json, the warnings (stderr lines with ``warning:``
and report.json ``warnings``) and the signs map_refined.json names as moved.
Verdict: ``refused`` (exit != 0), ``told`` (exit 0 with a warning; ``told*``:
its ``ok`` poses are still bad by the rule below), ``SILENT`` (exit 0, no
warning, and for smoothed or PnP more than 1 % of the ``ok`` poses beyond
3 sigma or an RMSE more than 3x the correct set-up's while some of its poses
are ``ok``: a method with no ``ok`` pose claims no accuracy, its ``weak``
statuses say so: ``weak`` when no warning came), else ``harmless``.

With ``--moved-suspect [SIGMAS]`` each run is graded a second time as a proposed
survey check would leave it: every pose of a frame that sees a sign the flight
moved by more than SIGMAS survey sigmas (map_refined.json; default 4.03, chi
with 3 dof at a 1 % family-wise rate over 10 signs) marked ``suspect``, from the
run's own files (the poses are the run's; only statuses change).

    nice -n 5 .venv/bin/python scripts/eval_setup_faults.py [--quick] [--work DIR]
        [--json PATH] [--flights NAME ...] [--scenarios NAME ...] [--moved-suspect]
        [--rerun]

The default (2 flights x 19 runs) took 4.7-6.8 min wall (4.8 min CPU) on the
shared 2-core machine at load 1-6 (before principal_15px_stated); ``--quick``
(1 flight, the reference and 3 mistakes) 45 s to 1.8 min wall (47 s CPU).
Flights and runs are kept in ``--work`` and reused when their commands and
signpose's source files are unchanged (``--rerun`` redoes them).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
from eval_flight import DEFAULT_SET, FlightSpec, pose_metrics, prepare, read_gt, run_signpose
from signpose.estimator.camera import EQUIDISTANT, CameraModel
from signpose.maps.loader import MapSign, SignMap, load_map, write_map

from signpose.core.fileio import atomic_write, ensure_dir
from signpose.io.camera_file import load_camera, write_camera_info

FLIGHT_FRAMES = 120
FLIGHTS = tuple(replace(s, frames=FLIGHT_FRAMES) for s in DEFAULT_SET[:2])
# The rule of a SILENT scenario (the brief's): beyond 3 sigma among ``ok``, RMSE ratio.
MAX_OK_BEYOND_3SIGMA = 0.01
MAX_RMSE_RATIO = 3.0
METHODS = ("smoothed", "pnp")
REFERENCE = "correct"
# --moved-suspect: the proposed survey check's threshold, chi with 3 dof at a 1 %
# family-wise rate over a 10-sign map (per sign 0.001: sqrt(16.27)).
MOVED_SUSPECT_SIGMAS = 4.03


# --------------------------------------------------------------------------- the mistakes


def scaled_focal(camera: CameraModel, factor: float) -> CameraModel:
    """``camera`` with fx and fy multiplied by ``factor`` (nothing else changed)."""
    K = np.array(camera.K, float)
    K[0, 0] *= factor
    K[1, 1] *= factor
    return replace(camera, K=K)


def shifted_principal_point(camera: CameraModel, du_px: float, dv_px: float) -> CameraModel:
    """``camera`` with the principal point moved by (du, dv) [px]."""
    K = np.array(camera.K, float)
    K[0, 2] += du_px
    K[1, 2] += dv_px
    return replace(camera, K=K)


def other_lens(camera: CameraModel, dist: tuple[float, ...]) -> CameraModel:
    """``camera``'s intrinsics with another lens's plumb_bob coefficients."""
    return replace(camera, dist=np.array(dist, float))


def relabelled_model(camera: CameraModel, model: str = EQUIDISTANT) -> CameraModel:
    """``camera``'s first four coefficients kept, labelled as ``model``."""
    return replace(camera, dist=np.array(camera.dist[:4], float), model=model)


def resized_calibration(camera: CameraModel, width: int, height: int) -> CameraModel:
    """The same camera calibrated at ``width`` x ``height`` (K scaled with the image)."""
    K = np.array(camera.K, float)
    K[0] *= width / camera.width
    K[1] *= height / camera.height
    return replace(camera, width=width, height=height, K=K)


def swapped_codes(sign_map: SignMap, a: str, b: str) -> SignMap:
    """``sign_map`` with the codes of signs ``a`` and ``b`` exchanged (places kept).

    The keypoints of each sign follow its code (``frontend.sign``), so the map's
    geometry differs only where the two codes' coded slots do.
    """
    swap = {a: b, b: a}
    return replace(
        sign_map, signs=tuple(replace(s, code=swap.get(s.code, s.code)) for s in sign_map.signs)
    )


def moved_sign(sign_map: SignMap, code: str, offset_m: np.ndarray) -> SignMap:
    """``sign_map`` with sign ``code``'s centre moved by ``offset_m`` (3,) [m]."""
    signs = tuple(
        replace(s, center_m=np.asarray(s.center_m, float) + offset_m) if s.code == code else s
        for s in sign_map.signs
    )
    return replace(sign_map, signs=signs)


def along_face(sign: MapSign, length_m: float) -> np.ndarray:
    """(3,) ``length_m`` along the sign's face, horizontal for an upright sign
    (its right axis; world x for a centre-only sign)."""
    if not sign.oriented:
        return np.array([length_m, 0.0, 0.0])
    return length_m * sign.world_R_sign()[:, 0]


def scaled_diameters(sign_map: SignMap, factor: float) -> SignMap:
    """``sign_map`` with every sign's diameter multiplied by ``factor``."""
    signs = tuple(replace(s, diameter_m=s.diameter_m * factor) for s in sign_map.signs)
    return replace(sign_map, signs=signs)


def without_sign(sign_map: SignMap, code: str) -> SignMap:
    """``sign_map`` without sign ``code``."""
    return replace(sign_map, signs=tuple(s for s in sign_map.signs if s.code != code))


def with_survey_sigma(sign_map: SignMap, sigma_m: float) -> SignMap:
    """``sign_map`` claiming ``sigma_m`` for every sign's survey."""
    return replace(sign_map, signs=tuple(replace(s, sigma_m=sigma_m) for s in sign_map.signs))


def turned_sign(sign_map: SignMap, code: str, angle_deg: float) -> SignMap:
    """``sign_map`` with sign ``code``'s ``up`` turned by ``angle_deg`` about its normal."""
    a = math.radians(angle_deg)

    def turn(s: MapSign) -> MapSign:
        if s.code != code:
            return s
        right = np.cross(s.up, s.normal)
        return replace(s, up=math.cos(a) * np.asarray(s.up, float) - math.sin(a) * right)

    return replace(sign_map, signs=tuple(turn(s) for s in sign_map.signs))


def video_to_folder(video: Path, folder: Path) -> int:
    """Every frame of ``video`` as ``folder/frame_NNNNN.png`` (lossless); the frame count."""
    ensure_dir(folder)
    done = folder / "frames.done"
    if done.is_file():
        return int(done.read_text())
    cap = cv2.VideoCapture(str(video))
    n = 0
    try:
        while True:
            ok, image = cap.read()
            if not ok:
                break
            cv2.imwrite(str(folder / f"frame_{n:05d}.png"), image)
            n += 1
    finally:
        cap.release()
    done.write_text(str(n))
    return n


# --------------------------------------------------------------------------- scenarios


@dataclass(frozen=True)
class Flight:
    """One drawn flight as the scenarios see it.

    Attributes:
        spec: what was drawn; folder: its work folder; video, camera_path, gt: its files.
        sign_map: the surveyed map (the correct set-up's).
        camera: the flight's correct camera.
        most_seen: codes by frames seen in the correct run, most first.
        other_dist: a plumb_bob lens of another flight.
    """

    spec: FlightSpec
    folder: Path
    video: Path
    camera_path: Path
    gt: Path
    sign_map: SignMap
    camera: CameraModel
    most_seen: tuple[str, ...] = ()
    other_dist: tuple[float, ...] = ()


@dataclass(frozen=True)
class Setup:
    """What ``signpose run`` is given: the input, map, camera, --fps, --gt (None: left
    out), and more options (``extra``)."""

    input_path: Path
    map_path: Path
    camera_path: Path
    fps: float | None = None
    gt: Path | None = None
    extra: tuple[str, ...] = ()


def _with_map(f: Flight, d: Path, sign_map: SignMap) -> Setup:
    write_map(d / "map.yaml", sign_map)
    return Setup(f.video, d / "map.yaml", f.camera_path, gt=f.gt)


def _with_camera(f: Flight, d: Path, camera: CameraModel) -> Setup:
    write_camera_info(d / "camera.yaml", camera)
    return Setup(f.video, f.folder / "map_surveyed.yaml", d / "camera.yaml", gt=f.gt)


def _sign(f: Flight, code: str) -> MapSign:
    return next(s for s in f.sign_map.signs if s.code == code)


def _oriented_most_seen(f: Flight) -> str:
    return next(c for c in f.most_seen if _sign(f, c).oriented)


def _folder(f: Flight, fps: float) -> Setup:
    frames = f.folder / "frames_png"
    video_to_folder(f.video, frames)
    return Setup(frames, f.folder / "map_surveyed.yaml", f.camera_path, fps=fps)


@dataclass(frozen=True)
class Scenario:
    name: str
    what: str
    build: Callable[[Flight, Path], Setup]


SCENARIOS = (
    Scenario(REFERENCE, "the correct set-up",
             lambda f, d: Setup(f.video, f.folder / "map_surveyed.yaml", f.camera_path, gt=f.gt)),
    Scenario("focal_3pct", "fx, fy 3 % too large",
             lambda f, d: _with_camera(f, d, scaled_focal(f.camera, 1.03))),
    Scenario("focal_8pct", "fx, fy 8 % too large",
             lambda f, d: _with_camera(f, d, scaled_focal(f.camera, 1.08))),
    Scenario("focal_3pct_stated", "fx, fy 3 % too large, run with --focal-sigma 0.03",
             lambda f, d: replace(_with_camera(f, d, scaled_focal(f.camera, 1.03)),
                                  extra=("--focal-sigma", "0.03"))),
    Scenario("principal_15px", "principal point 15 px off in u",
             lambda f, d: _with_camera(f, d, shifted_principal_point(f.camera, 15.0, 0.0))),
    Scenario("principal_15px_stated", "principal point 15 px off in u, --principal-sigma 15",
             lambda f, d: replace(_with_camera(f, d, shifted_principal_point(f.camera, 15.0, 0.0)),
                                  extra=("--principal-sigma", "15"))),
    Scenario("codes_swapped", "the two most seen signs' codes swapped in the map",
             lambda f, d: _with_map(f, d, swapped_codes(f.sign_map, *f.most_seen[:2]))),
    Scenario("sign_0.2m", "the most seen sign 0.2 m off along its face",
             lambda f, d: _with_map(f, d, moved_sign(
                 f.sign_map, f.most_seen[0], along_face(_sign(f, f.most_seen[0]), 0.2)))),
    Scenario("sign_1m", "the most seen sign 1 m off along its face",
             lambda f, d: _with_map(f, d, moved_sign(
                 f.sign_map, f.most_seen[0], along_face(_sign(f, f.most_seen[0]), 1.0)))),
    Scenario("sign_1m_2nd", "the second most seen sign 1 m off along its face",
             lambda f, d: _with_map(f, d, moved_sign(
                 f.sign_map, f.most_seen[1], along_face(_sign(f, f.most_seen[1]), 1.0)))),
    Scenario("diameter_10pct", "every diameter 10 % too large in the map",
             lambda f, d: _with_map(f, d, scaled_diameters(f.sign_map, 1.1))),
    Scenario("sign_missing", "the most seen sign left out of the map",
             lambda f, d: _with_map(f, d, without_sign(f.sign_map, f.most_seen[0]))),
    Scenario("other_lens", "the intrinsics with another flight's lens distortion",
             lambda f, d: _with_camera(f, d, other_lens(f.camera, f.other_dist))),
    Scenario("lens_model_label", "plumb_bob k1 k2 p1 p2 labelled equidistant",
             lambda f, d: _with_camera(f, d, relabelled_model(f.camera))),
    Scenario("calibration_1080p", "the same camera's calibration at 1920x1080",
             lambda f, d: _with_camera(f, d, resized_calibration(f.camera, 1920, 1080))),
    Scenario("survey_sigma_1mm", "the map claims sigma_m 1 mm for a 1 cm survey",
             lambda f, d: _with_map(f, d, with_survey_sigma(f.sign_map, 0.001))),
    Scenario("sign_turned_15deg", "the most seen oriented sign hung 15 deg off its 'up'",
             lambda f, d: _with_map(f, d, turned_sign(f.sign_map, _oriented_most_seen(f), 15.0))),
    Scenario("frames_folder", "the frames as PNGs, --fps 30 (its rate; control)",
             lambda f, d: _folder(f, 30.0)),
    Scenario("fps_25", "the frames as PNGs, --fps 25 (true 30)",
             lambda f, d: _folder(f, 25.0)),
)  # fmt: skip
QUICK_FLIGHTS = FLIGHTS[:1]
QUICK_SCENARIOS = (REFERENCE, "focal_8pct", "codes_swapped", "sign_1m")


def _run_argv(setup: Setup, out: Path) -> list[str]:
    argv = ["run", str(setup.input_path), "--map", str(setup.map_path)]
    argv += ["--camera", str(setup.camera_path), "--out", str(out), "--workers", "1", "-q"]
    if setup.fps is not None:
        argv += ["--fps", f"{setup.fps:g}"]
    if setup.gt is not None:
        argv += ["--gt", str(setup.gt)]
    return argv + list(setup.extra)


def _noise_scales(report: dict) -> dict[str, float]:
    """Every ``*noise_scale`` key of report.json (any depth), by its dotted name."""
    out = {}

    def walk(d: dict, where: str) -> None:
        for k, v in d.items():
            if isinstance(v, dict):
                walk(v, f"{where}{k}.")
            elif k.endswith("noise_scale") and isinstance(v, int | float):
                out[where + k] = float(v)

    walk(report, "")
    return out


def _warnings(stderr: str) -> list[str]:
    return [line.strip() for line in stderr.splitlines() if "warning:" in line]


def moved_suspect(out: Path, gt: Path, n_frames: int, sigmas: float) -> dict | None:
    """The proposed survey check, from the run's own files: every pose of a frame that
    sees a sign the flight moved by more than ``sigmas`` survey sigmas
    (map_refined.json's ``moved_sigmas``) marked ``suspect``; then graded as the run.

    Returns the flagged signs, the frames marked and the methods' metrics, or None
    without map_refined.json.
    """
    refined = out / "map_refined.json"
    if not refined.is_file():
        return None
    moved = {
        s["code"]: s["moved_sigmas"]
        for s in json.loads(refined.read_text()).get("signs", [])
        if s["moved_sigmas"] > sigmas
    }
    flagged = set()
    with open(out / "observations.jsonl") as fh:
        for line in fh:
            if line.strip():
                frame = json.loads(line)
                if any(o["code"] in moved for o in frame["signs"]):
                    flagged.add(frame["frame"])
    with open(out / "trajectory.csv") as fh:
        rows = list(csv.DictReader(fh))
    for r in rows:
        if int(r["frame"]) in flagged and r["status"] in ("ok", "weak"):
            r["status"] = "suspect"
    marked = out.parent / "moved_suspect_trajectory.csv"
    with atomic_write(marked) as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    return {
        "sigmas": sigmas,
        "signs": {c: round(v, 1) for c, v in sorted(moved.items(), key=lambda kv: -kv[1])},
        "frames_marked": len(flagged),
        "methods": pose_metrics(marked, read_gt(gt), n_frames),
    }


def grade(
    f: Flight, scenario: Scenario, work: Path, rerun: bool, suspect_sigmas: float | None = None
) -> dict:
    """Run one scenario on one flight and read what it said and how right it was."""
    d = ensure_dir(work / f.spec.name / scenario.name)
    setup = scenario.build(f, d)
    argv = _run_argv(setup, d / "out")
    t0 = time.perf_counter()
    ran = run_signpose(argv, d / "ran.json", rerun)
    row = {
        "flight": f.spec.name,
        "scenario": scenario.name,
        "what": scenario.what,
        "command": "nice -n 5 .venv/bin/signpose " + " ".join(argv),
        "exit": ran["exit"],
        "seconds": round(time.perf_counter() - t0, 1),
        "stderr_warnings": _warnings(ran["stderr"]),
        "stderr": ran["stderr"].strip()[-2000:],
    }
    out = d / "out"
    if not (out / "report.json").is_file() or not (out / "trajectory.csv").is_file():
        return row
    report = json.loads((out / "report.json").read_text())
    refined = out / "map_refined.json"
    row |= {
        "report_warnings": list(report.get("warnings", [])),
        "noise_scales": _noise_scales(report),
        "moved": json.loads(refined.read_text()).get("moved", []) if refined.is_file() else [],
        "methods": pose_metrics(out / "trajectory.csv", read_gt(f.gt), f.spec.frames),
    }
    if suspect_sigmas is not None:
        row["moved_suspect"] = moved_suspect(out, f.gt, f.spec.frames, suspect_sigmas)
    return row


def _bad(row: dict, reference: dict | None) -> list[str]:
    """Why ``row``'s poses are wrong by the SILENT rule (empty: they are not)."""
    why = []
    for m in METHODS:
        r = row.get("methods", {}).get(m)
        if r is None:
            continue
        if r["ok"] and r["ok_beyond_3sigma"] / r["ok"] > MAX_OK_BEYOND_3SIGMA:
            why.append(f"{m} {r['ok_beyond_3sigma']} of {r['ok']} ok beyond 3 sigma")
        ratio = _rmse_ratio(r, reference, m)
        if r["ok"] and ratio > MAX_RMSE_RATIO:
            why.append(f"{m} RMSE {ratio:.1f}x the correct set-up's")
    return why


def _rmse_ratio(r: dict, reference: dict | None, method: str) -> float:
    """``r``'s RMSE over the correct set-up's for ``method`` (0 when either is unknown)."""
    ref = (reference or {}).get("methods", {}).get(method, {}).get("rmse_m")
    return r["rmse_m"] / ref if ref and r["rmse_m"] is not None else 0.0


def verdict(row: dict, reference: dict | None) -> str:
    """refused / told / told* / SILENT / weak / harmless (module docstring)."""
    if row["exit"] != 0:
        return "refused"
    bad = _bad(row, reference)
    if row["stderr_warnings"] or row.get("report_warnings"):
        return "told*" if bad else "told"
    if bad:
        return "SILENT"
    return "weak" if _far_but_not_ok(row, reference) else "harmless"


def _far_but_not_ok(row: dict, reference: dict | None) -> bool:
    """A method far off (RMSE > ``MAX_RMSE_RATIO`` x the reference's) with no ``ok`` pose."""
    rows = ((m, row.get("methods", {}).get(m)) for m in METHODS)
    return any(r and not r["ok"] and _rmse_ratio(r, reference, m) > MAX_RMSE_RATIO for m, r in rows)


# --------------------------------------------------------------------------- flights


def _seen_counts(observations: Path) -> Counter:
    seen: Counter = Counter()
    with open(observations) as fh:
        for line in fh:
            if line.strip():
                seen.update({o["code"] for o in json.loads(line)["signs"]})
    return seen


def most_seen(seen: Counter, codes: tuple[str, ...]) -> tuple[str, ...]:
    """The map's codes by frames seen, most first, ties by code (not by the order a set
    of strings, hashed per process, happened to give: a different sign each run)."""
    return tuple(sorted((c for c in seen if c in codes), key=lambda c: (-seen[c], c)))


def load_flight(spec: FlightSpec, work: Path, rerun: bool, other_dist: tuple[float, ...]) -> Flight:
    """Draw ``spec`` (unless drawn) and read what the scenarios need."""
    flight, _, _ = prepare(spec, work, rerun)
    d = work / spec.name
    return Flight(
        spec=spec,
        folder=d,
        video=flight / "video.mp4",
        camera_path=flight / "camera.yaml",
        gt=flight / "groundtruth.tum",
        sign_map=load_map(d / "map_surveyed.yaml"),
        camera=load_camera(flight / "camera.yaml"),
        other_dist=other_dist,
    )


def evaluate(
    spec: FlightSpec,
    work: Path,
    rerun: bool,
    names: tuple[str, ...],
    suspect_sigmas: float | None = None,
) -> list[dict]:
    """Every scenario in ``names`` on one flight, the correct set-up first."""
    other = next(s for s in DEFAULT_SET if s.options.dist and s.options.dist != spec.options.dist)
    f = load_flight(spec, work, rerun, other.options.dist)
    by_name = {s.name: s for s in SCENARIOS}
    ref = grade(f, by_name[REFERENCE], work, rerun, suspect_sigmas)
    if ref["exit"] != 0 or "methods" not in ref:
        raise SystemExit(f"the correct set-up failed: {ref['command']}: {ref['stderr']}")
    seen = _seen_counts(work / spec.name / REFERENCE / "out" / "observations.jsonl")
    f = replace(f, most_seen=most_seen(seen, f.sign_map.codes))
    rows = [ref]
    for name in names:
        if name != REFERENCE:
            rows.append(grade(f, by_name[name], work, rerun, suspect_sigmas))
    for row in rows:
        row["verdict"] = verdict(row, ref)
        row["why_bad"] = _bad(row, ref)
        if row.get("moved_suspect"):
            what_if = row | {"methods": row["moved_suspect"]["methods"]}
            row["moved_suspect"]["why_bad"] = _bad(what_if, ref)
    rows[0]["most_seen"] = list(f.most_seen)
    return rows


# --------------------------------------------------------------------------- printing


def _cell(row: dict, key: str) -> str:
    vals = []
    for m in METHODS:
        r = row.get("methods", {}).get(m)
        if r is None:
            vals.append("-")
        elif key == "rmse":
            vals.append("-" if r["rmse_m"] is None else f"{r['rmse_m']:.3f}")
        elif key == "ok":
            vals.append(f"{100 * r['status'].get('ok', 0):.0f}%")
        else:
            vals.append(f"{r['ok_beyond_3sigma']}/{r['ok']}")
    return " / ".join(vals)


def print_table(rows: list[dict]) -> None:
    head = (
        f"{'flight':<14}{'scenario':<23}{'exit':>4}  {'RMSE m sm / pnp':<17}"
        f"{'ok sm / pnp':<13}{'ok>3sig sm / pnp':<18}{'noise scale':<12}{'warn':>4}  verdict"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        scales = r.get("noise_scales", {})
        scale = "-" if not scales else "/".join(f"{v:.2f}" for v in scales.values())
        n_warn = f"{len(r['stderr_warnings'])}/{len(r.get('report_warnings', []))}"
        print(
            f"{r['flight']:<14}{r['scenario']:<23}{r['exit']:>4}  {_cell(r, 'rmse'):<17}"
            f"{_cell(r, 'ok'):<13}{_cell(r, 'beyond'):<18}{scale:<12}{n_warn:>13}  {r['verdict']}"
        )


def print_details(rows: list[dict]) -> None:
    for r in rows:
        print(f"\n== {r['flight']} / {r['scenario']}: {r['what']} -> {r['verdict']}")
        print(f"  $ {r['command']}")
        if r.get("most_seen"):
            print(f"  signs by frames seen: {' '.join(r['most_seen'])}")
        if r.get("noise_scales"):
            print(f"  report.json noise scales: {r['noise_scales']}; moved: {r.get('moved')}")
        for line in r["stderr_warnings"]:
            print(f"  stderr: {line}")
        for line in r.get("report_warnings", []):
            print(f"  report.json warning: {line}")
        if r["exit"] != 0:
            print(f"  exit {r['exit']}: {r['stderr']}")
        if r.get("why_bad"):
            print(f"  wrong: {'; '.join(r['why_bad'])}")


def print_moved_suspect(rows: list[dict]) -> None:
    """The table's pose columns again with the proposed survey check applied."""
    print(
        "\nwith every frame that sees a sign moved by more than "
        f"{rows[0]['moved_suspect']['sigmas'] if rows[0].get('moved_suspect') else '?'} "
        "survey sigmas (map_refined.json) marked suspect:"
    )
    head = (
        f"{'flight':<14}{'scenario':<23}{'frames':>6}  {'ok sm / pnp':<13}"
        f"{'ok>3sig sm / pnp':<18}still wrong (ok poses)"
    )
    print(head)
    print("-" * len(head))
    for r in rows:
        m = r.get("moved_suspect")
        if not m:
            continue
        what_if = {"methods": m["methods"]}
        print(
            f"{r['flight']:<14}{r['scenario']:<23}{m['frames_marked']:>6}  "
            f"{_cell(what_if, 'ok'):<13}{_cell(what_if, 'beyond'):<18}"
            f"{'; '.join(w for w in m['why_bad'] if 'ok beyond' in w) or '-'}"
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="1 flight, the reference and 3 mistakes")
    ap.add_argument("--flights", nargs="+", default=None, help="names of the flights to run")
    ap.add_argument("--scenarios", nargs="+", default=None, choices=[s.name for s in SCENARIOS])
    ap.add_argument("--work", type=Path, default=None, help="keep flights and runs here (reused)")
    ap.add_argument("--rerun", action="store_true", help="draw and run again even if cached")
    ap.add_argument(
        "--moved-suspect", type=float, nargs="?", const=MOVED_SUSPECT_SIGMAS, default=None,
        metavar="SIGMAS",
        help="also grade each run with every frame that sees a sign the flight moved by more "
        f"than SIGMAS survey sigmas marked suspect (the proposed survey check; default "
        f"{MOVED_SUSPECT_SIGMAS})",
    )  # fmt: skip
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)
    specs = QUICK_FLIGHTS if args.quick else FLIGHTS
    if args.flights:
        specs = tuple(s for s in FLIGHTS if s.name in args.flights)
    names = tuple(
        args.scenarios or (QUICK_SCENARIOS if args.quick else [s.name for s in SCENARIOS])
    )
    work = args.work or Path(tempfile.mkdtemp(prefix="signpose_setup_faults_"))
    print(f"flights and runs in {work}")
    rows = []
    for spec in specs:
        rows += evaluate(spec, work, args.rerun, names, args.moved_suspect)
    print_details(rows)
    print(
        f"\nSILENT: exit 0, no warning, and for smoothed or PnP > {100 * MAX_OK_BEYOND_3SIGMA:g} % "
        f"of the ok poses beyond 3 sigma or RMSE > {MAX_RMSE_RATIO:g}x the correct set-up's "
        "with some poses ok; "
        "told*: warned, its ok poses still wrong by that rule\n"
    )
    print_table(rows)
    silent = sorted({r["scenario"] for r in rows if r["verdict"] == "SILENT"})
    print(f"\nsilent scenarios: {', '.join(silent) or 'none'}")
    if args.moved_suspect is not None:
        print_moved_suspect(rows)
    if args.json is not None:
        with atomic_write(args.json) as fh:
            json.dump({"rows": rows, "silent": silent}, fh, indent=1, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
