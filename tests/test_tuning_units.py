"""report.json's motion prior names each density's parameter and unit."""

from dataclasses import replace

import pytest
from signpose.estimator.smoother import SmootherSettings
from signpose.estimator.tuning import MotionChoice


@pytest.mark.parametrize(
    ("motion", "position", "unit"),
    [
        ("constant-velocity", "cv_sigma_acc", "m/s^2/sqrt(Hz)"),
        ("random-walk", "rw_sigma_pos", "m/sqrt(s)"),
    ],
)
def test_motion_prior_densities_carry_their_units(motion, position, unit):
    s = replace(SmootherSettings(), motion=motion)
    d = MotionChoice(s, 0.5, 0.2, 2.0, 0.2, ((position, 0.5, 1.0),), 42).to_dict()
    assert d["parameters"]["position"] == position
    assert d["units"]["position"] == d["units"]["default_position"] == unit
    assert d["units"]["rotation"].startswith("rad/")
    assert d["position"] == 0.5 and "settings" not in d
