"""scripts/reproduce_paper.py: its tables from recorded step JSON, and its failure handling.

The full reproduction (every step, a few minutes even with --quick) is the script's own
job; here the section builders get small JSON results built in the test, the step runner
gets throw-away scripts, and one real step runs at its smallest size.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from signpose.estimator.trajectory import Trajectory

from signpose.io.tum import write_tum

REPO = Path(__file__).resolve().parent.parent
SCRIPT = REPO / "scripts" / "reproduce_paper.py"
HEADINGS = ("## Table 1", "## Table 2", "## Table 3", "## Table 4", "## Table 5", "## Fig. 13")


@pytest.fixture(scope="module")
def mod():
    spec = importlib.util.spec_from_file_location("reproduce_paper", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the file runs
    spec.loader.exec_module(module)
    return module


# ---------------------------------------------------------------- recorded step JSON


def _counts(n: int, s: int, t: int, f: int, d: int) -> dict:
    return {
        "N": n,
        "D": d,
        "S": s,
        "T": t,
        "F": f,
        "precision": t / s if s else math.nan,
        "recall": s / n,
        "true_recall": t / n,
        "recall_of_decodable": t / d if d else math.nan,
    }


def _detector() -> dict:
    table = {"18-30": _counts(40, 20, 20, 0, 30), "all": _counts(100, 90, 89, 1, 95)}
    return {
        "frames": 7,
        "seed": 4242,
        "results": {
            "paper/paper": {"table": table, "median_ms": 260.4},
            "fast/paper": {"table": table, "median_ms": 44.6},
        },
    }


def _decoder() -> dict:
    cond = {"n": 20, "correct": 18, "wrong": 0, "no_decode": 2}
    return {
        "seed": 2017,
        "n_main": 30,
        "table2": {
            "0001": {"n": 10, "wrong": 0, "no_decode": 1},
            "1111": {"n": 20, "wrong": 1, "no_decode": 0},
        },
        "total": {"n": 30, "wrong": 1, "no_decode": 1},
        "no_decode_reasons": {"inconsistent": 1},
        "by_size": {"18-24": {"n": 30, "correct": 28, "wrong": 1}},
        "table3": {"dirt": cond, "motion blur": dict(cond, correct=20, no_decode=0)},
        "centre_rms_px_ge40": 0.12,
        "centre_rms_px_all": 0.11,
        "median_ms_wall": 1.55,
        "median_ms_cpu": 1.54,
    }


def _estimator() -> dict:
    def metrics(x: float) -> dict:
        m = {"n_matched": 120, "coverage": 1.0, "mae_xyz_m": [x, 0.002, 0.01]}
        return {k: m for k in ("baseline", "pnp", "smoothed")}

    scenarios = {
        f"{map_name}/{fault}/{flight}": {"metrics": metrics(x), "isam2_vs_batch_max_m": 2e-5}
        for map_name in ("planar", "demo")
        for fault in ("clean", "faults")
        for flight, x in (("orbit", 0.010), ("climb", 0.050))
    }
    sweep = {
        "offset_m": 0.0,
        "baseline_exact": 0.0,
        "baseline_noisy": 0.04,
        "pnp_noisy": 0.02,
        "baseline_cov_noisy": 1.0,
    }
    return {
        "settings": {"sigma_px": 0.13, "hfov": 60.0},
        "scenarios": scenarios,
        "planarity_sweep": [sweep, dict(sweep, offset_m=0.3, baseline_noisy=0.9)],
    }


def _frontend() -> dict:
    modes = {"paper": (240.0, 25.0), "fast": (46.0, 13.0), "track": (15.0, 9.0)}
    data = {"frames": 5, "seed": 5151, "aruco": 19.7}
    for mode, (total, decode) in modes.items():
        data |= {mode: total, f"{mode}_decode": decode, f"{mode}_cascade_only": total / 2}
    return data | {"found_fraction": dict.fromkeys(modes, 0.9)}


def _pipeline() -> dict:
    return {
        "frames": 40,
        "wall_s": 4.0,
        "cpu_s": 4.6,
        "frames_per_second": 10.0,
        "stages_ms_per_frame": {"detect": 36.1, "decode": 24.3, "track": 1.3},
        "estimator_timing_s": {"baseline": 0.04, "smoothed": 0.2},
    }


def _estimator_bench() -> dict:
    return {
        "frames": 200,
        "pnp_ms_per_frame": 0.72,
        "batch_s": 0.14,
        "batch_with_pnp_s": 0.28,
        "isam2_frames": 100,
        "isam2_median_ms": 5.59,
        "isam2_p90_ms": 35.9,
    }


def _simulate() -> dict:
    return {
        "frames": 5,
        "wall_s": 1.6,
        "cpu_s": 1.6,
        "frames_per_s": 3.18,
        "frames_per_cpu_s": 3.19,
    }


def _fig13() -> dict:
    def method(x: float, coverage: float) -> dict:
        return {"mae_xyz": [x, 0.005, 0.02], "coverage": coverage, "ate_rmse": 2 * x, "n": 40}

    return {"frames": 40, "methods": {"baseline": method(2.0, 0.5), "smoothed": method(0.01, 1.0)}}


RECORDED = {
    "detector": _detector,
    "decoder": _decoder,
    "estimator": _estimator,
    "frontend": _frontend,
    "pipeline": _pipeline,
    "estimator_bench": _estimator_bench,
    "simulate": _simulate,
    "fig13": _fig13,
}


def _results(mod, **data: dict) -> dict:
    """StepResults as run_step leaves them: every step ok with its recorded JSON (or ``data``)."""
    out = {}
    for name, build in RECORDED.items():
        text = json.dumps(data.get(name, build()))
        out[name] = mod.StepResult(name, f"python scripts/{name}.py", "ok", 1.0)
        out[name].data = mod.parse_step_json(text, name)
    return out


META = {
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
}


def _summary_row(text: str, what: str) -> list[str]:
    """The cells of the summary row whose 'What' cell is ``what``."""
    for line in text.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 5 and cells[1] == what:
            return cells
    raise AssertionError(f"no summary row {what!r}")


def _section(text: str, heading: str) -> str:
    """The Markdown from ``heading`` up to the next heading of any level."""
    start = text.index(heading)
    rest = text[start + len(heading) :]
    ends = [i for i in (rest.find("\n## "), rest.find("\n### ")) if i >= 0]
    return text[start : start + len(heading) + min(ends, default=len(rest))]


# ---------------------------------------------------------------- the tables


def test_every_table_is_built_from_the_recorded_json(mod):
    text = mod.build_report(_results(mod), META)
    for heading in HEADINGS:
        assert heading in text, heading
    assert "Not measured" not in text
    det = _detector()["results"]["paper/paper"]["table"]["all"]
    row = _summary_row(text, "Detection precision (paper's method)")
    assert row[3] == f"{100 * det['precision']:.2f} %" == "98.89 %"
    assert row[4] == "**misses** by 0.96 pp"
    row = _summary_row(text, "Detection recall (paper's method)")
    assert row[3] == "90.00 %" and row[4] == "**misses** by 4.35 pp"
    assert "| paper's sliding window + paper's merge | 100 | 90 | 89 | 1 | 98.89 % |" in text
    # Table 2: 1 wrong code in 30 crops against the paper's 1 in 2,019.
    assert _summary_row(text, "Wrong decodes")[3:] == [
        "1 / 30 (3.333 %)",
        "**misses**: 3.333 % > 0.050 %",
    ]
    assert "| 1111 | - | - | - | 20 | 1 | 0 | 5.000 % | 95.0 % |" in text
    assert "| **Total** | 2,019 | 1 | 0.0495 % | 30 | 1 | 1 | 3.333 % | 93.3 % |" in text
    assert _summary_row(text, "Worst disturbance, decoded correctly")[3] == "dirt: 90.0 %"
    # Table 4: the mean over the two flights of each scenario.
    mae_x = np.mean([0.010, 0.050])
    row = _summary_row(text, "Per-axis MAE, smoothed, demo map, faults")
    assert row[3] == f"{mae_x:.4f} / 0.0020 / 0.0100 m (100 % posed)"
    assert row[4] == "**misses** (x 0.030 m)"
    assert "at most 0.020 mm" in text
    # Table 4b and Table 5.
    assert _summary_row(text, "Per-axis MAE end to end, smoothed")[4] == "**misses** (z 0.020 m)"
    pos_ms = 1e3 * _pipeline()["estimator_timing_s"]["baseline"] / _pipeline()["frames"]
    fast = _frontend()["fast"] + pos_ms
    assert _summary_row(text, "Total per frame, fast mode, 1 core")[3] == f"{fast:.0f} ms"
    assert (
        f"| **Total** | 153 | {240 + pos_ms:.1f} | {fast:.1f} | {15 + pos_ms:.1f} | 100.0 |" in text
    )
    assert "iSAM2 median 5.59 ms per frame over 100 frames (p90 35.90 ms)" in text
    assert "5 frames 1920x1080 mp4 with everything on, 1.6 s wall (3.18 frames/s)" in text
    assert "](figures/fig13_trajectory.png)" in text


def test_a_missing_key_fails_only_its_section(mod):
    decoder = _decoder()
    del decoder["total"]["n"]
    detector = _detector()
    del detector["results"]
    text = mod.build_report(_results(mod, decoder=decoder, detector=detector), META)
    t1, t2, t3 = (_section(text, f"## Table {i}") for i in (1, 2, 3))
    assert "_Not measured: step `detector` wrote no 'results'._" in t1
    assert _summary_row(text, "Detection precision (paper's method)")[3:] == ["n/a", "failed"]
    assert "_Not measured: step `decoder` wrote no 'n'._" in t2
    assert "| **Total**" not in t2  # no half-built table
    assert _summary_row(text, "Wrong decodes")[3:] == ["n/a", "failed"]
    # The same step's JSON still feeds the sections whose keys are there.
    assert "| dirt | Dirt on the surface of encoded sign | 1111 | 20 | 90.0 % | 0 | 2 |" in t3
    assert "Decoding one sign crop (`eval_decoder.py`): median 1.55 ms wall" in text


def test_json_of_the_wrong_shape_is_reported_not_raised(mod):
    decoder = _decoder()
    decoder["table3"] = [1, 2]
    text = mod.build_report(_results(mod, decoder=decoder), META)
    assert "_Not measured: unexpected JSON from `decoder` (AttributeError" in _section(
        text, "## Table 3"
    )
    assert _summary_row(text, "Worst disturbance, correct")[3:] == ["n/a", "failed"]


def test_failed_and_skipped_steps_are_reported(mod, tmp_path):
    results = {
        name: mod.StepResult(name, status="failed", error="exit 1: boom") for name in mod.STEP_NAMES
    }
    results["frontend"] = mod.StepResult("frontend", status="skipped")
    out = tmp_path / "results.md"
    text = mod.write_report(out, results, META)
    assert out.read_text(encoding="utf-8") == text
    for heading in HEADINGS:
        assert heading in text
    assert "step `detector` failed (exit 1: boom)" in text
    assert "step `frontend` was skipped" in text
    assert "| detector | - | **failed**: exit 1: boom | 0 s |" in text


def test_every_section_reads_steps_that_run_and_every_script_step_writes_json(mod):
    read = {s.name for sec in mod.SECTIONS for s in sec.steps + sec.reads}
    assert read == set(mod.STEP_NAMES)
    for step in mod.STEPS:
        if step.script is not None:
            assert (REPO / "scripts" / step.script).is_file(), step.script
            for quick in (True, False):
                argv = step.argv(Path("/w"), quick)
                assert argv[argv.index("--json") + 1] == f"/w/{step.name}.json", step.name


# ---------------------------------------------------------------- running steps

FAILING = "import sys\nprint('boom: bad input', file=sys.stderr)\nsys.exit(3)\n"
NO_JSON = "print('numbers only printed')\n"
WRITES_JSON = (
    "import json, sys\n"
    "path = sys.argv[sys.argv.index('--json') + 1]\n"
    "json.dump({'frames': 5, 'nested': {'a': 1}}, open(path, 'w'))\n"
)


def test_a_failing_step_is_reported_and_the_next_runs(mod, tmp_path, capsys):
    scripts = tmp_path / "scripts"
    scripts.mkdir()
    steps = []
    for name, body in (("fails", FAILING), ("silent", NO_JSON), ("writes", WRITES_JSON)):
        (scripts / f"{name}.py").write_text(body)
        steps.append(mod.Step(name, f"{name}.py", ("--json", "{json}")))
    steps.append(mod.Step("absent", "absent.py"))
    work = tmp_path / "work"
    work.mkdir()
    results = mod.run_steps(
        tuple(steps), work, True, ["nothing"], 60.0, tmp_path / "f.png", scripts
    )
    assert results["fails"].status == "failed"
    assert results["fails"].error == "exit 3: boom: bad input"
    assert results["silent"].error == "wrote no JSON (silent.json)"
    assert results["absent"].error == "scripts/absent.py does not exist"
    assert results["writes"].status == "ok"
    assert results["writes"].command == "python scripts/writes.py --json $WORK/writes.json"
    with pytest.raises(mod.MissingKey, match="step `writes` wrote no 'b'"):
        results["writes"].data["nested"]["b"]
    printed = capsys.readouterr().out.splitlines()
    assert [line.split()[0] for line in printed] == ["[1/4]", "[2/4]", "[3/4]", "[4/4]"]
    assert "FAILED (exit 3: boom: bad input)" in printed[0]


def test_one_real_step_feeds_its_section(mod, tmp_path):
    """bench_estimator.py at its smallest: the report's numbers are the ones it wrote."""
    step = dataclasses.replace(mod.ESTIMATOR_BENCH, quick=("--frames", "20", "--isam-frames", "10"))
    res = mod.run_step(step, tmp_path, True, 120.0)
    assert res.status == "ok", res.error
    data = json.loads((tmp_path / "estimator_bench.json").read_text())
    text = mod.build_report({"estimator_bench": res}, META)
    assert (
        f"Smoother (`bench_estimator.py`, 20 frames): per-frame PnP "
        f"{data['pnp_ms_per_frame']:.2f} ms/frame, batch LM {data['batch_s']:.2f} s" in text
    )
    assert f"iSAM2 median {data['isam2_median_ms']:.2f} ms per frame over 10 frames" in text


