"""Map schema, loader errors, round trip, and the CLI's answer to a bad map."""

import copy
import math

import numpy as np
import pytest
from conftest import valid_map_dict, write_yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from signpose.frontend.sign import PAPER_CODES
from signpose.maps.loader import load_map, parse_map, write_map

from signpose.cli import main
from signpose.core.errors import InputError


def test_bundled_map_has_the_papers_ten_signs(demo_map):
    assert sorted(demo_map.codes) == sorted(PAPER_CODES)
    centers = demo_map.centers_m()
    assert np.ptp(centers[:, 0]) == pytest.approx(3.7, abs=0.5)  # about 4 m wide
    assert np.ptp(centers[:, 2]) == pytest.approx(9.8, abs=1.0)  # about 10 m high
    assert 0.0 < np.abs(centers[:, 1]).max() <= 0.3  # not all coplanar
    for s in demo_map.signs:
        assert s.diameter_m == 0.8
        R = s.world_R_sign()
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0)
        kp = s.keypoints_world()
        np.testing.assert_allclose(kp["center"], s.center_m)
        # The directional keypoint is 0.6 R from the centre along 'up'.
        np.testing.assert_allclose(kp["direction"] - s.center_m, 0.6 * 0.4 * s.up, atol=1e-9)


def test_map_round_trip(tmp_path):
    m = parse_map(valid_map_dict(), "x.yaml")
    write_map(tmp_path / "m.yaml", m)
    back = load_map(tmp_path / "m.yaml")
    assert back.frame == m.frame and back.codes == m.codes
    for a, b in zip(m.signs, back.signs, strict=True):
        np.testing.assert_allclose(a.center_m, b.center_m, atol=1e-6)
        assert a.oriented == b.oriented and a.diameter_m == b.diameter_m
        if a.oriented:
            np.testing.assert_allclose(a.world_R_sign(), b.world_R_sign(), atol=1e-8)
    assert not back.signs[2].oriented
    assert set(back.signs[2].keypoints_world()) == {"center"}


def _broken(edit):
    data = valid_map_dict()
    edit(data["signs"])
    return data


# (what is wrong, edit to the valid map, sign named in the message, field named in the message)
BAD_MAPS = [
    ("unknown code", lambda s: s[0].update(code="0102"), "sign #1", "code"),
    ("integer code", lambda s: s[0].update(code=101), "sign #1", "code"),
    ("duplicate code", lambda s: s[1].update(code="0101"), "sign 0101", "code"),
    ("non-finite centre", lambda s: s[1].update(center_m=[1.0, math.nan, 2.0]), "1001", "center_m"),
    ("infinite diameter", lambda s: s[0].update(diameter_m=math.inf), "0101", "diameter_m"),
    ("zero normal", lambda s: s[0].update(normal=[0.0, 0.0, 0.0]), "0101", "normal"),
    ("zero up", lambda s: s[1].update(up=[0, 0, 0]), "1001", "up"),
    ("non-orthogonal", lambda s: s[0].update(up=[0.0, 0.5, 0.866]), "0101", "up"),
    ("missing diameter", lambda s: s[1].pop("diameter_m"), "1001", "diameter_m"),
    ("missing sigma", lambda s: s[0].pop("sigma_m"), "0101", "sigma_m"),
    ("missing centre", lambda s: s[2].pop("center_m"), "0010", "center_m"),
    ("missing up", lambda s: s[0].pop("up"), "0101", "up"),
    ("missing code", lambda s: s[1].pop("code"), "sign #2", "code"),
    ("short vector", lambda s: s[0].update(center_m=[1.0, 2.0]), "0101", "center_m"),
    ("text number", lambda s: s[0].update(sigma_m="small"), "0101", "sigma_m"),
    ("unknown field", lambda s: s[0].update(colour="red"), "0101", "colour"),
]


