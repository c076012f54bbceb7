"""detector tracking: a predicted sign the cascade misses is decoded on its predicted box.

On scripts/eval_flight.py's flights (a real lens, JPEG, vibration) the cascade
fires on some signs neither in the tracked region nor in the full-frame search,
though the decoder reads them where the pose predicts them. Here the cascade is
kept from firing in the tracked region by its window range (``track_scale``
larger than the region), so what finds the sign without a full-frame search is
the decode of the predicted box alone.
"""

import cv2
import numpy as np
from signpose.frontend import detector
from signpose.frontend.decoder import _CODE_PARTS, DecodeReason
from signpose.frontend.detector import DetectorSettings, PredictedSign, SignDetector
from signpose.frontend.verify import VerifyOutcome

from signpose.sim.crops import render_crop

SIGN_PX = 60.0
# Windows of 3-3.5 predicted diameters do not fit the tracked region (1.8 + 8 px).
NO_TRACKED_WINDOWS = DetectorSettings(track_scale=(3.0, 3.5))


def _frame(rng, codes=("1011", "0110"), width=600):
    """Signs rendered side by side, and each one's true (centre, homography)."""
    img = np.full((240, width), 150, np.uint8)
    truth = {}
    for (x0, y0), code in zip(((20, 40), (width - 120, 60)), codes, strict=False):
        crop = render_crop(code, rng, sign_px=SIGN_PX, background="plain", noise_sigma=1.0)
        hh, ww = crop.image.shape
        img[y0 : y0 + hh, x0 : x0 + ww] = crop.image
        _, names, src = _CODE_PARTS[code]
        dst = np.array([crop.keypoints_px[n] for n in names], np.float32) + (x0, y0)
        h, _ = cv2.findHomography(src, dst)
        centre = tuple(float(c) for c in cv2.perspectiveTransform(np.zeros((1, 1, 2)), h)[0, 0])
        truth[code] = (centre, h)
    return img, truth


def _turned(h: np.ndarray, deg: float) -> np.ndarray:
    """``h`` with the sign plane turned by ``deg`` about its centre (the slots then
    read another code: the verification fails)."""
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return h @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _moved(h: np.ndarray, du: float) -> np.ndarray:
    return np.array([[1.0, 0.0, du], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]) @ h


def test_a_sign_whose_verification_fails_and_the_cascade_misses_is_read_on_its_box():
    img, truth = _frame(np.random.default_rng(3))
    det = SignDetector(settings=NO_TRACKED_WINDOWS)
    (c_a, h_a), (c_b, h_b) = truth["1011"], truth["0110"]
    preds = [
        PredictedSign("1011", c_a, SIGN_PX, h_a),
        PredictedSign("0110", c_b, SIGN_PX, _turned(h_b, 90)),
    ]
    res = det.detect_tracked(img, preds, refresh=True)
    assert res.verifications[0] is VerifyOutcome.VERIFIED
    assert res.verifications[1] is not VerifyOutcome.VERIFIED
    # Found without the full-frame search (the old tracker fell back here).
    assert not res.fell_back
    got = {d.code: d for d in res.detections}
    assert sorted(got) == ["0110", "1011"]
    assert np.hypot(*np.subtract(got["0110"].center_px, c_b)) < 0.5  # [px]
    # Turned off, the same frame needs the full-frame search.
    off = SignDetector(
        settings=DetectorSettings(track_scale=(3.0, 3.5), track_decode_predicted=False)
    )
    assert off.detect_tracked(img, preds, refresh=True).fell_back


def test_a_predicted_code_is_never_taken_for_another_sign_read_there():
    """A prediction of code X where sign Y is: the decoder reads Y, which is not X."""
    img, truth = _frame(np.random.default_rng(4))
    det = SignDetector(settings=NO_TRACKED_WINDOWS)
    (c_a, h_a), (c_b, _) = truth["1011"], truth["0110"]
    preds = [PredictedSign("1011", c_a, SIGN_PX, h_a), PredictedSign("1110", c_b, SIGN_PX)]
    res = det.detect_tracked(img, preds)
    assert "1110" not in {d.code for d in res.detections}
    # Nor a sign in empty background.
    empty = PredictedSign("1110", (300.0, 120.0), SIGN_PX)
    res = det.detect_tracked(img, [PredictedSign("1011", c_a, SIGN_PX, h_a), empty])
    assert "1110" not in {d.code for d in res.detections}


def test_the_predicted_box_moves_with_the_offset_of_the_signs_found():
    """Every prediction of a frame off by the same shift (the camera's turn since
    the predicted pose): the box of a sign left to the decoder is moved by the
    offset of the nearest sign found, where the decoder reads it; unmoved, the
    box cuts its rim and the decoder refuses it (the box misses the sign's
    centre, so the decoder's second crop around its disc is not made)."""
    img, truth = _frame(np.random.default_rng(5))
    det = SignDetector(settings=NO_TRACKED_WINDOWS)
    shift = 0.6 * SIGN_PX
    (c_a, _), (c_b, _) = truth["1011"], truth["0110"]
    preds = [
        PredictedSign("1011", (c_a[0] + shift, c_a[1]), SIGN_PX),
        PredictedSign("0110", (c_b[0] + shift, c_b[1]), SIGN_PX),
    ]
    found_a = [d for d in det.detect(img).detections if d.code == "1011"]
    assert len(found_a) == 1
    read = det._read_at_predictions(img, preds, found_a, None)
    assert [d.code for d in read] == ["0110"]
    assert np.hypot(*np.subtract(read[0].center_px, c_b)) < 0.5  # [px]
    assert det._read_at_predictions(img, preds, [], None) == []


def test_a_sign_the_decoder_found_occluded_there_is_not_decoded_again(monkeypatch):
    """A searched region centred on the prediction that the decoder refused as
    occluded is its verdict on that sign: no second decode on the predicted box
    (on bench_frontend's hard flight that skipped 38 of 70 such decodes)."""
    img, truth = _frame(np.random.default_rng(6))
    det = SignDetector(settings=NO_TRACKED_WINDOWS)
    (c_b, _) = truth["0110"]
    pred = [PredictedSign("0110", c_b, SIGN_PX)]
    box = (c_b[0] - 30.0, c_b[1] - 30.0, 60.0, 60.0)
    calls = []
    real = detector.decode_region
    monkeypatch.setattr(detector, "decode_region", lambda *a: calls.append(a[1]) or real(*a))
    assert det._read_at_predictions(img, pred, [], None, [(box, DecodeReason.OCCLUDED)]) == []
    assert calls == []
    # Refused for its crop (the rim cut), the predicted box is still tried, and reads.
    read = det._read_at_predictions(img, pred, [], None, [(box, DecodeReason.CUT_BY_EDGE)])
    assert [d.code for d in read] == ["0110"] and len(calls) == 1
