"""report.html beside a run's outputs and index.html in a batch folder (issue 16 item 8).

Each page is parsed with html.parser: tags balanced, every link resolves to a
file beside the page, every image embedded as base64 PNG (nothing fetched
from elsewhere, so the folder can be mailed).
"""

from __future__ import annotations

import base64
import json
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import simulate_tiny, truth_detector
from signpose.maps.loader import bundled_map_path, load_map

from signpose import batch, pipeline
from signpose.cli import main
from signpose.io.camera_file import load_camera
from signpose.report_html import (
    INDEX_NAME,
    RUN_REPORT_NAME,
    write_batch_index,
    write_run_report,
)

MAP = str(bundled_map_path())
VOID = {"meta", "img", "br", "hr", "link", "input", "source", "wbr", "col", "area", "base"}
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


class PageParser(HTMLParser):
    """Links, images, text and tag balance of one page."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.links: list[str] = []
        self.images: list[str] = []
        self.tags: list[str] = []
        self.unbalanced: list[str] = []
        self.text: list[str] = []
        self.seen: set[str] = set()

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.seen.add(tag)
        if tag == "a" and "href" in a:
            self.links.append(a["href"])
        if tag == "img":
            self.images.append(a.get("src", ""))
        for key in ("src", "href"):  # nothing fetched from elsewhere
            if tag not in ("a", "img") and key in a:
                self.unbalanced.append(f"<{tag} {key}=...>")
        if tag not in VOID:
            self.tags.append(tag)

    def handle_endtag(self, tag):
        if not self.tags or self.tags[-1] != tag:
            self.unbalanced.append(f"</{tag}> after {self.tags[-3:]}")
        else:
            self.tags.pop()

    def handle_data(self, data):
        self.text.append(data)


def check_page(path: Path) -> PageParser:
    """Parse ``path`` and assert what every page must hold."""
    page = PageParser()
    page.feed(path.read_text(encoding="utf-8"))
    page.close()
    assert page.unbalanced == [] and page.tags == [], (page.unbalanced, page.tags)
    assert "script" not in page.seen  # static: no script at all
    for href in page.links:
        assert "://" not in href and not href.startswith("/"), href  # relative only
        assert (path.parent / href).is_file(), f"{path.name}: broken link {href}"
    for src in page.images:
        assert src.startswith("data:image/png;base64,"), src[:40]
        assert base64.b64decode(src.split(",", 1)[1]).startswith(PNG_MAGIC)
    return page


def _png(path: Path, value: int) -> bytes:
    ok, buf = cv2.imencode(".png", np.full((12, 16, 3), value, np.uint8))
    assert ok
    path.write_bytes(buf.tobytes())
    return buf.tobytes()


def _report() -> dict:
    status = {"ok": 0.8, "weak": 0.1, "bridged": 0.05, "suspect": 0.05}
    return {
        "versions": {"python": "3.11", "signpose": "0.1.0", "gtsam": "4.3"},
        "settings": {"solver": "batch", "smoother": {"huber_k": 2.45}},
        "frames": 20,
        "coverage": {
            "smoothed": {
                "frames": 20,
                "posed": 20,
                "coverage": 1.0,
                "bridged": 1,
                "status": status,
                "weak": [{"frame": 3, "worst_sigma_m": 0.31}],
            }
        },
        "outliers": {
            "rejected": [{"frame": 7, "code": "0101", "test": "innovation", "statistic": 40.1}],
            "n_rejected": {"innovation": 1},
            "unknown_codes": ["<script>alert(1)</script>"],
        },
        "metrics": {
            "groundtruth": "gt.tum",
            "methods": {"smoothed": {"mae_xyz_m": [0.011, 0.012, 0.013], "ate_rmse_m": 0.0212}},
        },
        "pipeline": {"input": "flight/video.mp4", "problems": ["video.mp4: stopped at frame 19"]},
    }


def test_run_report_from_a_run_folder(tmp_path):
    pngs = {
        "views.png": _png(tmp_path / "views.png", 40),
        "extra.png": _png(tmp_path / "extra.png", 90),
    }
    (tmp_path / "report.json").write_text(json.dumps(_report()))
    (tmp_path / "trajectory.csv").write_text("method,frame\n")
    (tmp_path / ".hidden.tmp").write_text("")
    path = write_run_report(tmp_path)
    assert path == tmp_path / RUN_REPORT_NAME
    page = check_page(path)
    embedded = sorted(base64.b64decode(s.split(",", 1)[1]) for s in page.images)
    assert embedded == sorted(pngs.values())  # every PNG, once, byte for byte
    assert sorted(page.links) == ["extra.png", "report.json", "trajectory.csv", "views.png"]
    text = " ".join(page.text)
    for token in ("ok", "weak", "bridged", "suspect", "80.0 %", "innovation", "0.0212", "4.3"):
        assert token in text, token
    assert "<script>alert(1)</script>" in text  # shown as text, not run
    assert "stopped at frame 19" in text


def test_run_report_without_ground_truth_or_plots(tmp_path):
    page = check_page(write_run_report(tmp_path, {}))
    assert page.images == []
    assert "no ground truth given" in " ".join(page.text)


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    root = tmp_path_factory.mktemp("flights")
    return [
        simulate_tiny(root / "a", frames=6),
        simulate_tiny(root / "b", frames=6, seed=1, trajectory="orbit"),
    ]


@pytest.fixture
def replay(flights, monkeypatch):
    by_dir = {str(s.out_dir.resolve()): s for s in flights}
    real_observe = pipeline.observe

    def observe(source, *args, **kw):
        kw["detector"] = truth_detector(by_dir[str(source.path.resolve().parent)])
        return real_observe(source, *args, **kw)

    monkeypatch.setattr(pipeline, "observe", observe)


def test_pipeline_run_writes_report_html(flights, replay, tmp_path):
    sim = flights[0]
    out = tmp_path / "run"
    result = pipeline.run(
        sim.frames_path,
        load_map(MAP),
        out,
        camera=load_camera(sim.camera_path),
        gt_path=sim.groundtruth_path,
        progress=False,
    )
    assert out / RUN_REPORT_NAME in result.files
    page = check_page(out / RUN_REPORT_NAME)
    pngs = sorted(p.read_bytes() for p in out.glob("*.png"))
    assert len(pngs) >= 4
    assert sorted(base64.b64decode(s.split(",", 1)[1]) for s in page.images) == pngs
    assert {"trajectory.csv", "report.json", "result.mcap"} <= set(page.links)
    text = " ".join(page.text)
    assert "smoothed" in text and "Pose statuses" in text and "Metrics against" in text


def test_batch_index_links_every_flight(flights, replay, tmp_path):
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "video.mp4").write_bytes(b"\x00" * 4096)
    inputs = [str(s.frames_path) for s in flights] + [str(bad / "video.mp4")]
    out = tmp_path / "out"
    code = main(["batch", *inputs, "--map", MAP, "--out", str(out), "--no-plots", "-q"])
    assert code == 2  # the bad flight
    page = check_page(out / INDEX_NAME)
    assert sorted(page.links) == sorted(
        ["summary.csv", f"a_video/{RUN_REPORT_NAME}", f"b_video/{RUN_REPORT_NAME}"]
    )
    text = " ".join(page.text)
    assert "bad_video" in text and "failed" in text and "video.mp4" in text  # its reason
    assert "3 flights" in text
    for link in page.links:
        if link.endswith(RUN_REPORT_NAME):
            check_page(out / link)
    # A rerun skips the finished flights and keeps their links.
    assert batch.run_batch(inputs, MAP, out, progress=False, plots=False)[0].skipped
    assert f"a_video/{RUN_REPORT_NAME}" in check_page(write_batch_index(out)).links


@pytest.mark.skipif(shutil.which("chromium") is None, reason="chromium is not installed")
def test_pages_render_in_headless_chromium(tmp_path):
    (tmp_path / "report.json").write_text(json.dumps(_report()))
    _png(tmp_path / "views.png", 40)
    for path in (write_run_report(tmp_path), write_batch_index(tmp_path)):
        proc = subprocess.run(
            ["chromium", "--headless", "--no-sandbox", "--disable-gpu", "--enable-logging=stderr",
             "--dump-dom", path.as_uri()],
            capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
        assert proc.returncode == 0, proc.stderr[-500:]
        assert "</table>" in proc.stdout
        assert "Uncaught" not in proc.stderr and "CONSOLE" not in proc.stderr


def test_a_section_in_an_unknown_form_does_not_stop_the_page(tmp_path, caplog):
    report = _report()
    report["coverage"]["smoothed"]["status"] = ["ok", "weak"]  # a list, not token -> share
    report["metrics"]["methods"] = ["smoothed"]
    page = check_page(write_run_report(tmp_path, report))
    text = " ".join(page.text)
    assert text.count("not shown: report.json has it in a form") == 2
    assert "innovation" in text  # the other sections are there
    assert "section not shown" in caplog.text