def test_fig13_step_draws_and_writes_its_metrics(mod, tmp_path):
    stamps = np.arange(20) / 30.0
    world_t_cam = np.c_[np.linspace(0, 2, 20), np.zeros(20), np.linspace(5, 7, 20)]
    gt = Trajectory(stamps, world_t_cam, np.tile([0.0, 0.0, 0.0, 1.0], (20, 1)))
    off = Trajectory(stamps[::2], gt.world_t_cam[::2] + [0.1, 0.0, 0.0], gt.quat_xyzw[::2])
    run_dir, flight_dir = mod._pipeline_dirs(tmp_path)
    flight_dir.mkdir(parents=True)
    run_dir.mkdir(parents=True)
    write_tum(flight_dir / "groundtruth.tum", gt)
    write_tum(run_dir / "smoothed.tum", gt)
    write_tum(run_dir / "baseline.tum", off)
    fig_path = tmp_path / "figures" / "fig13.png"
    ok = mod.StepResult("pipeline", status="ok")
    res = mod.run_fig13(tmp_path, fig_path, ok)
    assert res.status == "ok", res.error
    assert fig_path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    methods = json.loads((tmp_path / "fig13.json").read_text())["methods"]
    assert methods["smoothed"]["mae_xyz"] == pytest.approx([0, 0, 0], abs=1e-6)
    assert methods["baseline"]["mae_xyz"][0] == pytest.approx(0.1, abs=1e-5)
    assert methods["baseline"]["coverage"] == pytest.approx(0.5)
    failed = mod.run_fig13(tmp_path, fig_path, mod.StepResult("pipeline", status="failed"))
    assert (failed.status, failed.error) == ("failed", "the pipeline step did not run")


