"""The sign definition: codes, geometry, keypoints, PNG/SVG rendering and `signpose sign`."""

import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest
from signpose.frontend.sign import (
    ALL_CODES,
    PAPER_CODES,
    all_slot_keypoints,
    code_bits,
    render_sign_png,
    render_sign_svg,
    sign_keypoints,
    sign_shape,
    texture_px_from_sign_xy,
    validate_code,
)

from signpose.cli import main
from signpose.core.errors import InputError

PX = 256


def _inside(point: np.ndarray, polygon: np.ndarray) -> bool:
    contour = np.asarray(polygon, np.float32).reshape(-1, 1, 2)
    return cv2.pointPolygonTest(contour, (float(point[0]), float(point[1])), False) > 0


@pytest.mark.parametrize("code", ALL_CODES)
def test_every_code_renders_with_keypoints_on_white_and_black_slots_black(code):
    img = render_sign_png(code, PX)
    assert img.shape == (PX, PX) and img.dtype == np.uint8
    assert img[0, 0] == 255 and img[-1, -1] == 255  # outside the disc
    keypoints = sign_keypoints(code, 1.0)
    bits = code_bits(code)
    assert set(keypoints) == {"center", "direction"} | {
        f"slot{k}" for k, b in enumerate(bits, start=1) if b
    }
    for name, p in keypoints.items():
        u, v = np.round(texture_px_from_sign_xy(p[None, :2], 1.0, PX)[0]).astype(int)
        assert img[v, u] == 255, f"{code}: keypoint {name} at ({u}, {v}) is not white"
    for name, p in all_slot_keypoints(1.0).items():
        if name in keypoints:
            continue
        u, v = np.round(texture_px_from_sign_xy(p[None, :2], 1.0, PX)[0]).astype(int)
        assert img[v, u] == 0, f"{code}: black slot {name} at ({u}, {v}) is not black"


@pytest.mark.parametrize("code", ALL_CODES)
def test_keypoints_lie_inside_their_white_rectangles(code):
    shape = sign_shape(code, 0.8)
    for name, p in sign_keypoints(code, 0.8).items():
        assert p[2] == 0.0
        assert _inside(p[:2], shape.white_parts[name])
        others = [n for n in shape.white_parts if n != name]
        assert not any(_inside(p[:2], shape.white_parts[n]) for n in others)


def test_bits_are_clockwise_from_direction_msb_first():
    # The directional rectangle is straight up; slot 1 is the next one clockwise
    # (to the viewer's right), so its keypoint has x > 0.
    kp = all_slot_keypoints(1.0)
    assert abs(kp["direction"][0]) < 1e-12 and kp["direction"][1] > 0
    assert kp["slot1"][0] > 0 and kp["slot4"][0] < 0
    angles = [np.arctan2(kp[f"slot{k}"][1], kp[f"slot{k}"][0]) for k in range(1, 5)]
    steps = np.degrees(np.diff(np.unwrap(angles)))
    np.testing.assert_allclose(steps, -72.0, atol=1e-9)  # clockwise
    assert code_bits("1000") == (1, 0, 0, 0)
    assert set(sign_shape("1000").white_parts) == {"center", "direction", "slot1"}


def test_direction_rectangle_has_smallest_area_and_largest_aspect():
    parts = sign_shape("1111", 1.0).white_parts

    def sides(c):
        return sorted(np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)[:2])

    area = {n: np.prod(sides(c)) for n, c in parts.items()}
    aspect = {n: sides(c)[1] / sides(c)[0] for n, c in parts.items()}
    assert min(area, key=area.get) == "direction"
    assert max(aspect, key=aspect.get) == "direction"


def test_white_parts_inside_disc_and_disjoint():
    shape = sign_shape("1111", 1.0)
    for corners in shape.white_parts.values():
        assert np.all(np.linalg.norm(corners, axis=1) < 0.5)
    names = list(shape.white_parts)
    for i, a in enumerate(names):
        for b in names[i + 1 :]:
            assert not any(_inside(p, shape.white_parts[b]) for p in shape.white_parts[a])


@pytest.mark.parametrize("bad", ["", "0102", "10101", "abcd", 101, None])
def test_validate_code_rejects_bad_codes(bad):
    with pytest.raises(InputError):
        validate_code(bad)


def test_paper_codes_are_valid_and_distinct():
    assert len(set(PAPER_CODES)) == 10
    assert all(validate_code(c) == c for c in PAPER_CODES)


def test_svg_has_disc_and_white_parts_at_true_size():
    svg = render_sign_svg("0110", 800.0)
    root = ET.fromstring(svg.encode())
    ns = "{http://www.w3.org/2000/svg}"
    assert root.get("width") == "800mm"
    assert len(root.findall(f"{ns}circle")) == 1
    titles = sorted(p.find(f"{ns}title").text for p in root.findall(f"{ns}polygon"))
    assert titles == ["center", "direction", "slot2", "slot3"]


def test_cli_sign_writes_svg_and_png(tmp_path, capsys):
    svg, png = tmp_path / "s.svg", tmp_path / "s.png"
    assert main(["sign", "0101", "--out", str(svg)]) == 0
    assert main(["sign", "0101", "--out", str(png), "--px", "128"]) == 0
    assert svg.read_text().lstrip().startswith("<?xml")
    img = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (128, 128)
    np.testing.assert_array_equal(img, render_sign_png("0101", 128))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.png", "s.svg"]  # no temp files


def test_cli_sign_rejects_bad_code_with_exit_2(tmp_path, capsys):
    out = tmp_path / "s.svg"
    assert main(["sign", "0120", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "0120" in err
    assert not out.exists()
