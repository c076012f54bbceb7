"""scripts/reproduce_paper.py: the quick reproduction end to end, and its failure handling."""

from __future__ import annotations

import importlib.util
import math
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SCRIPT = REPO / "scripts" / "reproduce_paper.py"
HEADINGS = ("## Table 1", "## Table 2", "## Table 3", "## Table 4", "## Table 5", "## Fig. 13")


def _module():
    spec = importlib.util.spec_from_file_location("reproduce_paper", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up while the file runs
    spec.loader.exec_module(mod)
    return mod


def _summary_value(text: str, what: str) -> str:
    """The 'Measured' cell of the summary row whose 'What' cell starts with ``what``."""
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 5 and cells[1].startswith(what):
            return cells[3]
    raise AssertionError(f"no summary row {what!r}")


@pytest.fixture(scope="module")
def quick_report(tmp_path_factory):
    """Run ``reproduce_paper.py --quick`` once into a temporary folder."""
    root = tmp_path_factory.mktemp("reproduce")
    out = root / "results.md"
    committed = REPO / "docs" / "results.md"
    before = committed.stat().st_mtime_ns if committed.exists() else None
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--quick", "--out", str(out), "--work", str(root / "work")],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    after = committed.stat().st_mtime_ns if committed.exists() else None
    return root, out, proc, (before, after)


def test_quick_reproduction_writes_every_table(quick_report):
    root, out, proc, (before, after) = quick_report
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert before == after, "the quick run must not touch the committed docs/results.md"
    text = out.read_text(encoding="utf-8")
    for heading in HEADINGS:
        assert heading in text, heading
    # One status line per step, streamed.
    assert len(re.findall(r"^\[\d+/\d+\] ", proc.stdout, re.M)) == 8

    for what in ("Detection precision (paper's method)", "Detection recall (paper's method)"):
        v = float(_summary_value(text, what).rstrip(" %"))
        assert 0.0 <= v <= 100.0, (what, v)

    wrong, total = map(
        int, re.match(r"(\d+) / (\d+)", _summary_value(text, "Wrong decodes")).groups()
    )
    assert 0 <= wrong <= total and total > 0

    for method in ("baseline", "smoothed"):
        for cond in ("planar map, clean", "planar map, faults", "demo map, faults"):
            cell = _summary_value(text, f"Per-axis MAE, {method}, {cond}")
            axes = [float(x) for x in re.match(r"([\d.]+) / ([\d.]+) / ([\d.]+) m", cell).groups()]
            assert all(math.isfinite(x) and x >= 0 for x in axes), (method, cond, axes)
    cell = _summary_value(text, "Per-axis MAE end to end, smoothed")
    assert all(math.isfinite(float(x)) for x in cell.split(" m")[0].split(" / "))

    total_ms = float(_summary_value(text, "Total per frame, fast mode").rstrip(" ms"))
    assert 0.0 < total_ms < 1e5
    assert re.search(r"\| \*\*Total\*\* \| 153 \| [\d.]+ \| [\d.]+ \|", text)

    fig = root / "figures" / "fig13_trajectory.png"
    assert fig.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "](figures/fig13_trajectory.png)" in text
    # Header: the command, the machine and the runtime.
    assert "reproduce_paper.py --quick" in text
    assert re.search(r"total runtime \d+ s", text)
    assert "cores" in text and "gtsam" in text and "OpenCV" in text


def test_failed_and_skipped_steps_are_reported(tmp_path):
    mod = _module()
    results = {
        name: mod.StepResult(name, status="failed", error="exit 1: boom") for name in mod.STEP_NAMES
    }
    results["frontend"] = mod.StepResult("frontend", status="skipped")
    meta = {
        "command": "x",
        "date": "today",
        "cpu": "cpu",
        "cores": 2,
        "python": "3",
        "opencv": "4",
        "gtsam": "4",
        "numpy": "2",
        "commit": "abc",
        "quick": True,
        "load_start": 1.0,
        "load_end": 1.0,
        "total_s": 1.0,
        "figure_path": tmp_path / "figures" / "fig13_trajectory.png",
    }
    out = tmp_path / "results.md"
    text = mod.write_report(out, results, None, "", meta)
    assert out.read_text(encoding="utf-8") == text
    for heading in HEADINGS:
        assert heading in text
    assert "step `detector` failed (exit 1: boom)" in text
    assert "step `frontend` was skipped" in text


def test_unknown_options_are_dropped_and_printouts_parsed():
    mod = _module()
    args = ("--json", "/w/x.json", "--quick", "--frames", "5", "--seed", "3")
    assert mod._build_args(args, {"--frames", "--quick"}) == ["--quick", "--frames", "5"]
    text = (
        "# 200 frames, 10 signs\nper-frame PnP (initial values): 1.43 s (7.15 ms/frame)\n"
        "batch LM: 0.31 s (build 0.1 s, optimise 0.2 s, 4 iterations); "
        "MAE xyz [0.0239 0.0057 0.0216]\n"
        "iSAM2 over 100 frames: median 9.02 ms/frame (p90 1)\n"
    )
    d = mod.parse_bench_estimator(text)
    assert d["pnp_ms_per_frame"] == 7.15 and d["batch_s"] == 0.31
    assert d["isam2_frames"] == 100 and d["isam2_median_ms"] == 9.02
    assert d["batch_mae_xyz"] == [0.0239, 0.0057, 0.0216]
    assert mod.parse_bench_estimator("nothing here") == {}
