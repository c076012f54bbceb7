"""The estimator's PnP reuses the tracker's calls only where they had its exact inputs."""

import pickle

import numpy as np
from conftest import estimator_scene
from signpose.estimator import perframe
from signpose.estimator.perframe import SolvedPnP, run_per_frame, solve_frame_pnp


def _tracker_calls(frames, sign_map, camera, skip_prior_at=()):
    """What a tracker posing every frame from the previous pose records."""
    calls, prior = [], None
    for i, f in enumerate(frames):
        p_in = None if i in skip_prior_at else prior
        pose = solve_frame_pnp(f, sign_map, camera, p_in)
        calls.append(SolvedPnP(f, p_in, None, pose, sign_map, camera))
        prior = pose.world_T_cam
    return calls


def _count_solves(monkeypatch):
    count = [0]
    real = perframe.solve_frame_pnp

    def counted(*args, **kw):
        count[0] += 1
        return real(*args, **kw)

    monkeypatch.setattr(perframe, "solve_frame_pnp", counted)
    return count


def test_reused_where_inputs_match_and_bytes_identical(monkeypatch):
    sign_map, camera, frames, _, _ = estimator_scene(n_frames=12, sigma_px=0.4, seed=5)
    fresh = run_per_frame(frames, sign_map, camera, "pnp")
    # Frame 5 was tracked without a prior (the tracker had lost the pose): solved again.
    calls = _tracker_calls(frames, sign_map, camera, skip_prior_at=(5,))
    count = _count_solves(monkeypatch)
    reused = run_per_frame(frames, sign_map, camera, "pnp", solved=calls)
    # Frame 5 and the frames whose prior then differs are solved again (the chain
    # meets the tracker's again once a pose comes out to the same bits).
    again = [i for i in range(12) if reused[i] is not calls[i].pose]
    assert again[0] == 5 and len(again) == count[0] < 7
    assert all(reused[i] is calls[i].pose for i in range(5))
    for a, b in zip(fresh, reused, strict=True):
        assert a.world_T_cam.tobytes() == b.world_T_cam.tobytes()
        assert a.cov6.tobytes() == b.cov6.tobytes() and a.rms_px == b.rms_px


def test_copies_from_another_process_count_other_settings_do_not(monkeypatch):
    sign_map, camera, frames, _, _ = estimator_scene(n_frames=6, sigma_px=0.4, seed=5)
    # What a worker process sends back: the frames and the calls in one pickle.
    frames, calls = pickle.loads(pickle.dumps((frames, _tracker_calls(frames, sign_map, camera))))
    count = _count_solves(monkeypatch)
    run_per_frame(frames, sign_map, camera, "pnp", solved=calls)
    assert count[0] == 0
    settings = perframe.PerFrameSettings(ransac_px=2.0)
    run_per_frame(frames, sign_map, camera, "pnp", settings, solved=calls)
    assert count[0] == 6
    moved = camera.__class__(**{**camera.__dict__, "K": camera.K * np.array([[1.01], [1], [1]])})
    run_per_frame(frames, sign_map, moved, "pnp", solved=calls)
    assert count[0] == 12
