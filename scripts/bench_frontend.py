#!/usr/bin/env python
"""Frontend CPU per 1080p frame and per crop, as ratios measured in one run.

Simulates two short held-out flights: ``sim`` (``SimSettings()`` defaults)
and ``hard`` (``SimSettings().hard()``: photographs behind the pylon,
members and conductors in front of signs, JPEG 70-90, blur bursts, exposure
steps). On the same frames, one after the other per frame (so that the
machine's load hits all alike), with ``cv2.setNumThreads(1)``, it measures
the CPU time of this thread (``time.thread_time``) of:

* ``fast``: full-frame cold detection, fast mode (cascade + merge + decoder);
* ``track``: tracking as ``pipeline.observe`` runs it: the pipeline's
  ``FrameTracker`` (poses from the frame's own observations, predictions
  from the pose ``track_lag_frames`` back: code, centre, diameter and
  homography) plans each frame; ``detect_tracked`` verifies the predicted
  signs (``frontend.verify``) and searches only those that disagree; frames
  without predictions (the first ones, lost track) are fast-mode searches;
* ``track_search``: the same with the predictions' homographies left out
  (every predicted sign searched with the cascade and decoded in full: the
  tracking before verification), fed its own results;
* ``aruco``: ``cv2.aruco.ArucoDetector.detectMarkers`` (DICT_4X4_50).

Per mode: the median over frames of the per-frame minimum over ``--repeat``
passes, and its ratio to ArUco's; the ratio is also given per pass (min and
median over passes). Per crop (the true signs >= 18 px of those frames, and
crops of ``scripts/independent_scene.py``, a renderer that shares no
drawing code with the simulator): median CPU of a full decode
(``decode_region`` on the true box) and of a verification (``verify_sign``
at the predicted homography, moved by the frame's median prediction offset
as ``detect_tracked`` moves it; on the independent crops the true homography
shifted by 0.5 px). Found signs, wrong codes (a code at no true sign of that
code) and verification outcomes are counted per mode. ``--check-verify``
also runs the slow reference verification of tests/test_verify_fast.py on
every timed crop and counts those whose outcome or reading differs.

    .venv/bin/python scripts/bench_frontend.py [--quick] [--frames N] [--repeat R] [--json PATH]
        [--check-verify] [--profile {fast,track}] [--appearance]

``--appearance`` measures the premise of reusing a verification's checks while a
tracked sign looks unchanged (``_appearance``): how much a verified sign's disc
changes from one frame to the next, against the image noise.
"""

from __future__ import annotations

import argparse
import collections
import cProfile
import importlib.util
import json
import math
import pstats
import statistics
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from signpose.frontend.decoder import _CODE_PARTS, decode_region, decode_roi
from signpose.frontend.detector import PredictedSign, SignDetector, to_frame_observations
from signpose.frontend.verify import verify_sign
from signpose.maps.loader import bundled_map_path, load_map

from signpose.core.fileio import atomic_write
from signpose.io.boxes import read_boxes
from signpose.pipeline import FramePlan, FrameTracker, ObserveSettings
from signpose.sim.flight import SimSettings, simulate

BENCH_SEED = 5151
MODES = ("fast", "track", "track_search", "aruco")
MIN_SIGN_PX = 18.0
SCENE_CROPS = 60


def _cpu_ms(fn) -> tuple[float, object]:
    t0 = time.thread_time()
    out = fn()
    return (time.thread_time() - t0) * 1e3, out


def _scene(kind: str, n: int, sign_map) -> dict:
    """Frames, truth and camera of one simulated flight."""
    settings = SimSettings(frames=n, seed=BENCH_SEED, format="png")
    if kind == "hard":
        settings = settings.hard()
    with tempfile.TemporaryDirectory() as tmp:
        sim = simulate(sign_map, tmp, settings, progress=False)
        boxes = read_boxes(Path(tmp) / "boxes.jsonl")
        frames = [
            cv2.imread(str(Path(tmp) / "frames" / f"{i:06d}.png"), cv2.IMREAD_GRAYSCALE)
            for i in range(settings.frames)
        ]
    return {
        "frames": frames,
        "boxes": boxes,
        "camera": sim.camera,
        "preds": {},
        "plans": {},
        "crops": [],
    }