@pytest.mark.parametrize("edit,sign,field", [b[1:] for b in BAD_MAPS], ids=[b[0] for b in BAD_MAPS])
def test_loader_errors_name_file_sign_and_field(tmp_path, edit, sign, field):
    path = write_yaml(tmp_path / "bad_map.yaml", _broken(edit))
    with pytest.raises(InputError) as info:
        load_map(path)
    msg = str(info.value)
    assert "\n" not in msg
    assert str(path) in msg
    assert sign in msg
    assert field in msg


@pytest.mark.parametrize(
    "text,expect",
    [
        ("frame: x\nsigns: [\n", "YAML"),
        ("- 1\n- 2\n", "frame"),
        ("frame: x\nsigns: []\n", "signs"),
        ("signs:\n  - code: '0101'\n", "frame"),
    ],
)
def test_loader_rejects_malformed_files(tmp_path, text, expect):
    path = tmp_path / "m.yaml"
    path.write_text(text)
    with pytest.raises(InputError, match=expect) as info:
        load_map(path)
    assert str(path) in str(info.value)


def test_missing_map_file_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="not found"):
        load_map(tmp_path / "nope.yaml")


def test_cli_exits_2_with_one_line_for_a_bad_map(tmp_path, capsys):
    path = write_yaml(tmp_path / "bad.yaml", _broken(lambda s: s[0].update(normal=[0, 0, 0])))
    out = tmp_path / "out"
    code = main(["simulate", "--map", str(path), "--out", str(out), "--frames", "1", "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(path) in err and "normal" in err
    assert "Traceback" not in err
    assert not out.exists() or not any(out.iterdir())


# Hypothesis: whatever the YAML holds, parse_map raises InputError or returns a map.
_scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(10**400), max_value=10**400),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=6),
    st.sampled_from(["0101", "1001", "0000", "1111", "nan", "1e400", 10**400, -(10**309)]),
)
_values = st.recursive(
    _scalars,
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=4), children)
    ),
    max_leaves=12,
)
_fields = ["code", "center_m", "normal", "up", "diameter_m", "sigma_m"]
_vectors = st.lists(
    st.one_of(st.floats(allow_nan=True), st.integers(), st.just(10**400), st.text(max_size=2))
)
_sign = st.dictionaries(
    st.sampled_from(_fields + ["other"]), st.one_of(_values, _vectors), max_size=7
)
_maps = st.one_of(
    _values,
    st.fixed_dictionaries(
        {"frame": st.one_of(st.text(max_size=5), _scalars), "signs": st.lists(_sign, max_size=4)}
    ),
)


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_maps)
def test_parse_map_raises_only_input_error(data):
    try:
        m = parse_map(data, "fuzz.yaml")
    except InputError as exc:
        assert str(exc).startswith("fuzz.yaml")
        return
    assert m.signs and all(np.all(np.isfinite(s.center_m)) for s in m.signs)


@settings(max_examples=150, deadline=None)
@given(st.data())
def test_parse_map_mutations_of_a_valid_map_raise_only_input_error(data):
    raw = copy.deepcopy(valid_map_dict())
    i = data.draw(st.integers(0, len(raw["signs"]) - 1))
    field = data.draw(st.sampled_from(_fields))
    if data.draw(st.booleans()):
        raw["signs"][i].pop(field, None)
    else:
        raw["signs"][i][field] = data.draw(st.one_of(_values, _vectors))
    try:
        m = parse_map(raw, "fuzz.yaml")
    except InputError as exc:
        assert "fuzz.yaml" in str(exc)
    else:
        assert len(m.signs) == 3


def test_a_key_given_twice_is_refused_with_its_line(tmp_path):
    # yaml.safe_load keeps the last of two equal keys silently: the sign would
    # sit where the second line says
    p = tmp_path / "map.yaml"
    p.write_text(
        'frame: t\nsigns:\n  - code: "0101"\n    center_m: [0, 0, 1]\n'
        "    center_m: [0, 0, 3]\n    diameter_m: 0.8\n    sigma_m: 0.01\n"
    )
    with pytest.raises(InputError, match=r"duplicate key 'center_m' at line 5"):
        load_map(p)
    p.write_text(p.read_text().replace("    center_m: [0, 0, 3]\n", ""))
    assert load_map(p).signs[0].center_m[2] == 1.0
