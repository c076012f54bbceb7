"""``boxes.jsonl``: per-frame ground truth of a simulated flight (the one reader and writer).

One JSON object per line, one line per frame, in frame order::

    {"frame": 0, "stamp_ns": 0,
     "conditions": {"jpeg_quality": 90, "gain": 1.02, "offset": 0.4,
                    "vibration_px": [0.0, 0.0], "background": "procedural"},
     "signs": [{"code": "0101", "bbox_px": [x, y, w, h], "center_px": [u, v],
                "diameter_px": d, "keypoints_px": {"center": [u, v], ...},
                "occluded": false, "truncated": false, "distance_m": 27.1,
                "covered_slots": [2], "part_cover": {"center": 0.0, ..., "slot4": 0.0},
                "occluders": ["member"], "fade": 0.0, "dirty": false, "glare_dn": 0.0}]}

Pixels are raw (distorted) image pixels with pixel centres at integers.

Per sign:
    ``code``            the sign's code.
    ``bbox_px``         bounding box of the projected disc, clipped to the image.
    ``center_px``       projection of the map centre.
    ``diameter_px``     longest projected diameter of the disc [px].
    ``keypoints_px``    keypoints of ``frontend.sign.sign_keypoints`` (white parts only).
    ``occluded``        something in front (a bar, a member, a conductor) covers part
                        of the face.
    ``truncated``       part of the disc is outside the image.
    ``distance_m``      camera centre to sign centre [m].
    ``covered_slots``   coded slots (1..4, white or black) whose rectangle is covered
                        by at least ``COVERED_FRACTION`` of its area.
    ``part_cover``      fraction of each part's area covered by what is in front:
                        ``center``, ``direction`` and ``slot1``..``slot4`` (all four
                        slots, whatever their bit).
    ``occluders``       kinds of what covers the disc: ``bar`` (an opaque bracket on
                        the face), ``member`` (a lattice member in front), ``conductor``.
    ``fade``            0 = fresh paint; f > 0 pulls black and white toward grey by f.
    ``dirty``           stains on the face.
    ``glare_dn``        peak specular glare added on the face this frame [DN].

Per frame, ``conditions``: the JPEG quality (null = no JPEG), the global
``gain`` and ``offset`` [DN] (``out = gain * in + offset``), the vibration
blur segment [px] added to every motion this frame, and the background
(``procedural``, ``flat`` or ``photo:<name>``).

Files written before these fields existed lack them; the reader fills defaults.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from signpose.core.errors import InputError
from signpose.core.fileio import atomic_write

# A slot counts as covered when this share of its area is hidden: about what
# makes its mean grey level drift half-way between the paint and the occluder.
COVERED_FRACTION = 0.2
PART_NAMES = ("center", "direction", "slot1", "slot2", "slot3", "slot4")
OCCLUDER_KINDS = ("bar", "member", "conductor")


@dataclass(frozen=True)
class SignTruth:
    """Ground truth of one visible sign in one frame (fields: see the module docstring).

    Attributes:
        code: the sign's code.
        bbox_px: (x, y, w, h) bounding box of the projected disc, clipped to the image.
        center_px: (u, v) projection of the map centre.
        diameter_px: longest projected diameter of the disc [px].
        keypoints_px: keypoint name -> (u, v), white parts only.
        occluded: something in front covers part of the face.
        truncated: part of the disc is outside the image.
        distance_m: distance from the camera centre to the sign centre [m].
        covered_slots: coded slots (1..4) covered by >= ``COVERED_FRACTION``.
        part_cover: part name (``PART_NAMES``) -> covered fraction of its area.
        occluders: kinds (``OCCLUDER_KINDS``) of what covers the disc.
        fade: paint fading of the face (0 = none).
        dirty: stains on the face.
        glare_dn: peak specular glare on the face [DN].
    """

    code: str
    bbox_px: tuple[float, float, float, float]
    center_px: tuple[float, float]
    diameter_px: float
    keypoints_px: dict[str, tuple[float, float]]
    occluded: bool
    truncated: bool
    distance_m: float
    covered_slots: tuple[int, ...] = ()
    part_cover: dict[str, float] = field(default_factory=dict)
    occluders: tuple[str, ...] = ()
    fade: float = 0.0
    dirty: bool = False
    glare_dn: float = 0.0

    def to_json(self) -> dict:
        return {
            "code": self.code,
            "bbox_px": [round(v, 3) for v in self.bbox_px],
            "center_px": [round(v, 4) for v in self.center_px],
            "diameter_px": round(self.diameter_px, 3),
            "keypoints_px": {
                k: [round(v[0], 4), round(v[1], 4)] for k, v in self.keypoints_px.items()
            },
            "occluded": self.occluded,
            "truncated": self.truncated,
            "distance_m": round(self.distance_m, 4),
            "covered_slots": list(self.covered_slots),
            "part_cover": {k: round(v, 4) for k, v in self.part_cover.items()},
            "occluders": list(self.occluders),
            "fade": round(self.fade, 4),
            "dirty": self.dirty,
            "glare_dn": round(self.glare_dn, 2),
        }

    @classmethod
    def from_json(cls, d: dict) -> SignTruth:
        return cls(
            code=d["code"],
            bbox_px=tuple(float(v) for v in d["bbox_px"]),
            center_px=tuple(float(v) for v in d["center_px"]),
            diameter_px=float(d["diameter_px"]),
            keypoints_px={k: (float(v[0]), float(v[1])) for k, v in d["keypoints_px"].items()},
            occluded=bool(d["occluded"]),
            truncated=bool(d["truncated"]),
            distance_m=float(d["distance_m"]),
            covered_slots=tuple(int(k) for k in d.get("covered_slots", ())),
            part_cover={k: float(v) for k, v in d.get("part_cover", {}).items()},
            occluders=tuple(d.get("occluders", ())),
            fade=float(d.get("fade", 0.0)),
            dirty=bool(d.get("dirty", False)),
            glare_dn=float(d.get("glare_dn", 0.0)),
        )


@dataclass(frozen=True)
class FrameConditions:
    """The imaging conditions of one frame.

    Attributes:
        jpeg_quality: JPEG round-trip quality, None = none.
        gain, offset: global lighting, ``out = gain * in + offset`` [DN].
        vibration_px: (du, dv) extra blur segment of a vibration burst [px].
        background: ``procedural``, ``flat`` or ``photo:<name>``.
    """

    jpeg_quality: int | None = None
    gain: float = 1.0
    offset: float = 0.0
    vibration_px: tuple[float, float] = (0.0, 0.0)
    background: str = "procedural"

    def to_json(self) -> dict:
        return {
            "jpeg_quality": self.jpeg_quality,
            "gain": round(self.gain, 5),
            "offset": round(self.offset, 4),
            "vibration_px": [round(v, 3) for v in self.vibration_px],
            "background": self.background,
        }

    @classmethod
    def from_json(cls, d: dict) -> FrameConditions:
        q = d.get("jpeg_quality")
        return cls(
            jpeg_quality=None if q is None else int(q),
            gain=float(d.get("gain", 1.0)),
            offset=float(d.get("offset", 0.0)),
            vibration_px=tuple(float(v) for v in d.get("vibration_px", (0.0, 0.0))),
            background=str(d.get("background", "procedural")),
        )


@dataclass(frozen=True)
class FrameTruth:
    """Ground truth of one frame: its index, stamp [ns], conditions and visible signs."""

    frame: int
    stamp_ns: int
    signs: tuple[SignTruth, ...]
    conditions: FrameConditions = FrameConditions()

    def to_json(self) -> dict:
        return {
            "frame": self.frame,
            "stamp_ns": self.stamp_ns,
            "conditions": self.conditions.to_json(),
            "signs": [s.to_json() for s in self.signs],
        }

    @classmethod
    def from_json(cls, d: dict) -> FrameTruth:
        return cls(
            frame=int(d["frame"]),
            stamp_ns=int(d["stamp_ns"]),
            signs=tuple(SignTruth.from_json(s) for s in d["signs"]),
            conditions=FrameConditions.from_json(d.get("conditions", {})),
        )


def boxes_line(truth: FrameTruth) -> str:
    """One ``boxes.jsonl`` line (no newline)."""
    return json.dumps(truth.to_json(), separators=(",", ":"))


def write_boxes(path: str | os.PathLike, frames: Iterable[FrameTruth]) -> Path:
    """Write one line per frame to ``path`` atomically; return the path."""
    target = Path(path)
    with atomic_write(target) as f:
        f.writelines(boxes_line(t) + "\n" for t in frames)
    return target


def read_boxes(path: str | os.PathLike) -> list[dict]:
    """Read ``boxes.jsonl``: one dict per frame, as written (see the module docstring)."""
    p = Path(path)
    try:
        lines = p.read_text(encoding="utf-8").splitlines()
    except OSError as exc:
        raise InputError(f"{p}: cannot read boxes file ({exc})") from None
    out = []
    for i, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            raise InputError(f"{p}: line {i}: not valid JSON") from None
    return out


def read_frame_truths(path: str | os.PathLike) -> list[FrameTruth]:
    """Read ``boxes.jsonl`` into ``FrameTruth`` objects (missing fields get defaults)."""
    p = Path(path)
    try:
        return [FrameTruth.from_json(d) for d in read_boxes(p)]
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"{p}: not a boxes file ({type(exc).__name__}: {exc})") from None
