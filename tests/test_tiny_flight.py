"""A flight too short to move the signs: the run completes without a refined map, said."""

import logging

import pytest
from signpose.estimator import refine

from signpose.cli import main
from signpose.core.errors import one_line

# gtsam's message, as its Python binding raises it (a RuntimeError).
INDETERMINATE = "\nIndeterminate linear system detected while working near variable\nx6.\n"


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> list[str]:
    """``signpose run``'s arguments for an 8-frame simulated flight (simulated once)."""
    sim = tmp_path_factory.mktemp("tiny") / "s"
    args = ["simulate", "--out", str(sim), "--frames", "8", "--width", "480", "--height", "270"]
    assert main(args + ["--quiet"]) == 0
    run = ["run", str(sim / "video.mp4"), "--map", str(sim / "map.yaml")]
    return run + ["--camera", str(sim / "camera.yaml"), "--no-plots", "--quiet"]


def test_an_indeterminate_map_solve_ends_the_run_well(tiny_run, tmp_path, monkeypatch, caplog):
    def indeterminate(*args, **kwargs):
        raise RuntimeError(INDETERMINATE)

    monkeypatch.setattr(refine, "_solve_flights", indeterminate)
    out = tmp_path / "o"
    with caplog.at_level(logging.WARNING):
        assert main(tiny_run + ["--out", str(out)]) == 0
    assert not (out / "map_refined.yaml").exists()
    assert "do not constrain the sign positions" in caplog.text
    assert (out / "result.mcap").stat().st_size > 0
    assert (out / "smoothed.tum").exists()


def test_other_map_solve_errors_are_not_hidden(tiny_run, tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("some other gtsam failure")

    monkeypatch.setattr(refine, "_solve_flights", broken)
    # An internal error: exit 1, not a silent success.
    assert main(tiny_run + ["--out", str(tmp_path / "o")]) == 1


def test_one_line_flattens_library_paragraphs():
    assert one_line(INDETERMINATE) == (
        "Indeterminate linear system detected while working near variable x6."
    )
    assert len(one_line("x" * 1000, limit=50)) == 50


@pytest.mark.parametrize("text", ["", "one line"])
def test_one_line_keeps_short_messages(text):
    assert one_line(text) == text