class _Tracking:
    """The pipeline's tracker (``FrameTracker``) fed one frame at a time, frames in order.

    ``plan(i)`` sees the frames up to ``i - track_lag_frames`` finished, as
    in ``pipeline.observe`` (whatever the number of workers).
    """

    def __init__(self, sign_map, camera, codes, homographies: bool):
        self.settings = ObserveSettings(workers=1)
        self.tracker = FrameTracker(sign_map, camera, codes, self.settings)
        self.homographies = homographies
        self.pending: collections.deque = collections.deque()

    def plan(self, i: int) -> FramePlan:
        while self.pending and self.pending[0][0] <= i - self.settings.track_lag_frames:
            self._finish(*self.pending.popleft())
        plan = self.tracker.plan(i)
        if not self.homographies:
            plan = FramePlan(tuple(PredictedSign(*p[:3]) for p in plan.predictions), plan.refresh)
        return plan

    def done(self, i: int, plan: FramePlan, result, shape) -> None:
        self.pending.append((i, plan, result, shape))

    def _finish(self, i, plan, result, shape) -> None:
        obs = to_frame_observations(result, i, 0, (shape[1], shape[0]))
        tracked = bool(plan.predictions) and not result.fell_back
        self.tracker.finish(i, obs, plan, not tracked)


def _score(dets, truth: dict, tally: collections.Counter) -> None:
    signs = [s for s in truth["signs"] if s["diameter_px"] >= MIN_SIGN_PX and not s["truncated"]]
    tally["signs"] += len(signs)
    for d in dets:
        near = [
            s
            for s in truth["signs"]
            if s["code"] == d.code
            and math.dist(d.center_px, s["center_px"]) <= 0.5 * s["diameter_px"]
        ]
        tally["found" if near else "wrong"] += 1
        if near and near[0] in signs:
            tally["found_ge18"] += 1


def _frame_modes(det, aruco, scene, sign_map, repeat):
    """Per mode: per-frame minimum CPU [ms] over ``repeat`` passes, and per-pass lists."""
    codes = sign_map.codes
    passes = {m: [[] for _ in range(repeat)] for m in MODES}
    tallies = {m: collections.Counter() for m in MODES if m != "aruco"}
    outcomes = collections.Counter()
    parts = {m: collections.defaultdict(list) for m in tallies}
    trackers = {
        "track": _Tracking(sign_map, scene["camera"], codes, True),
        "track_search": _Tracking(sign_map, scene["camera"], codes, False),
    }
    for i, f in enumerate(scene["frames"]):
        plans = {m: t.plan(i) for m, t in trackers.items()}
        scene["preds"][i] = plans["track"].predictions
        scene["plans"][i] = plans["track"]
        calls = {"fast": lambda f=f: det.detect(f, codes, "fast")}
        for m, plan in plans.items():
            if plan.predictions:
                calls[m] = lambda f=f, p=plan: det.detect_tracked(
                    f, p.predictions, codes, p.refresh
                )
            else:
                calls[m] = lambda f=f: det.detect(f, codes, "fast")
        calls["aruco"] = lambda f=f: aruco.detectMarkers(f)
        for r in range(repeat):
            for m in MODES:
                ms, res = _cpu_ms(calls[m])
                passes[m][r].append(ms)
                if r or m == "aruco":
                    continue
                _score(res.detections, scene["boxes"][i], tallies[m])
                for part in ("cascade", "verify", "decode", "retry"):
                    parts[m][part].append(res.timing.get(part, 0.0))
                if m in trackers:
                    tallies[m]["full_frames"] += int(not plans[m].predictions or res.fell_back)
                    trackers[m].done(i, plans[m], res, f.shape)
                    if m == "track":
                        outcomes.update(o.value for o in res.verifications)
    per_frame = {m: [min(v) for v in zip(*passes[m], strict=True)] for m in MODES}
    for m, t in tallies.items():
        for part, v in parts[m].items():
            t[f"{part}_ms_median"] = statistics.median(v)  # wall, pass 0
            t[f"{part}_ms_mean"] = statistics.fmean(v)
    return per_frame, passes, tallies, outcomes


