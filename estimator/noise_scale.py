"""The flight's own check of the decoder's keypoint sigmas: an a posteriori noise scale.

The decoder's ``sigma_px`` is calibrated on rendered crops, but a flight can
show what the calibration never saw (another lens, codec, blur direction,
light): its keypoints then scatter more than their sigmas say, and every pose
sigma and chi-square test downstream inherits the optimism. Each posed frame
of the per-frame PnP is such a test: with its keypoints' sigmas right, its
whitened residuals' ``chi2`` follows chi-square with ``dof = 2 n - 6``
degrees of freedom, ``chi2 / dof`` about 1. The scale is the median over
frames of ``chi2 / dof`` over the median of ``chi2_dof / dof`` (Wilson-
Hilferty: ``(1 - 2 / (9 dof))^3``), square-rooted: the photogrammetrists'
a posteriori variance factor, taken robustly (a frame with a wrong code or a
crossed sign does not move the median).

It only ever scales sigmas up (a scale below 1 is taken as 1): a sigma that is
too cautious costs efficiency, one that is too tight sends a user a pose to
bet on that does not hold. On the demo flight (210 frames) the decoder's
sigmas were 1.45x too tight by this measure (PnP ``suspect`` 79 % of frames,
smoothed 41 % at 0.021 / 0.007 m RMSE); with the scale, 19 % and 0 %. (That
measure took the map's 1 cm survey errors for pixel noise: ``chi2_map``
now whitens by both, see ``pixel_noise_scale``.)

Three scales, in the order the estimator applies them:

* ``pixel_noise_scale``: PnP's residuals (``FramePose.chi2_map``), before
  the per-frame statuses and the smoother;
* ``residual_noise_scale``: the smoother's residuals after its first solve
  (the signs estimated with the poses: it sees the pixel noise where a
  surveyed map's error swamps PnP's), on top of the first;
* ``pose_noise_scale``: with the map taken as exact, PnP's scatter about the
  smoothed poses (keypoint errors that mimic a pose change leave no
  residual); it scales the pose covariances, not the pixels.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from signpose.estimator.perframe import FramePose
from signpose.frontend.observations import FrameObservations, SignObservation

# A pose spends six of its residuals' degrees of freedom on itself.
_POSE_DOF = 6
# The quantile of the frames' position-difference chi-squares the pose scale
# matches, and chi-square(3)'s value there.
_POSE_QUANTILE = 0.75
_CHI2_3_AT_QUANTILE = 4.108345
_NORMAL_AT_QUANTILE = 0.674490
# A difference covariance whose smallest eigenvalue is below this share of its
# largest says the smoother is not (much) better than PnP along some axis: skipped.
_MIN_DIFFERENCE_SHARE = 1e-3
# Fewer posed frames than this say too little about the noise: no scale.
MIN_FRAMES = 10


def pixel_noise_scale(poses: Sequence[FramePose], min_frames: int = MIN_FRAMES) -> float:
    """The factor (>= 1) by which the keypoints' sigmas understate their scatter.

    Each frame's ``chi2_map`` whitens its residuals by the pixel noise and
    the map's survey noise together: a surveyed map's own error (1 cm per
    sign is ~0.4 px at 27 m, ten times the decoder's sigmas on a clean
    flight) is not pixel noise. Taken as pixel noise (``chi2`` alone), a
    map with 1 cm survey errors scaled every sigma by 5-13 on rendered
    orbits where the keypoints' own scatter was 1.05-1.15 times their sigma
    (scripts/eval_pose_sigma.py). For an exact map (``exact_map_pose``)
    ``chi2_map`` is ``chi2``.

    Args:
        poses: per-frame PnP poses (``FramePose.chi2_map`` and ``keypoints_used``).
        min_frames: below this many posed frames with residual freedom, 1.0.
    """
    ratios = []
    for p in poses:
        dof = 2 * p.keypoints_used - _POSE_DOF
        if p.world_T_cam is None or dof < 2 or not math.isfinite(p.chi2_map):
            continue
        ratios.append(p.chi2_map / dof / (1.0 - 2.0 / (9.0 * dof)) ** 3)
    if len(ratios) < min_frames:
        return 1.0
    return max(1.0, math.sqrt(float(np.median(ratios))))


def exact_map_pose(p: FramePose) -> FramePose:
    """``p`` for a map taken as exact: no survey share in its covariance or chi-square."""
    return replace(p, cov6=p.cov6_pixel, chi2_map=p.chi2)


def scaled_pose(p: FramePose, scale: float) -> FramePose:
    """``p`` as if its keypoints' sigmas were ``scale`` times larger.

    Only the pixel noise's share of the covariance grows (the survey's is
    the map's, not the decoder's). ``chi2_map`` is divided by ``scale**2``
    like the pixel-only ``chi2``: the scale was measured on it as a factor
    of the whole residual covariance, so that a median frame keeps ratio 1.
    """
    if scale == 1.0 or p.world_T_cam is None:
        return p
    cov6, pixel = p.cov6, p.cov6_pixel
    if pixel is not None:
        cov6 = None if cov6 is None else cov6 + (scale**2 - 1.0) * pixel
        pixel = pixel * scale**2
    elif cov6 is not None:  # no split known: all of it is the pixels'
        cov6 = cov6 * scale**2
    return replace(
        p, cov6=cov6, cov6_pixel=pixel, chi2=p.chi2 / scale**2, chi2_map=p.chi2_map / scale**2
    )


def _scaled_sign(o: SignObservation, scale: float) -> SignObservation:
    kp = {k: (su * scale, sv * scale) for k, (su, sv) in o.keypoint_sigma_px.items()}
    return replace(o, sigma_px=o.sigma_px * scale, keypoint_sigma_px=kp)


def scaled_frames(frames: Sequence[FrameObservations], scale: float) -> Sequence[FrameObservations]:
    """``frames`` with every keypoint sigma ``scale`` times larger (the same object at 1)."""
    if scale == 1.0:
        return frames
    return [
        replace(f, signs=tuple(_scaled_sign(o, scale) for o in f.signs)) if f.signs else f
        for f in frames
    ]


def pose_noise_scale(
    poses: Sequence[FramePose],
    world_T_cam: np.ndarray,
    cov6: np.ndarray | None,
    min_frames: int = MIN_FRAMES,
) -> float:
    """The factor (>= 1) by which the pose sigmas understate the poses' scatter.

    Keypoint errors shared by a frame's keypoints in the pattern a pose
    change makes (all signs read a little to one side) leave no residual:
    ``pixel_noise_scale`` cannot see them, yet they move every pose. What
    they do show is PnP's frame-to-frame scatter about the smoothed
    trajectory: with both models right, PnP minus smoothed has the
    covariance PnP's minus the smoother's (the smoother uses every frame's
    information and more), so ``d^T (C_pnp - C_smoothed)^-1 d`` is
    chi-square with 3 dof per frame. The scale matches the frames' 75th
    percentile to chi-square(3)'s (4.108), square-rooted; never below 1. A
    quantile, so that a quarter of wild frames cannot move it; the 75th, not
    the median, because these errors come in bursts (a fast stretch of the
    flight) whose spread is heavier than Gaussian: on 8 rendered orbits
    (clean and hard, seeds 5-8) with the map fixed, ``ok`` smoothed poses
    beyond 3 sigma on an axis were 30 of 1390 with the median, 15 with the
    75th percentile (Gaussian: 0.8 %, 11), 40 without the scale. Errors
    shared over more frames than the smoother averages stay unseen.

    Only for a map taken as exact: with a survey prior PnP's survey share
    (each frame's own reading of the map's error, up to 0.3 m across the
    view) dominates the difference and says nothing of the pixels.

    Args:
        poses: the per-frame PnP poses (``cov6``: their pixel covariance).
        world_T_cam: (N, 4, 4) the smoothed poses of the same frames.
        cov6: (N, 6, 6) their marginal covariances, or None (then 1.0).
        min_frames: below this many frames to compare, 1.0.
    """
    if cov6 is None:
        return 1.0
    ratios = []
    for i, p in enumerate(poses):
        if p.world_T_cam is None or p.cov6 is None or not np.all(np.isfinite(cov6[i])):
            continue
        r_pnp, r_sm = p.world_T_cam[:3, :3], world_T_cam[i][:3, :3]
        c = r_pnp @ p.cov6[3:, 3:] @ r_pnp.T - r_sm @ cov6[i][3:, 3:] @ r_sm.T
        eig = np.linalg.eigvalsh(0.5 * (c + c.T))
        if not eig[0] > _MIN_DIFFERENCE_SHARE * eig[-1]:
            continue
        d = p.world_T_cam[:3, 3] - world_T_cam[i][:3, 3]
        ratios.append(float(d @ np.linalg.solve(c, d)))
    if len(ratios) < min_frames:
        return 1.0
    return max(1.0, math.sqrt(float(np.quantile(ratios, _POSE_QUANTILE)) / _CHI2_3_AT_QUANTILE))


def inflated_pose(p: FramePose, scale: float) -> FramePose:
    """``p`` with its covariance ``scale**2`` times larger (its residuals' chi-squares kept)."""
    if scale == 1.0 or p.world_T_cam is None:
        return p
    cov6 = None if p.cov6 is None else p.cov6 * scale**2
    pixel = None if p.cov6_pixel is None else p.cov6_pixel * scale**2
    return replace(p, cov6=cov6, cov6_pixel=pixel)


def residual_noise_scale(
    chi2: np.ndarray, frame: np.ndarray, n_frames: int, min_frames: int = MIN_FRAMES
) -> float:
    """``pixel_noise_scale`` on the smoother's residuals: the factor (>= 1) its sigmas miss.

    The smoother estimates the signs with the poses, so its residuals show
    the pixel noise where PnP's show the survey's error too: with a
    surveyed map's 1 cm per sign (~0.4 px at 27 m) against keypoint sigmas
    of 0.03-0.1 px, ``chi2_map`` whitens PnP's residuals mostly by the
    survey and cannot tell whether the pixel sigmas are right (the demo
    flight: 1.45 from the pixel-only chi-square, 1.0 from ``chi2_map``;
    its smoothed poses then failed their residual test on 4.8 % of frames).
    Per frame the whitened squared residuals of its k keypoints with
    2 k - 6 degrees of freedom (the pose's share; the motion prior and the
    signs take a little more, so the scale errs large); by Wilson-Hilferty
    each frame's (chi2 / dof)^(1/3) is normal, and the scale is the one that
    puts the frames' 75th percentile of its standard score at the normal's
    (as ``pose_noise_scale``: robust to a quarter of wild frames, and it
    sees residuals heavier-tailed than Gaussian, which the median would
    pass as scale 1); never below 1.

    Args:
        chi2: (M,) each measurement's squared residual whitened per axis.
        frame: (M,) its frame (0..n_frames-1).
        n_frames: number of frames.
        min_frames: below this many frames with residual freedom, 1.0.
    """
    per = np.bincount(frame, weights=chi2, minlength=n_frames)
    dof = 2 * np.bincount(frame, minlength=n_frames) - _POSE_DOF
    ok = dof >= 2
    if ok.sum() < min_frames:
        return 1.0
    d = dof[ok].astype(float)
    cube = np.cbrt(per[ok] / d)  # Wilson-Hilferty: ~ N(1 - 2 / (9 d), 2 / (9 d)) at scale 1
    mean, sd = 1.0 - 2.0 / (9.0 * d), np.sqrt(2.0 / (9.0 * d))

    def score(scale: float) -> float:  # the frames' 75th percentile standard score
        return float(np.quantile((cube / scale ** (2.0 / 3.0) - mean) / sd, _POSE_QUANTILE))

    if score(1.0) <= _NORMAL_AT_QUANTILE:
        return 1.0
    lo, hi = 1.0, 2.0
    while score(hi) > _NORMAL_AT_QUANTILE:
        lo, hi = hi, 2.0 * hi
    for _ in range(40):  # bisection: the score falls as the scale grows
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if score(mid) > _NORMAL_AT_QUANTILE else (lo, mid)
    return 0.5 * (lo + hi)
