"""Shared test builders. Append only (several developers add to this file)."""

# ---------------------------------------------------------------- sign, maps, camera, simulator
# Builders for tests/test_sign.py, test_maps.py, test_camera.py, test_simulate.py.

from pathlib import Path

import numpy as np
import pytest
import yaml
from signpose.maps.loader import SignMap, bundled_map_path, load_map


@pytest.fixture
def demo_map() -> SignMap:
    """The bundled demo pylon map."""
    return load_map(bundled_map_path())


def valid_map_dict() -> dict:
    """A small valid map as plain data (two oriented signs and one centre-only sign)."""
    return {
        "frame": "test_site",
        "signs": [
            {
                "code": "0101",
                "center_m": [0.0, 0.0, 10.0],
                "normal": [0.0, 1.0, 0.0],
                "up": [0.0, 0.0, 1.0],
                "diameter_m": 0.8,
                "sigma_m": 0.01,
            },
            {
                "code": "1001",
                "center_m": [1.5, 0.1, 12.0],
                "normal": [0.0, 1.0, 0.0],
                "up": [0.5, 0.0, 0.8660254],
                "diameter_m": 0.8,
                "sigma_m": 0.02,
            },
            {"code": "0010", "center_m": [-1.0, 0.0, 11.0], "diameter_m": 0.6, "sigma_m": 0.01},
        ],
    }


def write_yaml(path: Path, data) -> Path:
    """Write ``data`` as YAML to ``path`` and return the path."""
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def clean_sim_options():
    """Render options for geometry checks: no background, noise, blur, lighting or JPEG."""
    from signpose.sim.render import RenderOptions

    return RenderOptions(
        blur=False, noise_sigma=0.0, jpeg_quality=None, background=False, lighting=False
    )


def white_centroid_px(gray: np.ndarray, center_px, radius_px: float, iterations: int = 3):
    """Intensity-weighted centroid (u, v) of the bright blob near ``center_px``.

    Weights are the intensity above the local dark level (the 10th percentile
    of a ring around the window), inside a disc of ``radius_px`` that is
    re-centred on the estimate each iteration.
    """
    img = np.asarray(gray, dtype=float)
    c = np.asarray(center_px, dtype=float)
    for _ in range(iterations):
        r_out = int(np.ceil(radius_px)) + 3
        x0, y0 = int(round(c[0])) - r_out, int(round(c[1])) - r_out
        patch = img[y0 : y0 + 2 * r_out + 1, x0 : x0 + 2 * r_out + 1]
        yy, xx = np.mgrid[y0 : y0 + patch.shape[0], x0 : x0 + patch.shape[1]]
        d = np.hypot(xx - c[0], yy - c[1])
        dark = np.percentile(patch[d <= radius_px], 10)
        w = np.clip(patch - dark, 0, None) * (d <= radius_px)
        c = np.array([(w * xx).sum() / w.sum(), (w * yy).sum() / w.sum()])
    return c


# ---------------------------------------------------------------- estimator
# Builders for tests/test_estimator*.py and test_metrics.py.


def estimator_scene(
    n_frames: int = 40,
    sigma_px: float = 0.0,
    seed: int = 0,
    flat: bool = True,
    wrong_code_rate: float = 0.0,
    false_rate: float = 0.0,
    hfov_deg: float = 60.0,
    duration_s: float = 7.0,
):
    """(sign_map, camera, frames, ground truth, faults): a short paper-like flight.

    The flight lasts ``duration_s`` whatever ``n_frames`` (so speeds stay realistic).

    ``flat`` puts every sign on the best-fit plane of the demo map (the
    paper's planar assumption), so the baseline is exact without noise.
    """
    from signpose.estimator.camera import pinhole_camera

    from signpose.sim.observations import SyntheticSettings, flatten_map, paper_like_frames

    sign_map = load_map(bundled_map_path())
    if flat:
        sign_map = flatten_map(sign_map)
    camera = pinhole_camera(1920, 1080, hfov_deg)
    rng = np.random.default_rng(seed)
    settings = SyntheticSettings(
        sigma_px=sigma_px, wrong_code_rate=wrong_code_rate, false_rate=false_rate
    )
    frames, gt, truth = paper_like_frames(
        sign_map, camera, n_frames, rng, settings, fps=n_frames / duration_s, seed=seed
    )
    return sign_map, camera, frames, gt, truth


# ---------------------------------------------------------------- pipeline, batch, CLI
# Builders for tests/test_pipeline.py, test_batch.py and test_cli_errors.py.


class TruthDetector:
    """A ``frontend.detector.Detector`` that replays ``boxes.jsonl``: frame i's truth.

    The i-th call answers with frame i's true keypoints (signs cut by the
    border left out), so it must be called in frame order. ``interrupt_at``:
    raise KeyboardInterrupt on that call (Ctrl-C in the frame loop).
    """

    def __init__(self, boxes: list[dict], interrupt_at: int | None = None):
        self.boxes = boxes
        self.interrupt_at = interrupt_at
        self.calls: list[str] = []
        self.predictions: list[list] = []

    def _next(self, kind: str, codes):
        from signpose.frontend.detector import DetectionResult, DetectorMode
        from signpose.frontend.observations import SignObservation

        i = len(self.calls)
        if i == self.interrupt_at:
            raise KeyboardInterrupt
        self.calls.append(kind)
        signs = self.boxes[i]["signs"] if i < len(self.boxes) else []
        found = tuple(
            SignObservation(
                s["code"],
                {k: (float(v[0]), float(v[1])) for k, v in s["keypoints_px"].items()},
                tuple(s["bbox_px"]),
            )
            for s in signs
            if not s["truncated"] and (codes is None or s["code"] in codes)
        )
        mode = DetectorMode.TRACK if kind == "track" else DetectorMode.FAST
        return DetectionResult(found, len(found), 0, mode=mode)

    def detect(self, image, codes=None, mode="fast"):
        return self._next("full", codes)

    def detect_tracked(self, image, predictions, codes=None, refresh=False):
        self.predictions.append(list(predictions))
        return self._next("track", codes)


def simulate_tiny(out: Path, frames: int = 16, fmt: str = "mp4", **kw):
    """A small flight (320x240) in front of the bundled pylon."""
    from signpose.sim.flight import SimSettings, simulate

    settings = SimSettings(frames=frames, width=320, height=240, format=fmt, **kw)
    return simulate(load_map(bundled_map_path()), out, settings, progress=False)


def truth_detector(sim, **kw) -> TruthDetector:
    """A TruthDetector replaying the simulated flight ``sim``."""
    from signpose.io.boxes import read_boxes

    return TruthDetector(read_boxes(sim.boxes_path), **kw)