def _crop_times(scene, codes, check=None, other=None) -> dict:
    """Median CPU [ms] per crop: full decode on the true box, verification at the prediction.

    ``check``: ``_reference_check()``, to count the verifications whose outcome
    or reading differs from the reference's (``check_differ``). ``other``:
    another ``verify_sign`` (``--ab-verify``), timed against this one.
    """
    full, ver = [], []
    ab: dict[str, list[float]] = {"this": [], "other": []}
    outcomes = collections.Counter()
    for i, f in enumerate(scene["frames"]):
        truth = scene["boxes"][i]
        by_code = {s["code"]: s for s in truth["signs"] if s["diameter_px"] >= MIN_SIGN_PX}
        preds = [p for p in scene["preds"][i] if p.image_H_sign is not None and p.code in by_code]
        if not preds:
            continue
        du, dv = np.median(
            [np.subtract(by_code[p.code]["center_px"], p.center_px) for p in preds], 0
        )
        shift = np.array([[1.0, 0, du], [0, 1.0, dv], [0, 0, 1.0]])
        for p in preds:
            s = by_code[p.code]
            ms, _ = _cpu_ms(lambda s=s, f=f: decode_region(f, tuple(s["bbox_px"]), codes))
            full.append(ms)
            h = shift @ p.image_H_sign
            scene["crops"].append((f, h, p.code))
            ms, v = _cpu_ms(lambda p=p, f=f, h=h: verify_sign(f, h, p.code, codes))
            ver.append(ms)
            outcomes[v.outcome.value] += 1
            if check is not None:
                reference, differences = check
                outcomes["check_differ"] += bool(differences(v, reference(f, h, p.code, codes)))
            if other is not None:
                _ab(
                    ab,
                    lambda p=p, f=f, h=h: verify_sign(f, h, p.code, codes),
                    lambda p=p, f=f, h=h: other(f, h, p.code, codes),
                )
    out = {"full_decode_ms": _med(full), "verify_ms": _med(ver), "crops": len(full), **outcomes}
    return out | _ab_medians(ab)


# The smoothing of --appearance [px], and the white noise's gain through it (1 / (2 sqrt(pi) s)).
APPEARANCE_BLUR_PX = 1.0
APPEARANCE_NOISE_GAIN = 1.0 / (2.0 * math.sqrt(math.pi) * APPEARANCE_BLUR_PX)
# --appearance's test for a change: beyond this many noise sigmas of a difference of two
# images, plus this registration error [px] times the local gradient.
APPEARANCE_NOISE_K = 5.0
APPEARANCE_SHIFT_PX = 0.2


