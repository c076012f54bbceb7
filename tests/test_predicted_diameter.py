"""predict_signs sizes a sign as the lens draws it, not as a pinhole would.

fx * D / z (the pinhole size of a disc parallel to the image) overstates an
equidistant lens's image of a sign 60 deg off the axis about twice: on
scripts/eval_flight.py's fisheye flight, frame 41, sign 1110 was predicted
120.5 px across where it is 73 px, so the tracker's prediction_margin (-0.6
predicted diameters) dropped it and the signs near the image's edge were
never searched in tracked frames.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from signpose.estimator.camera import CameraModel, pixel_from_world_point
from signpose.maps.loader import MapSign, SignMap

from signpose.pipeline import predict_signs

FX_PX = 612.24  # the fisheye flight's camera: 1280x720, 120 deg across
DIAMETER_M = 0.8
RANGE_M = 7.0


def _camera(model: str) -> CameraModel:
    k = np.array([[FX_PX, 0.0, 639.5], [0.0, FX_PX, 359.5], [0.0, 0.0, 1.0]])
    return CameraModel(1280, 720, k, np.zeros(4), model)


def _sign_at(off_axis_deg: float) -> MapSign:
    a = math.radians(off_axis_deg)
    ray = np.array([math.sin(a), 0.0, math.cos(a)])
    return MapSign("1110", RANGE_M * ray, -ray, np.array([0.0, -1.0, 0.0]), DIAMETER_M, 0.01)


def _drawn_diameter_px(camera: CameraModel, sign: MapSign) -> float:
    """The longest chord of the projected rim [px]."""
    t = np.linspace(0.0, 2 * math.pi, 360, endpoint=False)
    r = sign.world_R_sign()
    rim = sign.center_m + 0.5 * DIAMETER_M * (
        np.cos(t)[:, None] * r[:, 0] + np.sin(t)[:, None] * r[:, 1]
    )
    px, _ = pixel_from_world_point(camera, np.eye(4), rim)
    return float(np.max(np.linalg.norm(px[:, None] - px[None], axis=2)))


@pytest.mark.parametrize("off_axis_deg", [0.0, 30.0, 55.0, 62.0])
def test_the_predicted_diameter_is_the_lens_image_of_the_disc(off_axis_deg):
    camera = _camera("equidistant")
    sign = _sign_at(off_axis_deg)
    (p,) = predict_signs(SignMap("world", (sign,)), camera, np.eye(4), ("1110",), 0.5)
    drawn = _drawn_diameter_px(camera, sign)
    assert p.diameter_px == pytest.approx(drawn, rel=0.02)
    if off_axis_deg > 55.0:
        assert camera.fx * DIAMETER_M / sign.center_m[2] > 1.7 * drawn  # the pinhole size


def test_through_a_pinhole_it_is_fx_d_over_z_on_the_axis():
    camera = _camera("plumb_bob")
    sign = _sign_at(0.0)
    (p,) = predict_signs(SignMap("world", (sign,)), camera, np.eye(4), ("1110",), 0.5)
    assert p.diameter_px == pytest.approx(FX_PX * DIAMETER_M / RANGE_M, rel=1e-6)
