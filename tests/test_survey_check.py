"""A sign the flight moves far from its survey: the poses that see it are suspect
(refine.survey_checked), and the correct map leaves every status as it was."""

from dataclasses import replace

import numpy as np
import pytest
from conftest import estimator_scene
from signpose.estimator.estimate import EstimatorSettings, estimate_trajectories
from signpose.estimator.refine import SUSPECT_MOVED_SIGMAS, refine_flight, survey_checked
from signpose.estimator.status import PoseStatus


@pytest.fixture(scope="module")
def scene():
    sign_map, camera, frames, _, _ = estimator_scene(n_frames=30, sigma_px=0.2, seed=3)
    return sign_map, camera, frames


def _checked(sign_map, camera, frames):
    s = replace(EstimatorSettings(), methods=("pnp", "smoothed"))
    result = estimate_trajectories(frames, sign_map, camera, s, False)
    refined = refine_flight(frames, sign_map, camera, result)
    return result, refined, survey_checked(result, refined, frames)


def test_the_correct_map_changes_nothing(scene):
    result, refined, checked = _checked(*scene)
    assert max(s.moved_sigmas for s in refined.signs) < SUSPECT_MOVED_SIGMAS
    assert checked is result


def test_a_sign_surveyed_off_makes_its_frames_suspect(scene):
    sign_map, camera, frames = scene
    seen = [o.code for f in frames for o in f.signs]
    code = max(set(seen), key=seen.count)
    signs = tuple(
        replace(s, center_m=s.center_m + np.array([0.2, 0.0, 0.0])) if s.code == code else s
        for s in sign_map.signs
    )
    result, refined, checked = _checked(replace(sign_map, signs=signs), camera, frames)
    assert refined.sign_map.sign(code) is not None
    assert len(checked.warnings) == len(result.warnings) + 1
    assert code in checked.warnings[-1] and "suspect" in checked.warnings[-1]
    sees = [any(o.code == code for o in f.signs) for f in frames]
    for name, m in checked.methods.items():
        before = result.methods[name].status
        for st, old, seen in zip(m.status, before, sees, strict=True):
            if seen and old in (PoseStatus.OK, PoseStatus.WEAK):
                assert st is PoseStatus.SUSPECT
            elif not seen:
                assert st is old
    assert any(st is PoseStatus.OK for st in result.methods["smoothed"].status)
