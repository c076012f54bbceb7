"""signpose.core: the ground floor (units, atomic files) behaves as its docstrings say."""

import numpy as np
import pytest

from signpose.core.errors import OutputError
from signpose.core.fileio import atomic_write, ensure_dir
from signpose.core.units import (
    NS_PER_S,
    ms_from_s,
    s_from_stamp_ns,
    s_from_stamps_ns,
    stamp_ns_from_s,
    stamps_ns_from_s,
)


def test_stamps_round_trip_to_the_nanosecond():
    rng = np.random.default_rng(3)
    stamps_ns = np.sort(rng.integers(0, 10_000 * NS_PER_S, size=200))
    back = stamps_ns_from_s(s_from_stamps_ns(stamps_ns))
    # float64 seconds hold ~16 digits: 1e4 s with 1 ns steps survives the round trip.
    assert np.array_equal(back, stamps_ns)
    for ns in stamps_ns[:20]:
        assert stamp_ns_from_s(s_from_stamp_ns(int(ns))) == int(ns)


def test_rounding_is_to_the_nearest_nanosecond():
    assert stamp_ns_from_s(1.0000000004) == NS_PER_S
    assert stamp_ns_from_s(1.0000000006) == NS_PER_S + 1
    assert ms_from_s(0.0125) == pytest.approx(12.5)


def test_atomic_write_leaves_no_half_written_file(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError), atomic_write(target) as f:
        f.write("half")
        raise RuntimeError("interrupted")
    assert target.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]
    with atomic_write(target) as f:
        f.write("new")
    assert target.read_text() == "new"


def test_ensure_dir_names_the_folder_it_cannot_make(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(OutputError, match=str(blocker)):
        ensure_dir(blocker / "sub")
