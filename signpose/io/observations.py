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

# Ranges a reader accepts (a number outside is a damaged file, not an observation).
MAX_STAMP_NS = 2**63 - 1  # int64, as every log and container stores time
MAX_IMAGE_SIDE_PX = 100_000
MAX_FRAME_INDEX = 2**53


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


def _finite(value, where: str) -> float:
    """A JSON number as a finite float; ValueError otherwise (bools and strings too)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{where} must be a number")
    x = float(value)  # OverflowError for a huge int: caught by the line reader
    if not math.isfinite(x):
        raise ValueError(f"{where} is not finite")
    return x


def _whole(value, where: str, low: int, high: int) -> int:
    """A JSON whole number in [low, high]; ValueError otherwise."""
    if isinstance(value, float) and math.isfinite(value) and value == int(value):
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ValueError(f"{where} must be a whole number in {low}..{high}")
    return value


def _pair(value, where: str) -> tuple[float, float]:
    if not isinstance(value, list | tuple) or len(value) != 2:
        raise ValueError(f"{where} must be [u, v]")
    return (_finite(value[0], where), _finite(value[1], where))


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
            bbox = tuple(_finite(v, f"sign #{i + 1}: bbox_px") for v in bbox)
        sigma = _finite(s.get("sigma_px", DEFAULT_SIGMA_PX), f"sign #{i + 1}: sigma_px")
        if sigma <= 0:
            raise ValueError(f"sign #{i + 1}: sigma_px must be > 0")
        score = _finite(s.get("score", 1.0), f"sign #{i + 1}: score")
        erased, kp_sigma = _optional_fields(s, i, keypoints)
        signs.append(SignObservation(code, keypoints, bbox, sigma, score, erased, kp_sigma))
    return FrameObservations(
        frame=_whole(d["frame"], "frame", 0, MAX_FRAME_INDEX),
        stamp_ns=_whole(d["stamp_ns"], "stamp_ns", 0, MAX_STAMP_NS),
        image_size=(
            _whole(size[0], "image_size width", 1, MAX_IMAGE_SIDE_PX),
            _whole(size[1], "image_size height", 1, MAX_IMAGE_SIDE_PX),
        ),
        signs=tuple(signs),
    )


def _parse_line(raw: bytes) -> FrameObservations:
    """One line's bytes; ValueError (or one of the errors below) says what is wrong."""
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"byte {exc.start} is not UTF-8 text") from None
    return frame_from_dict(json.loads(text))


def iter_observations(path: str | Path) -> Iterator[FrameObservations]:
    """Yield the frames of an observations file; InputError names the bad line.

    Frames must be in time order with unique stamps (as signpose writes them):
    a stamp that is not after the previous line's is refused with both line
    numbers, never sorted silently.
    """
    p = Path(path)
    try:
        handle = p.open("rb")
    except FileNotFoundError:
        raise InputError(f"{p}: observations file not found") from None
    except IsADirectoryError:
        raise InputError(f"{p}: is a folder; pass the observations file") from None
    except OSError as exc:
        raise InputError(f"{p}: cannot read observations file ({exc.strerror})") from None
    previous: tuple[int, int] | None = None  # (line, stamp_ns)
    with handle:
        for lineno, line in enumerate(handle, start=1):
            if not line.strip():
                continue
            try:
                obs = _parse_line(line)
            except (ValueError, TypeError, OverflowError, RecursionError) as exc:
                msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise InputError(f"{p}: line {lineno}: malformed observation ({msg})") from None
            if previous is not None and obs.stamp_ns <= previous[1]:
                how = "repeats" if obs.stamp_ns == previous[1] else "is before"
                raise InputError(
                    f"{p}: line {lineno}: stamp_ns {obs.stamp_ns} {how} line {previous[0]}'s "
                    f"{previous[1]}; frames must be in time order with unique stamps"
                )
            previous = (lineno, obs.stamp_ns)
            yield obs


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