def _appearance(scene, codes) -> dict:
    """How much a verified sign's appearance changes from one frame to the next.

    The premise of reusing a verification's checks while a tracked sign looks
    unchanged (issue 14): for every sign verified (at the prediction, moved as
    in ``_crop_times``) in two consecutive frames, the earlier frame's pixels
    warped onto the later frame's refit homography (through the sign plane),
    compared over the disc less its outer pixel (the background's parallax
    stays out), raw and with both images smoothed over the disc by a
    ``APPEARANCE_BLUR_PX`` Gaussian (a normalised convolution): the largest
    absolute difference as a fraction of the contrast (the disc's 97th less
    its 3rd percentile of gray), and whether every pixel is within
    ``APPEARANCE_NOISE_K`` noise sigmas of a difference of two images
    (``sigma_inputs.noise`` times the contrast, floored at 1, times sqrt(2),
    and times ``APPEARANCE_NOISE_GAIN`` when smoothed) plus
    ``APPEARANCE_SHIFT_PX`` times the local gradient (the test a reuse would
    make). The control: a still sign, i.e. the earlier frame again with
    fresh Gaussian noise of sqrt(2) times its measured noise (a difference of
    two such images has the noise of a difference of two frames), verified
    again and compared the same way. ``scale_3pct``: the share of pairs whose
    major axis changed by at most 3 %.
    """
    rng = np.random.default_rng(BENCH_SEED)
    prev: dict[str, tuple] = {}
    rows: dict[str, list] = {"flight": [], "still": []}
    scale_ok = []
    for i, f in enumerate(scene["frames"]):
        truth = scene["boxes"][i]
        by_code = {s["code"]: s for s in truth["signs"] if s["diameter_px"] >= MIN_SIGN_PX}
        preds = [p for p in scene["preds"][i] if p.image_H_sign is not None and p.code in by_code]
        cur: dict[str, tuple] = {}
        if preds:
            du, dv = np.median(
                [np.subtract(by_code[p.code]["center_px"], p.center_px) for p in preds], 0
            )
            shift = np.array([[1.0, 0, du], [0, 1.0, dv], [0, 0, 1.0]])
            for p in preds:
                h = shift @ p.image_H_sign
                v = verify_sign(f, h, p.code, codes)
                if v.ok and v.result.sigma_inputs is not None:
                    r = v.result
                    cur[p.code] = (f, r.image_H_sign, r.ellipse[1][0], r.sigma_inputs.noise, h)
        for code, (g1, h1, major1, _, _) in cur.items():
            if code not in prev:
                continue
            g0, h0, major0, noise0, predicted0 = prev[code]
            flight = _appearance_change(g0, h0, g1, h1, major1, noise0)
            if flight is None:
                continue
            rows["flight"].append(flight)
            scale_ok.append(abs(major1 / major0 - 1.0) <= 0.03)
            noisy = _with_fresh_noise(g0, h0, math.sqrt(2.0) * max(noise0 * flight[2], 1.0), rng)
            v = verify_sign(noisy, predicted0, code, codes)
            if v.ok:
                (_, (major, _), _) = v.result.ellipse
                still = _appearance_change(g0, h0, noisy, v.result.image_H_sign, major, noise0)
                if still is not None:
                    rows["still"].append(still)
        prev = cur
    out: dict = {"pairs": len(rows["flight"]), "still_pairs": len(rows["still"])}
    if not rows["flight"]:
        return out
    out["scale_3pct"] = float(np.mean(scale_ok))
    for name, r in rows.items():
        if not r:
            continue
        raw, smooth, _, same_raw, same_smooth = (np.array(x, float) for x in zip(*r, strict=True))
        out[name] = {
            "raw_p50": float(np.median(raw)),
            "smooth_p50": float(np.median(smooth)),
            "smooth_p90": float(np.percentile(smooth, 90)),
            "unchanged_raw": float(same_raw.mean()),
            "unchanged_smooth": float(same_smooth.mean()),
        }
    return out


def _with_fresh_noise(g, image_H_sign, sigma, rng):
    """``g`` with Gaussian noise of ``sigma`` [gray levels] added around the sign's disc."""
    rim = cv2.perspectiveTransform(_APPEARANCE_RIM[None] * 1.0, image_H_sign)[0]
    x0, y0 = np.maximum(np.floor(rim.min(axis=0)).astype(int) - 4, 0)
    x1, y1 = np.ceil(rim.max(axis=0)).astype(int) + 5
    out = g.copy()
    win = out[y0:y1, x0:x1]
    win[...] = np.clip(np.round(win + rng.normal(0.0, sigma, win.shape)), 0, 255)
    return out


_APPEARANCE_RIM = 0.5 * np.stack(
    [np.cos(np.linspace(0, 2 * np.pi, 48)), np.sin(np.linspace(0, 2 * np.pi, 48))], axis=1
)