def test_report_only_rebuilds_from_the_work_folder(mod, tmp_path, capsys):
    work = tmp_path / "work"
    work.mkdir()
    results = _results(mod)
    steps = {}
    for name, res in results.items():
        (work / f"{name}.json").write_text(json.dumps(RECORDED[name]()))
        steps[name] = {k: v for k, v in dataclasses.asdict(res).items() if k != "data"}
    (work / "frontend.json").unlink()  # a step's JSON lost since: that step is reported
    saved = {"steps": steps, "quick": True, "skip": ["fig13"]} | {
        k: META[k] for k in ("date", "commit", "load_start", "load_end", "total_s")
    }
    (work / "steps.json").write_text(json.dumps(saved))
    out = tmp_path / "docs" / "results.md"
    rc = mod.main(["--report-only", "--work", str(work), "--out", str(out)])
    assert rc == 1  # the frontend step now counts as failed
    text = out.read_text(encoding="utf-8")
    assert "--quick" in text and "--skip fig13" in text and "- Date: today" in text
    assert "| fig13 | - | skipped | - |" in text
    assert "step `frontend` failed (wrote no JSON (frontend.json))" in text
    assert _summary_row(text, "Wrong decodes")[3] == "1 / 30 (3.333 %)"
    assert "wrote " in capsys.readouterr().out


def test_report_only_without_an_earlier_run_is_an_error(mod, tmp_path, capsys):
    assert mod.main(["--report-only", "--work", str(tmp_path)]) == 2
    assert "cannot read the earlier run" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        mod.main(["--report-only"])
