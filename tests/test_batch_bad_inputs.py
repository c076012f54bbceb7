"""Issue 16's bad batch: one input missing, one truncated, one camera of another size.

The good flight finishes, summary.csv names each failure with its one-line
reason, index.html lists all four, and the exit code follows the rule (the
worst flight decides; here: bad input, 2).
"""

from __future__ import annotations

import csv
import shutil

import yaml
from conftest import TruthDetector, simulate_tiny
from signpose.maps.loader import bundled_map_path

from signpose import batch, pipeline
from signpose.cli import EXIT_INPUT, main
from signpose.io.boxes import read_boxes
from signpose.report_html import INDEX_NAME


def test_missing_truncated_and_wrong_camera(tmp_path, monkeypatch, capsys):
    site = tmp_path / "site"
    good = simulate_tiny(site / "good", frames=12)
    cut = site / "cut"
    shutil.copytree(good.out_dir, cut)
    video = (cut / "video.mp4").read_bytes()
    (cut / "video.mp4").write_bytes(video[: len(video) // 2])  # the recorder died mid-flight
    other = site / "other_camera"
    shutil.copytree(good.out_dir, other)
    cam = yaml.safe_load((other / "camera.yaml").read_text())
    cam["image_width"], cam["image_height"] = 640, 480
    (other / "camera.yaml").write_text(yaml.safe_dump(cam))
    real_observe = pipeline.observe

    def observe(source, *args, **kw):
        kw["detector"] = TruthDetector(read_boxes(source.path.parent / "boxes.jsonl"))
        return real_observe(source, *args, **kw)

    monkeypatch.setattr(pipeline, "observe", observe)
    names = ("good", "missing", "cut", "other_camera")
    inputs = [str(site / n / "video.mp4") for n in names]
    out = tmp_path / "out"
    argv = ["batch", *inputs, "--map", str(bundled_map_path()), "--out", str(out)]
    code = main([*argv, "--root", str(site), "--no-plots", "-q"])
    assert code == EXIT_INPUT
    with open(out / batch.SUMMARY_NAME, newline="") as f:
        rows = {r["flight"]: r for r in csv.DictReader(f)}
    assert list(rows) == ["good_video", "missing_video", "cut_video", "other_camera_video"]
    assert rows["good_video"]["status"] == "ok" and rows["good_video"]["message"] == ""
    assert rows["missing_video"]["status"] == "failed"
    assert rows["cut_video"]["status"] in ("partial", "failed")
    assert rows["other_camera_video"]["status"] == "failed"
    assert "640x480" in rows["other_camera_video"]["message"]
    for name in ("missing_video", "cut_video", "other_camera_video"):
        message = rows[name]["message"]
        assert message and "\n" not in message and "Traceback" not in message, name
        assert "internal error" not in message, (name, message)
    index = (out / INDEX_NAME).read_text()
    assert all(name in index for name in rows)
    err = capsys.readouterr().err
    assert "missing_video" in err and "Traceback" not in err
