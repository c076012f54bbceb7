#!/usr/bin/env python
"""Does ``--principal-sigma``'s share match what a principal point error does to the poses?

``estimator.intrinsics_share`` adds a principal point sigma to the position
sigmas through the pose fit's first-order response to a one-pixel shift of
every keypoint (``principal_point_response``). This script checks that answer
on paper-like flights (``sim.observations.paper_like_frames``: the bundled
pylon flattened onto its plane, a 1920x1080 pinhole, 27 m from the face,
clean keypoints unless ``--sigma-px``): it estimates each flight with the
correct camera and with the principal point ``--shift-px`` off in u, then in
v, and prints per method, over the frames posed by both:

* ``fit``: |actual position change| / |first-order response x shift|
  (1: the share is exact to first order);
* ``c/f*depth``: |actual position change| / (shift / f x the depth of the
  frame's signs' centroid), the simpler picture of a camera moved across its
  view: it overstates the change when the fit absorbs part of it as a
  rotation;
* with the principal point ``--fault-px`` off in u: the ``ok`` poses beyond
  3 sigma on some axis without the option and with ``--principal-sigma`` set
  to the fault;
* the share's cost: CPU per pose of ``with_principal_share`` (best of 3).

The estimator runs with the map taken as exact (``--map-fixed``), so that the
pixel noise and the principal point are the only errors.

    .venv/bin/python scripts/eval_principal_share.py [--seeds 5 6] [--frames 30]
        [--shift-px 5] [--fault-px 15] [--sigma-px 0.2]
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace

import numpy as np
from signpose.estimator.camera import CameraModel, pinhole_camera
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.intrinsics_share import (
    principal_point_response,
    scene_to_camera_m,
    with_principal_share,
)
from signpose.estimator.smoother import FIXED
from signpose.estimator.status import PoseStatus
from signpose.maps.loader import bundled_map_path, load_map

from signpose.sim.observations import SyntheticSettings, flatten_map, paper_like_frames

METHODS = ("pnp", "smoothed")
DURATION_S = 7.0  # as tests/conftest.estimator_scene: realistic speeds whatever the frames


def shifted(camera: CameraModel, du_px: float, dv_px: float) -> CameraModel:
    """``camera`` with its principal point moved by (du, dv) [px]."""
    K = np.array(camera.K, float)
    K[0, 2] += du_px
    K[1, 2] += dv_px
    return replace(camera, K=K)


def scene(seed: int, frames: int, sigma_px: float):
    """(sign_map, camera, frames, ground truth) of one paper-like flight."""
    sign_map = flatten_map(load_map(bundled_map_path()))
    camera = pinhole_camera(1920, 1080, 60.0)
    obs, gt, _ = paper_like_frames(
        sign_map,
        camera,
        frames,
        np.random.default_rng(seed),
        SyntheticSettings(sigma_px=sigma_px),
        fps=frames / DURATION_S,
        seed=seed,
    )
    return sign_map, camera, obs, gt


def settings(principal_sigma_px: float = 0.0) -> EstimatorSettings:
    s = replace(EstimatorSettings(), methods=METHODS, principal_sigma_px=principal_sigma_px)
    return replace(s, smoother=replace(s.smoother, landmarks=FIXED))


def ratios(seed: int, frames: int, sigma_px: float, shift_px: float) -> dict[str, dict]:
    """Per method: actual / first-order and actual / (c/f * depth), per frame and axis shift."""
    sign_map, camera, obs, _ = scene(seed, frames, sigma_px)
    right = estimate_trajectories(obs, sign_map, camera, settings(), False)
    out: dict[str, dict] = {m: {"fit": [], "depth": []} for m in METHODS}
    for axis in (0, 1):
        wrong = shifted(camera, shift_px * (axis == 0), shift_px * (axis == 1))
        moved = estimate_trajectories(obs, sign_map, wrong, settings(), False)
        f_px = camera.fx if axis == 0 else camera.fy
        for m in METHODS:
            a, b = right.methods[m], moved.methods[m]
            d = scene_to_camera_m(obs, sign_map, a.world_T_cam)
            for i in np.flatnonzero(a.valid & b.valid & np.all(np.isfinite(d), axis=1)):
                change = np.linalg.norm(b.world_T_cam[i, :3, 3] - a.world_T_cam[i, :3, 3])
                response = principal_point_response(obs[i], sign_map, camera, a.world_T_cam[i])
                if response is None:
                    continue
                depth = abs(a.world_T_cam[i, :3, 2] @ d[i])
                out[m]["fit"].append(change / (shift_px * np.linalg.norm(response[axis])))
                out[m]["depth"].append(change / (shift_px / f_px * depth))
    return out


def beyond_3_sigma(seed: int, frames: int, sigma_px: float, fault_px: float) -> dict[str, tuple]:
    """Per method: (ok beyond 3 sigma, ok) without and with ``--principal-sigma fault_px``."""
    sign_map, camera, obs, gt = scene(seed, frames, sigma_px)
    wrong = shifted(camera, fault_px, 0.0)
    out = {}
    for m in METHODS:
        row = []
        for stated in (0.0, fault_px):
            est = estimate_trajectories(obs, sign_map, wrong, settings(stated), False).methods[m]
            ok = np.array([st is PoseStatus.OK for st in est.status])
            z = np.abs(est.world_T_cam[:, :3, 3] - gt.world_t_cam) / est.sigma_xyz
            row += [int(np.sum(ok & (np.max(z, axis=1) > 3))), int(ok.sum())]
        out[m] = tuple(row)
    return out


def share_cpu_ms(seed: int, frames: int, sigma_px: float) -> tuple[float, int]:
    """(CPU per pose [ms] of ``with_principal_share`` on the smoothed poses, best of 3; poses)."""
    sign_map, camera, obs, _ = scene(seed, frames, sigma_px)
    m = estimate_trajectories(obs, sign_map, camera, settings(), False).methods["smoothed"]
    best = np.inf
    for _ in range(3):
        t0 = time.process_time()
        with_principal_share(m, obs, sign_map, camera, 1.0, weak_sigma_m=np.inf)
        best = min(best, time.process_time() - t0)
    return 1000 * best / len(obs), len(obs)


def _percentiles(values: list[float]) -> str:
    if not values:
        return "-"
    p10, p50, p90 = np.percentile(values, [10, 50, 90])
    return f"{p10:.3f} / {p50:.3f} / {p90:.3f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[5, 6])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--shift-px", type=float, default=5.0, help="shift for the ratios [px]")
    ap.add_argument("--fault-px", type=float, default=15.0, help="fault for the 3 sigma rows")
    ap.add_argument("--sigma-px", type=float, default=0.2, help="keypoint noise [px]")
    args = ap.parse_args(argv)
    print(
        f"position change from a {args.shift_px:g} px principal point shift, "
        "actual / predicted, p10 / median / p90 over frames and the u and v shifts"
    )
    print(f"{'seed':>4}  {'method':<9}{'fit (first order)':<26}c/f*depth")
    for seed in args.seeds:
        for m, r in ratios(seed, args.frames, args.sigma_px, args.shift_px).items():
            print(f"{seed:>4}  {m:<9}{_percentiles(r['fit']):<26}{_percentiles(r['depth'])}")
    print(
        f"\nprincipal point {args.fault_px:g} px off in u: ok poses beyond 3 sigma, "
        f"without / with --principal-sigma {args.fault_px:g}"
    )
    for seed in args.seeds:
        for m, (b0, n0, b1, n1) in beyond_3_sigma(
            seed, args.frames, args.sigma_px, args.fault_px
        ).items():
            print(f"{seed:>4}  {m:<9}{b0} of {n0} ok  /  {b1} of {n1} ok")
    ms, n = share_cpu_ms(args.seeds[0], args.frames, args.sigma_px)
    print(f"\nwith_principal_share: {ms:.2f} ms CPU per pose ({n} smoothed poses, best of 3)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