def _appearance_change(g0, h0, g1, h1, major1, noise0):
    """(raw, smoothed largest |difference| / contrast, contrast [gray levels],
    unchanged raw, unchanged smoothed) of frame 0's disc warped onto frame 1's,
    or None (see ``_appearance``); ``noise0``: frame 0's noise over the contrast."""
    inner = (1.0 - 2.0 / max(major1, 1e-9)) * _APPEARANCE_RIM
    rim1 = cv2.perspectiveTransform(inner[None], h1)[0]
    x0, y0 = np.floor(rim1.min(axis=0)).astype(int) - 2
    x1, y1 = np.ceil(rim1.max(axis=0)).astype(int) + 3
    if x0 < 0 or y0 < 0 or x1 > g1.shape[1] or y1 > g1.shape[0]:
        return None
    size = (int(x1 - x0), int(y1 - y0))
    to_crop = np.array([[1.0, 0, x0], [0, 1.0, y0], [0, 0, 1.0]])
    g0_from_crop = h0 @ np.linalg.inv(h1) @ to_crop
    before = cv2.warpPerspective(
        g0.astype(np.float32),
        g0_from_crop,
        size,
        flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )
    after = g1[y0:y1, x0:x1].astype(np.float32)
    mask = np.zeros((size[1], size[0]), np.uint8)
    cv2.fillPoly(mask, [np.round((rim1 - (x0, y0)) * 16).astype(np.int32)], 1, shift=4)
    inside = mask.astype(bool)
    if inside.sum() < 20:
        return None
    m = mask.astype(np.float32)
    weight = np.maximum(cv2.GaussianBlur(m, (0, 0), APPEARANCE_BLUR_PX), 1e-3)

    def smoothed(img):
        return cv2.GaussianBlur(img * m, (0, 0), APPEARANCE_BLUR_PX) / weight

    def gradient(img):
        gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
        gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
        return cv2.dilate(cv2.magnitude(gx, gy), np.ones((3, 3), np.uint8))

    contrast = float(np.percentile(before[inside], 97) - np.percentile(before[inside], 3))
    if contrast <= 0:
        return None
    noise = max(noise0 * contrast, 1.0) * math.sqrt(2.0)
    d_raw = np.abs(after - before)
    s_before = smoothed(before)
    d_smooth = np.abs(smoothed(after) - s_before)
    tol_raw = APPEARANCE_NOISE_K * noise + APPEARANCE_SHIFT_PX * gradient(before)
    tol_smooth = APPEARANCE_NOISE_K * noise * APPEARANCE_NOISE_GAIN
    tol_smooth = tol_smooth + APPEARANCE_SHIFT_PX * gradient(s_before)
    return (
        float(d_raw[inside].max()) / contrast,
        float(d_smooth[inside].max()) / contrast,
        contrast,
        bool((d_raw <= tol_raw)[inside].all()),
        bool((d_smooth <= tol_smooth)[inside].all()),
    )


def _ab(ab: dict, this, other, passes: int = 3) -> None:
    """Append the CPU [ms] of ``this`` and ``other`` on one crop to ``ab``: each the
    least of ``passes`` runs, the two run one after the other in alternating order."""
    best = {"this": math.inf, "other": math.inf}
    for r in range(passes):
        for name in ("this", "other") if r % 2 else ("other", "this"):
            ms, _ = _cpu_ms(this if name == "this" else other)
            best[name] = min(best[name], ms)
    for name, ms in best.items():
        ab[name].append(ms)


def _ab_medians(ab: dict) -> dict:
    if not ab["this"]:
        return {}
    this, other = _med(ab["this"]), _med(ab["other"])
    return {"ab_verify_ms": this, "ab_other_verify_ms": other, "ab_ratio": this / other}


