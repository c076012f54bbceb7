"""``signpose train-detector --out FILE --seed S``: train the Haar cascade (paper §2.1)."""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from signpose.cli import add_quiet, count_arg
from signpose.core.errors import InputError, OutputError
from signpose.io.boxes import read_boxes
from signpose.maps.loader import bundled_map_path, load_map
from signpose.sim.flight import SimSettings, simulate
from signpose.training.adaboost import TrainSettings
from signpose.training.cascade_xml import write_cascade_xml
from signpose.training.haar import train_sign_cascade

log = logging.getLogger(__name__)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train-detector",
        help="train the sign detector's Haar cascade and write OpenCV cascade XML",
        description="Train the attentional Haar/Adaboost cascade on synthetic signs and "
        "procedural/bundled background images; write it as OpenCV cascade XML.",
    )
    p.add_argument("--out", required=True, type=Path, help="output .xml")
    p.add_argument("--seed", type=count_arg, default=0, help="random seed (default 0)")
    p.add_argument("--positives", type=int, default=3000, help="positive windows")
    p.add_argument("--negatives", type=int, default=2500, help="negative windows per stage")
    p.add_argument("--features", type=int, default=3000, help="candidate features per stage")
    p.add_argument("--stages", type=int, default=20, help="maximum number of stages")
    p.add_argument("--max-weak", type=int, default=80, help="maximum weak classifiers per stage")
    p.add_argument(
        "--scene-frames",
        type=int,
        default=24,
        help="simulated pylon frames whose sign-free regions add negatives (0 = none)",
    )
    add_quiet(p)
    p.set_defaults(func=run)


def scene_negatives(seed: int, n_frames: int) -> list:
    """Simulated pylon frames (grey, (K, 4) sign boxes) for negative mining.

    Three short flights (far, middle, near) with seeds derived from ``seed``
    (``1_000_000 + 10 * seed + k``), so evaluation seeds stay unseen.
    """
    sign_map = load_map(bundled_map_path())
    out = []
    flights = (("orbit", 55.0), ("climb-hover-depart", 27.0), ("lawnmower", 14.0))
    with tempfile.TemporaryDirectory() as tmp:
        for k, (traj, dist) in enumerate(flights):
            n = max(1, n_frames // len(flights))
            folder = f"{tmp}/f{k}"
            settings = SimSettings(
                frames=n,
                trajectory=traj,
                distance_m=dist,
                seed=1_000_000 + 10 * seed + k,
                format="png",
            )
            simulate(sign_map, folder, settings, progress=False)
            for i, truth in enumerate(read_boxes(f"{folder}/boxes.jsonl")):
                gray = cv2.imread(f"{folder}/frames/{i:06d}.png", cv2.IMREAD_GRAYSCALE)
                boxes = np.array([s["bbox_px"] for s in truth["signs"]], float).reshape(-1, 4)
                # Grow each box so that no window holds a sizeable part of a sign.
                boxes[:, :2] -= 0.1 * boxes[:, 2:]
                boxes[:, 2:] *= 1.2
                out.append((gray, boxes))
    return out


def run(args: argparse.Namespace) -> int:
    if args.out.suffix.lower() != ".xml":
        raise InputError(f"{args.out}: use a .xml file name")
    if not args.out.parent.exists() and str(args.out.parent) not in ("", "."):
        raise OutputError(f"{args.out.parent}: folder does not exist")
    for name in ("positives", "negatives", "features", "stages", "max_weak"):
        if getattr(args, name) < 1:
            raise InputError(f"--{name.replace('_', '-')} must be >= 1")
    if args.scene_frames < 0:
        raise InputError("--scene-frames must be >= 0")
    settings = TrainSettings(
        features_per_stage=args.features, max_stages=args.stages, max_weak_per_stage=args.max_weak
    )
    t0 = time.perf_counter()
    bar = tqdm(total=args.positives, desc="positives", disable=not args.progress, unit="win")
    stages = tqdm(desc="boosting", disable=not args.progress, unit="weak")

    def progress(msg: str) -> None:
        bar.close()  # positives are done once boosting reports
        if msg.startswith("weak"):
            stages.update(1)
            stages.set_postfix_str(msg)
        else:
            log.info(msg)
            if not args.quiet:
                tqdm.write(msg)

    scenes = scene_negatives(args.seed, args.scene_frames) if args.scene_frames else []
    cascade = train_sign_cascade(
        args.seed,
        args.positives,
        args.negatives,
        settings,
        progress,
        pos_progress=bar.update,
        scene_negatives=scenes,
        on_stage=lambda c: write_cascade_xml(args.out, c, "partial: training in progress"),
    )
    bar.close()
    stages.close()
    minutes = (time.perf_counter() - t0) / 60
    cmd = (
        f"signpose train-detector --out {args.out.name} --seed {args.seed} "
        f"--positives {args.positives} --negatives {args.negatives} "
        f"--features {args.features} --stages {args.stages} --max-weak {args.max_weak} "
        f"--scene-frames {args.scene_frames}"
    )
    # XML comments cannot hold "--": the options are spelled out without dashes.
    options = cmd.split(" ", 2)[2].replace("--", "").split(" --")
    comment = (
        "signpose sign detector: Haar/Adaboost attentional cascade (paper 2.1), 24x24 window.\n"
        "Rebuild with `signpose train-detector` and the options (each with two leading\n"
        f"dashes): {' '.join(options)}\n"
        "(OPENBLAS_NUM_THREADS=1; see signs_cascade.md beside the bundled model).\n"
        f"Trained in {minutes:.1f} min: {len(cascade.stages)} stages, "
        f"{cascade.n_weak} weak classifiers."
    )
    write_cascade_xml(args.out, cascade, comment)
    print(
        f"wrote {args.out}: {len(cascade.stages)} stages, {cascade.n_weak} weak, {minutes:.1f} min"
    )
    return 0
