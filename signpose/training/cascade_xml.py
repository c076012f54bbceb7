"""OpenCV cascade XML (``opencv_storage/cascade``, BOOST + HAAR): the one reader/writer.

The layout is the one ``opencv_traincascade`` writes and ``cv2.CascadeClassifier``
loads: stump weak classifiers ``internalNodes = "0 -1 featureIdx threshold"``
with ``leafValues = "left right"`` (left when value < threshold), a stage
passes when the sum of its leaves is >= ``stageThreshold``, and ``features``
lists each feature's rectangles ``"x y w h weight"``.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from signpose.core.errors import InputError
from signpose.core.fileio import atomic_write
from signpose.training.cascade import Cascade, Stage, Stump


def _f(x: float) -> str:
    return f"{float(np.float32(x)):.10e}"


def cascade_to_xml(cascade: Cascade, comment: str = "") -> str:
    """The XML text of ``cascade``; ``comment`` goes into a leading XML comment."""
    feats: list[np.ndarray] = []
    feat_index: dict[bytes, int] = {}
    lines = ['<?xml version="1.0"?>']
    if comment:
        lines.append("<!--\n" + comment.replace("--", "- -").rstrip() + "\n-->")
    lines += [
        "<opencv_storage>",
        '<cascade type_id="opencv-cascade-classifier"><stageType>BOOST</stageType>',
        "  <featureType>HAAR</featureType>",
        f"  <height>{cascade.window_px}</height>",
        f"  <width>{cascade.window_px}</width>",
        "  <stageParams>",
        f"    <maxWeakCount>{max((len(s.stumps) for s in cascade.stages), default=0)}"
        "</maxWeakCount></stageParams>",
        "  <featureParams>",
        "    <maxCatCount>0</maxCatCount></featureParams>",
        f"  <stageNum>{len(cascade.stages)}</stageNum>",
        "  <stages>",
    ]
    for stage in cascade.stages:
        lines += [
            "    <_>",
            f"      <maxWeakCount>{len(stage.stumps)}</maxWeakCount>",
            f"      <stageThreshold>{_f(stage.threshold)}</stageThreshold>",
            "      <weakClassifiers>",
        ]
        for st in stage.stumps:
            key = np.asarray(st.rects, np.float32).tobytes()
            if key not in feat_index:
                feat_index[key] = len(feats)
                feats.append(np.asarray(st.rects, np.float32))
            lines += [
                "        <_>",
                f"          <internalNodes>0 -1 {feat_index[key]} {_f(st.threshold)}"
                "</internalNodes>",
                f"          <leafValues>{_f(st.left)} {_f(st.right)}</leafValues></_>",
            ]
        lines.append("      </weakClassifiers></_>")
    lines += ["  </stages>", "  <features>"]
    for rects in feats:
        parts = [
            f"<_>{int(x)} {int(y)} {int(w)} {int(h)} {wt:.1f}</_>"
            for x, y, w, h, wt in rects
            if wt != 0
        ]
        lines.append(f"    <_><rects>{''.join(parts)}</rects><tilted>0</tilted></_>")
    lines += ["  </features>", "</cascade>", "</opencv_storage>", ""]
    return "\n".join(lines)


def write_cascade_xml(path: str | Path, cascade: Cascade, comment: str = "") -> None:
    """Write ``cascade`` to ``path`` atomically."""
    with atomic_write(path) as f:
        f.write(cascade_to_xml(cascade, comment))


def read_cascade_xml(path: str | Path) -> Cascade:
    """Read a stump-based HAAR cascade (as written here) back into a ``Cascade``."""
    p = Path(path)
    try:
        root = ET.parse(p).getroot()
    except (OSError, ET.ParseError) as exc:
        raise InputError(f"{p}: cannot read cascade XML ({exc})") from None
    casc = root.find("cascade")
    if casc is None or (casc.findtext("featureType") or "").strip() != "HAAR":
        raise InputError(f"{p}: not an OpenCV HAAR cascade")
    window = int(casc.findtext("width") or 24)
    features = []
    for fe in casc.find("features") or []:
        rects = np.zeros((3, 5), np.float32)
        for k, r in enumerate(fe.find("rects") or []):
            rects[k] = [float(v) for v in r.text.split()]
        features.append(rects)
    stages = []
    for st in casc.find("stages") or []:
        stumps = []
        for wc in st.find("weakClassifiers") or []:
            nodes = wc.findtext("internalNodes").split()
            leaves = [float(v) for v in wc.findtext("leafValues").split()]
            if len(nodes) != 4 or len(leaves) != 2:
                raise InputError(f"{p}: only stump weak classifiers are supported")
            stumps.append(Stump(features[int(nodes[2])], float(nodes[3]), leaves[0], leaves[1]))
        stages.append(Stage(tuple(stumps), float(st.findtext("stageThreshold"))))
    return Cascade(tuple(stages), window)