def _load_verify(path: Path):
    """``verify_sign`` of another copy of frontend/verify.py (e.g. an earlier commit's)."""
    spec = importlib.util.spec_from_file_location("verify_other", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["verify_other"] = mod
    spec.loader.exec_module(mod)
    return mod.verify_sign


def _reference_check():
    """(reference verify_sign, field differences) of tests/test_verify_fast.py: the
    verification as it was before it was made cheaper, from the decoder's pieces."""
    path = Path(__file__).resolve().parents[1] / "tests" / "test_verify_fast.py"
    spec = importlib.util.spec_from_file_location("test_verify_fast", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["test_verify_fast"] = mod
    spec.loader.exec_module(mod)
    return mod._reference_verify_sign, mod._differences


def _scene_crop_times(n: int, check=None, other=None) -> dict:
    """The same on crops of scripts/independent_scene.py (mixed conditions)."""
    spec = importlib.util.spec_from_file_location(
        "independent_scene", Path(__file__).with_name("independent_scene.py")
    )
    mod = importlib.util.module_from_spec(spec)
    sys.modules["independent_scene"] = mod
    spec.loader.exec_module(mod)
    rng = np.random.default_rng(BENCH_SEED)
    full, ver = [], []
    ab: dict[str, list[float]] = {"this": [], "other": []}
    outcomes = collections.Counter()
    codes = [c for c in mod.PAPER_CODES if c.count("1") >= 1]
    for k in range(n):
        code = codes[k % len(codes)]
        crop = mod.render_scene_crop(code, mod.scene_settings(rng, "mixed"), rng)
        _, names, src = _CODE_PARTS[code]
        dst = np.array([crop.keypoints_px[nm] for nm in names], np.float32)
        if len(names) >= 4:
            h, _ = cv2.findHomography(src, dst)
        else:
            h = np.vstack([cv2.getAffineTransform(src.astype(np.float32), dst), [0, 0, 1.0]])
        h = np.array([[1.0, 0, 0.5], [0, 1.0, -0.5], [0, 0, 1.0]]) @ h
        ms, _ = _cpu_ms(lambda im=crop.image: decode_roi(im))
        full.append(ms)
        ms, v = _cpu_ms(lambda im=crop.image, h=h, c=code: verify_sign(im, h, c))
        ver.append(ms)
        outcomes[v.outcome.value] += 1
        if check is not None:
            outcomes["check_differ"] += bool(check[1](v, check[0](crop.image, h, code)))
        if other is not None:
            im = crop.image
            _ab(
                ab,
                lambda im=im, h=h, c=code: verify_sign(im, h, c),
                lambda im=im, h=h, c=code: other(im, h, c),
            )
    out = {"full_decode_ms": _med(full), "verify_ms": _med(ver), "crops": n, **outcomes}
    return out | _ab_medians(ab)


def _profile(det, scene, codes, mode: str, top: int) -> None:
    """cProfile of one more pass of ``mode`` (fast, track) over the scene's frames
    (tracking with the plans the timed pass made): the ``top`` lines by
    cumulative and by own time. For track also ``verify_sign`` alone on the
    timed crops: Python-level, numpy and OpenCV calls per verification, and
    its top lines (where a verification's time goes)."""
    calls = []
    for i, f in enumerate(scene["frames"]):
        plan = scene["plans"][i]
        if mode == "track" and plan.predictions:
            calls.append(lambda f=f, p=plan: det.detect_tracked(f, p.predictions, codes, p.refresh))
        elif mode == "fast":
            calls.append(lambda f=f: det.detect(f, codes, "fast"))
    print(f"  profile: {mode} on {len(calls)} frames")
    _print_profile(_profiled(calls), top)
    if mode == "track" and scene["crops"]:
        crops = [lambda c=c: verify_sign(c[0], c[1], c[2], codes) for c in scene["crops"]]
        stats = _profiled(crops)
        per = collections.Counter()
        for (path, _, name), (_, ncalls, *_rest) in stats.stats.items():
            per["calls"] += ncalls
            if "numpy" in path or "numpy" in name:
                per["numpy"] += ncalls
            elif path == "~" and (name[1:-1].isidentifier() or "'cv2." in name):
                per["cv2"] += ncalls  # OpenCV's functions show as <name>, its methods by class
        print(
            f"  profile: verify_sign on {len(crops)} crops, per verification:",
            ", ".join(f"{k} {v / len(crops):.0f}" for k, v in per.items()),
        )
        _print_profile(stats, top)


def _profiled(calls) -> pstats.Stats:
    prof = cProfile.Profile()
    prof.enable()
    for call in calls:
        call()
    prof.disable()
    return pstats.Stats(prof, stream=sys.stdout)


def _print_profile(stats: pstats.Stats, top: int) -> None:
    stats.sort_stats("cumulative").print_stats(top)
    stats.sort_stats("tottime").print_stats(top)


def _med(x) -> float:
    return float(statistics.median(x)) if x else float("nan")


def _ratios(per_frame, passes) -> dict:
    out = {}
    aruco = statistics.median(per_frame["aruco"])
    for m in MODES:
        per_pass = [
            statistics.median(p) / statistics.median(a)
            for p, a in zip(passes[m], passes["aruco"], strict=True)
        ]
        out[m] = {
            "median_ms": statistics.median(per_frame[m]),
            "ratio_to_aruco": statistics.median(per_frame[m]) / aruco,
            "ratio_per_pass_min": min(per_pass),
            "ratio_per_pass_median": statistics.median(per_pass),
        }
    return out


def _print_scene(name: str, res: dict, n: int) -> None:
    print(f"{name}: {n} frames 1920x1080, one thread, CPU per frame (median of per-frame min)")
    for m in MODES:
        r = res["modes"][m]
        print(
            f"  {m:13s} {r['median_ms']:7.1f} ms   / aruco {r['ratio_to_aruco']:5.2f}"
            f"   (per pass: min {r['ratio_per_pass_min']:.2f}, median "
            f"{r['ratio_per_pass_median']:.2f})"
        )
    for m, t in res["found"].items():
        print(
            f"  {m:13s} found {t['found']} (>= 18 px: {t['found_ge18']} of {t['signs']}), "
            f"wrong codes {t['wrong']}, full-frame searches {t['full_frames']}"
        )
        print(
            f"  {'':13s} wall medians: cascade {t['cascade_ms_median']:.1f} ms, verification"
            f" {t['verify_ms_median']:.1f} ms, decoder (verification included)"
            f" {t['decode_ms_median']:.1f} ms, of it crop retries {t['retry_ms_median']:.1f} ms"
            f" (mean {t['retry_ms_mean']:.1f})"
        )
    print(f"  verifications: {res['verifications']}")
    c = res["crops"]
    print(
        f"  per crop ({c['crops']} true signs >= 18 px): full decode {c['full_decode_ms']:.3f} ms,"
        f" verification {c['verify_ms']:.3f} ms"
        f" ({c['verify_ms'] / c['full_decode_ms']:.2f}x)"
    )
    if "check_differ" in c:
        print(f"  verifications differing from the reference: {c['check_differ']} of {c['crops']}")
    if "ab_ratio" in c:
        print(_ab_line(c))
    a = res.get("appearance")
    if a is not None and a["pairs"]:
        print(
            f"  appearance, {a['pairs']} signs verified in consecutive frames (a still sign:"
            f" {a['still_pairs']}), largest change over the disc / contrast, and unchanged"
            f" ({APPEARANCE_NOISE_K:g} noise sigmas + {APPEARANCE_SHIFT_PX:g} px x gradient);"
            f" scale within 3 %: {a['scale_3pct']:.1%}"
        )
        for name in ("flight", "still"):
            if name in a:
                b = a[name]
                print(
                    f"    {name:6s} raw median {b['raw_p50']:.3f}, smoothed {APPEARANCE_BLUR_PX:g}"
                    f" px median {b['smooth_p50']:.3f} (p90 {b['smooth_p90']:.3f}); unchanged"
                    f" raw {b['unchanged_raw']:.1%}, smoothed {b['unchanged_smooth']:.1%}"
                )


def _ab_line(c: dict) -> str:
    return (
        f"  verification per crop, least of 3 interleaved runs: {c['ab_verify_ms']:.3f} ms,"
        f" --ab-verify's {c['ab_other_verify_ms']:.3f} ms ({c['ab_ratio']:.2f}x)"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="8 frames per flight instead of 30")
    ap.add_argument("--frames", type=int, default=None, help="frames timed per flight")
    ap.add_argument("--repeat", type=int, default=3, help="passes over the frames")
    ap.add_argument("--scenes", default="sim,hard", help="flights: sim, hard")
    ap.add_argument("--cascade", type=Path, default=None, help="cascade XML (default: bundled)")
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    ap.add_argument(
        "--check-verify",
        action="store_true",
        help="also run the reference verification of tests/test_verify_fast.py on every"
        " timed crop and count the outcomes or readings that differ (check_differ)",
    )
    ap.add_argument(
        "--ab-verify",
        type=Path,
        default=None,
        help="another copy of frontend/verify.py (e.g. git show REV:frontend/verify.py > v.py):"
        " its verify_sign timed against this one on every crop, interleaved",
    )
    ap.add_argument(
        "--profile",
        choices=("fast", "track"),
        default=None,
        help="after the timing, profile one more pass of this mode (cProfile top lines)",
    )
    ap.add_argument("--profile-top", type=int, default=25, help="lines per --profile table")
    ap.add_argument(
        "--appearance",
        action="store_true",
        help="also measure how much each verified sign's appearance changes between"
        " consecutive frames (the premise of reusing a verification's checks)",
    )
    args = ap.parse_args(argv)
    check = _reference_check() if args.check_verify else None
    other = _load_verify(args.ab_verify) if args.ab_verify else None
    cv2.setNumThreads(1)
    n = args.frames or (8 if args.quick else 30)
    sign_map = load_map(bundled_map_path())
    codes = sign_map.codes
    det = SignDetector(args.cascade)
    aruco = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), cv2.aruco.DetectorParameters()
    )
    results: dict = {"frames": n, "seed": BENCH_SEED, "repeat": args.repeat, "scenes": {}}
    for name in args.scenes.split(","):
        scene = _scene(name, n, sign_map)
        per_frame, passes, tallies, outcomes = _frame_modes(
            det, aruco, scene, sign_map, args.repeat
        )
        res = {
            "modes": _ratios(per_frame, passes),
            "found": {m: dict(t) for m, t in tallies.items()},
            "verifications": dict(outcomes),
            "crops": _crop_times(scene, codes, check, other),
        }
        for t in res["found"].values():
            for k in ("found", "found_ge18", "wrong", "full_frames", "signs"):
                t.setdefault(k, 0)
        if args.appearance:
            res["appearance"] = _appearance(scene, codes)
        results["scenes"][name] = res
        _print_scene(name, res, n)
        if args.profile:
            _profile(det, scene, codes, args.profile, args.profile_top)
    sc = _scene_crop_times(SCENE_CROPS if not args.quick else 20, check, other)
    results["independent_crops"] = sc
    print(
        f"independent_scene crops ({sc['crops']}, mixed): full decode {sc['full_decode_ms']:.3f}"
        f" ms, verification {sc['verify_ms']:.3f} ms"
        f" ({sc['verify_ms'] / sc['full_decode_ms']:.2f}x); outcomes "
        + ", ".join(
            f"{k} {v}" for k, v in sc.items() if k != "crops" and "ms" not in k and "ab_" not in k
        )
    )
    if "ab_ratio" in sc:
        print(_ab_line(sc))
    if "sim" in results["scenes"]:
        results |= _table5_keys(results["scenes"]["sim"])
    if args.json:
        with atomic_write(args.json) as f:
            json.dump(results, f, indent=1)
    return 0


def _table5_keys(sim: dict) -> dict:
    """The simulator flight's numbers under the flat keys scripts/reproduce_paper.py's Table 5
    reads: per mode the median ms per frame, its decoding part (the frame minus the cascade's
    median: medians of parts need not add up) and the share of signs found; ArUco's ms."""
    out: dict = {"aruco": sim["modes"]["aruco"]["median_ms"], "found_fraction": {}}
    for mode in ("fast", "track"):
        total = sim["modes"][mode]["median_ms"]
        found = sim["found"][mode]
        out[mode] = total
        out[f"{mode}_decode"] = max(total - found.get("cascade_ms_median", 0.0), 0.0)
        out["found_fraction"][mode] = found["found"] / max(found["signs"], 1)
    return out


if __name__ == "__main__":
    sys.exit(main())
