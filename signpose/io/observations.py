"""observations.jsonl: the one module that reads and writes it.

One JSON object per line, one line per frame (the dataclasses and field meanings
are ``signpose.frontend.observations``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO

from signpose.core.errors import InputError
from signpose.core.fileio import atomic_write
from signpose.frontend.observations import DEFAULT_SIGMA_PX, FrameObservations, SignObservation
from signpose.frontend.sign import ALL_CODES, KEYPOINT_NAMES


def _num(x) -> float:
    return round(float(x), 4)


def frame_to_dict(obs: FrameObservations) -> dict:
    signs = []
    for s in obs.signs:
        d: dict = {
            "code": s.code,
            "keypoints_px": {k: [_num(v[0]), _num(v[1])] for k, v in s.keypoints_px.items()},
        }
        if s.bbox_px is not None:
            d["bbox_px"] = [_num(v) for v in s.bbox_px]
        d["sigma_px"] = _num(s.sigma_px)
        d["score"] = _num(s.score)
        # Optional fields (issue 11), left out when empty so older files and
        # writers stay byte-identical.
        if s.erased_slots:
            d["erased_slots"] = [int(k) for k in s.erased_slots]
        if s.keypoint_sigma_px:
            d["keypoint_sigma_px"] = {
                k: [_num(v[0]), _num(v[1])] for k, v in s.keypoint_sigma_px.items()
            }
        signs.append(d)
    return {
        "frame": int(obs.frame),
        "stamp_ns": int(obs.stamp_ns),
        "image_size": [int(obs.image_size[0]), int(obs.image_size[1])],
        "signs": signs,
    }


def frame_to_json(obs: FrameObservations) -> str:
    """One JSON line (no newline) for ``obs``."""
    return json.dumps(frame_to_dict(obs), separators=(", ", ": "))


def _pair(value, where: str) -> tuple[float, float]:
    if not isinstance(value, list | tuple) or len(value) != 2:
        raise ValueError(f"{where} must be [u, v]")
    u, v = float(value[0]), float(value[1])
    if not (math.isfinite(u) and math.isfinite(v)):
        raise ValueError(f"{where} is not finite")
    return (u, v)


def _optional_fields(
    s: dict, i: int, keypoints: dict
) -> tuple[tuple[int, ...], dict[str, tuple[float, float]]]:
    """``erased_slots`` and ``keypoint_sigma_px`` of sign ``i`` (both may be absent)."""
    erased = s.get("erased_slots", [])
    if not isinstance(erased, list) or any(k not in (1, 2, 3, 4) for k in erased):
        raise ValueError(f"sign #{i + 1}: erased_slots must be a list of slots 1..4")
    sig = s.get("keypoint_sigma_px", {})
    if not isinstance(sig, dict):
        raise ValueError(f"sign #{i + 1}: keypoint_sigma_px must be an object")
    kp_sigma = {}
    for name, value in sig.items():
        if name not in keypoints:
            raise ValueError(f"sign #{i + 1}: keypoint_sigma_px.{name} has no keypoint")
        su, sv = _pair(value, f"sign #{i + 1}: keypoint_sigma_px.{name}")
        if su <= 0 or sv <= 0:
            raise ValueError(f"sign #{i + 1}: keypoint_sigma_px.{name} must be > 0")
        kp_sigma[name] = (su, sv)
    return tuple(int(k) for k in erased), kp_sigma


def frame_from_dict(d: dict) -> FrameObservations:
    """Parse one line's object; raises ValueError with what is wrong."""
    if not isinstance(d, dict):
        raise ValueError("line is not a JSON object")
    for key in ("frame", "stamp_ns", "image_size", "signs"):
        if key not in d:
            raise ValueError(f"missing field '{key}'")
    size = d["image_size"]
    if not isinstance(size, list) or len(size) != 2:
        raise ValueError("image_size must be [width, height]")
    if not isinstance(d["signs"], list):
        raise ValueError("signs must be a list")
    signs = []
    for i, s in enumerate(d["signs"]):
        if not isinstance(s, dict):
            raise ValueError(f"sign #{i + 1} is not an object")
        code = s.get("code")
        if code not in ALL_CODES:
            raise ValueError(f"sign #{i + 1}: code must be '0000'..'1111', got {code!r}")
        kps = s.get("keypoints_px")
        if not isinstance(kps, dict) or "center" not in kps:
            raise ValueError(f"sign #{i + 1}: keypoints_px.center is required")
        keypoints = {}
        for name, value in kps.items():
            if name not in KEYPOINT_NAMES:
                raise ValueError(f"sign #{i + 1}: unknown keypoint '{name}'")
            keypoints[name] = _pair(value, f"sign #{i + 1}: keypoints_px.{name}")
        bbox = s.get("bbox_px")
        if bbox is not None:
            if not isinstance(bbox, list) or len(bbox) != 4:
                raise ValueError(f"sign #{i + 1}: bbox_px must be [x, y, w, h]")
            bbox = tuple(float(v) for v in bbox)
        sigma = float(s.get("sigma_px", DEFAULT_SIGMA_PX))
        if not math.isfinite(sigma) or sigma <= 0:
            raise ValueError(f"sign #{i + 1}: sigma_px must be > 0")
        score = float(s.get("score", 1.0))
        erased, kp_sigma = _optional_fields(s, i, keypoints)
        signs.append(SignObservation(code, keypoints, bbox, sigma, score, erased, kp_sigma))
    return FrameObservations(
        frame=int(d["frame"]),
        stamp_ns=int(d["stamp_ns"]),
        image_size=(int(size[0]), int(size[1])),
        signs=tuple(signs),
    )


def iter_observations(path: str | Path) -> Iterator[FrameObservations]:
    """Yield the frames of an observations file; InputError names the bad line."""
    p = Path(path)
    try:
        handle = p.open(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{p}: observations file not found") from None
    except OSError as exc:
        raise InputError(f"{p}: cannot read observations file ({exc.strerror})") from None
    with handle:
        for lineno, line in enumerate(handle, start=1):
            if not line.strip():
                continue
            try:
                yield frame_from_dict(json.loads(line))
            except (ValueError, TypeError) as exc:
                msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise InputError(f"{p}: line {lineno}: malformed observation ({msg})") from None


def read_observations(path: str | Path) -> list[FrameObservations]:
    """All frames of an observations file, in file order."""
    frames = list(iter_observations(path))
    if not frames:
        raise InputError(f"{path}: observations file is empty")
    return frames


def write_observations(path: str | Path, frames: Iterable[FrameObservations]) -> None:
    """Write all ``frames`` atomically."""
    with atomic_write(path) as f:
        for obs in frames:
            f.write(frame_to_json(obs) + "\n")


def append_observation(handle: IO[str], obs: FrameObservations) -> None:
    """Append one frame to an open stream (for streaming writers that flush as they go)."""
    handle.write(frame_to_json(obs) + "\n")
