"""Haar features, Adaboost stumps, cascade training and the OpenCV XML export."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from signpose.training import adaboost, data, features
from signpose.training.cascade_xml import read_cascade_xml, write_cascade_xml
from signpose.training.mining import NegativeMiner, sliding_windows


def _rect_sum(win: np.ndarray, x: int, y: int, w: int, h: int) -> float:
    return float(win[y : y + h, x : x + w].astype(np.float64).sum())


def test_feature_set_has_the_five_shapes_everywhere():
    fs = features.all_features()
    assert len(fs) == 162336
    counts = np.bincount(fs.shapes, minlength=5)
    assert counts.tolist() == [43200, 43200, 27600, 27600, 20736]
    # Every rectangle lies inside the window.
    r = fs.rects
    used = r[:, :, 4] != 0
    assert np.all((r[:, :, 0] + r[:, :, 2])[used] <= 24)
    assert np.all((r[:, :, 1] + r[:, :, 3])[used] <= 24)


def test_matmul_feature_values_equal_direct_rectangle_sums():
    rng = np.random.default_rng(0)
    fs = features.all_features()
    pick = fs.subset(rng.choice(len(fs), 300, replace=False))
    wins = rng.integers(0, 256, (7, 24, 24)).astype(np.uint8)
    got = features.feature_values(wins, features.corner_weights(pick.rects))
    for i, win in enumerate(wins):
        inner = win[1:-1, 1:-1].astype(np.float64)
        nf = np.sqrt(inner.size * (inner**2).sum() - inner.sum() ** 2)
        for j, rects in enumerate(pick.rects):
            raw = sum(wt * _rect_sum(win, *map(int, (x, y, w, h))) for x, y, w, h, wt in rects)
            assert got[i, j] == pytest.approx(raw / nf, rel=1e-5, abs=1e-6)


def test_best_stump_matches_brute_force():
    rng = np.random.default_rng(1)
    vals = rng.normal(size=(5, 40)).astype(np.float32)
    vals[2, :10] = 0.0  # ties
    y = rng.random(40) < 0.4
    w = rng.random(40)
    w /= w.sum()
    vals[4] = 1.0  # a constant feature has no threshold
    signed = np.where(y, w, -w).astype(np.float32)
    block = adaboost.PresortedBlock(vals)
    f, thr, pol, err = block.best(signed, w[y].sum(), w[~y].sum())
    brute = np.inf
    for j in range(4):
        for t in np.unique(vals[j]):
            for p in (1, -1):
                h = vals[j] < t if p == 1 else vals[j] >= t
                brute = min(brute, w[h != y].sum())
    assert err == pytest.approx(brute, abs=1e-6)
    h = vals[f] < thr if pol == 1 else vals[f] >= thr
    assert w[h != y].sum() == pytest.approx(err, abs=1e-6)


@pytest.fixture(scope="module")
def tiny_cascade(tmp_path_factory):
    """A 3-stage cascade trained in seconds on synthetic signs of two codes."""
    rng = np.random.default_rng(5)
    pos = data.render_positives(300, rng, codes=("0101", "1010"))
    images = data.background_images(rng, per_kind=2)
    settings = adaboost.TrainSettings(features_per_stage=600, max_stages=3, max_weak_per_stage=20)
    cascade = adaboost.train_cascade(
        pos, NegativeMiner(images, 2_000_000), 400, settings, rng, features.all_features()
    )
    path = tmp_path_factory.mktemp("cascade") / "tiny.xml"
    write_cascade_xml(path, cascade, "test cascade")
    return cascade, path, pos, images


def test_tiny_cascade_trains_and_opencv_finds_a_trained_sign(tiny_cascade):
    cascade, path, pos, images = tiny_cascade
    assert 1 <= len(cascade.stages) <= 3
    assert cascade.accepts(pos).mean() > 0.95
    clf = cv2.CascadeClassifier(str(path))
    assert not clf.empty()
    # A trained positive, magnified 3x, pasted into a textured background.
    scene = cv2.resize(images[0], (240, 200))
    sign = cv2.resize(pos[0], (72, 72), interpolation=cv2.INTER_LINEAR)
    scene[60:132, 100:172] = sign
    rects = clf.detectMultiScale(scene, 1.1, 0, minSize=(24, 24))
    assert len(rects) > 0
    c = np.asarray(rects)[:, :2] + np.asarray(rects)[:, 2:] / 2
    assert np.min(np.hypot(c[:, 0] - 136, c[:, 1] - 96)) < 10


def test_numpy_and_opencv_cascades_agree_window_by_window(tiny_cascade):
    cascade, path, pos, images = tiny_cascade
    rng = np.random.default_rng(6)
    negs = np.concatenate([sliding_windows(im, 17)[:150] for im in images[:6]])
    wins = np.concatenate([pos[:150], negs])
    ours = cascade.accepts(wins)
    clf = cv2.CascadeClassifier(str(path))
    theirs = np.array(
        [len(clf.detectMultiScale(w, 1.1, 0, minSize=(24, 24), maxSize=(24, 24))) > 0 for w in wins]
    )
    assert ours.sum() > 50 and (~ours).sum() > 50
    # Windows within float rounding of a threshold may differ; allow a handful.
    assert (ours != theirs).sum() <= max(2, len(wins) // 200)
    assert rng is not None


def test_xml_round_trip_keeps_the_cascade(tiny_cascade, tmp_path):
    cascade, path, pos, _ = tiny_cascade
    back = read_cascade_xml(path)
    assert len(back.stages) == len(cascade.stages)
    assert back.n_weak == cascade.n_weak
    np.testing.assert_allclose(back.stage_sums(pos[:50]), cascade.stage_sums(pos[:50]), atol=1e-4)
