"""The pylon around a sign map: lattice members, insulator strings and conductors, in 3D.

World frame: the map's (z up, metres), ground at z = 0. The tower is a square
lattice whose front face stands just behind the signs (``site_frame``'s
facing direction points from the pylon toward the viewers); two crossarms
and an earth-wire peak sit above the highest sign; conductors leave the
crossarm tips perpendicular to them, toward and away from the viewers; a
low-voltage line runs along the face between the pylon and the UAV.

Everything is a ``Line3D``: a polyline with a width and a colour, projected
and drawn by the caller (``signpose.sim.frame``, ``signpose.sim.render``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from signpose.maps.loader import SignMap
from signpose.sim.trajectories import site_frame

LATTICE_BGR = (105.0, 110.0, 112.0)
CONDUCTOR_BGR = (38.0, 40.0, 44.0)
CONDUCTOR_WIDTH_M = 0.03
LOW_VOLTAGE_WIDTH_M = 0.025
SPAN_M = 300.0  # conductor length drawn on each side of the pylon
SAG_M = 9.0  # conductor sag at mid span
LEVEL_M = 3.0  # height of one lattice bay
INSULATOR_BGR = (112.0, 128.0, 104.0)  # toughened glass, grey-green
SHED_DIAMETER_M = 0.255  # cap-and-pin disc insulator (IEC 60305 U120B)
SHED_SPACING_M = 0.146
INSULATOR_CORE_M = 0.06


@dataclass(frozen=True)
class Line3D:
    """A thin 3D structure: (N, 3) polyline [m], world; width [m]; colour BGR.

    ``widths_m``, when given, is the (N - 1,) width of each segment [m] (an
    insulator's sheds); otherwise every segment is ``width_m`` wide.
    """

    points_m: np.ndarray
    width_m: float
    bgr: tuple[float, float, float]
    widths_m: np.ndarray | None = None


@dataclass(frozen=True)
class PylonLines:
    """The pylon's structures, by where they are drawn.

    Attributes:
        lattice: tower members, crossarms and insulator strings (behind the signs).
        far: conductors on the far side of the pylon (behind the signs).
        near: conductors between the pylon and the camera (in front of the signs).
    """

    lattice: tuple[Line3D, ...]
    far: tuple[Line3D, ...]
    near: tuple[Line3D, ...]


def catenary(a: np.ndarray, b: np.ndarray, sag_m: float, n: int) -> np.ndarray:
    """(n, 3) points from ``a`` to ``b`` hanging ``sag_m`` at mid span (parabola)."""
    t = np.linspace(0.0, 1.0, n)[:, None]
    p = a * (1 - t) + b * t
    p[:, 2] -= 4.0 * sag_m * (t[:, 0] * (1 - t[:, 0]))
    return p


def segment(p: np.ndarray, q: np.ndarray, width_m: float, n: int = 8, bgr=LATTICE_BGR) -> Line3D:
    """A straight member from ``p`` to ``q`` sampled at ``n`` points (so the lens bends it)."""
    t = np.linspace(0, 1, n)[:, None]
    return Line3D(p * (1 - t) + q * t, width_m, bgr)


@dataclass(frozen=True)
class _Tower:
    """The tower's frame: lateral axis ``a`` and facing ``f`` (world), sizes [m]."""

    base: np.ndarray
    a: np.ndarray
    f: np.ndarray
    face: float
    half_top: float
    half_bottom: float
    z_top: float

    def hw(self, z: float) -> float:
        """Half width of the tower at height ``z`` [m]."""
        return self.half_bottom + (self.half_top - self.half_bottom) * z / self.z_top

    def point(self, lat: float, depth: float, z: float) -> np.ndarray:
        """World point ``lat`` along the face, ``depth`` behind its front, at height ``z``."""
        return self.base + lat * self.a + (self.face - depth) * self.f + np.array([0, 0, z])


def _tower(sign_map: SignMap) -> _Tower:
    center, f, a, _ = site_frame(sign_map)
    rel = sign_map.centers_m() - center
    radius = max(s.diameter_m for s in sign_map.signs) / 2.0
    half_top = max(float(np.abs(rel @ a).max()) + radius + 0.6, 1.5)
    z_top = float(sign_map.centers_m()[:, 2].max()) + 3.0
    return _Tower(
        base=center - center[2] * np.array([0, 0, 1.0]),  # below the centre, on z = 0
        a=a,
        f=f,
        face=float((rel @ f).min()) - 0.15,  # lattice face just behind the signs
        half_top=half_top,
        half_bottom=half_top + 0.12 * z_top,
        z_top=z_top,
    )


def _tower_members(t: _Tower) -> list[Line3D]:
    """Corner legs, and per bay the X bracing and horizontals of all four faces."""
    out: list[Line3D] = []
    levels = np.linspace(0.0, t.z_top, max(int(t.z_top / LEVEL_M), 2) + 1)
    # The tower is square: depth of a level equals its width.
    for side_lat in (-1, 1):
        for side_d in (0, 1):
            legs = [t.point(side_lat * t.hw(z), side_d * 2 * t.hw(z), z) for z in (0.0, t.z_top)]
            out.append(segment(legs[0], legs[1], 0.16, 16))
    for z0, z1 in zip(levels[:-1], levels[1:], strict=True):
        for d in (0, 1):  # front and back faces
            p00, p01 = (
                t.point(-t.hw(z0), d * 2 * t.hw(z0), z0),
                t.point(t.hw(z0), d * 2 * t.hw(z0), z0),
            )
            p10, p11 = (
                t.point(-t.hw(z1), d * 2 * t.hw(z1), z1),
                t.point(t.hw(z1), d * 2 * t.hw(z1), z1),
            )
            out += [segment(p00, p11, 0.08), segment(p01, p10, 0.08), segment(p10, p11, 0.09)]
        for lat in (-1, 1):  # side faces
            q00, q01 = t.point(lat * t.hw(z0), 0, z0), t.point(lat * t.hw(z0), 2 * t.hw(z0), z0)
            q10, q11 = t.point(lat * t.hw(z1), 0, z1), t.point(lat * t.hw(z1), 2 * t.hw(z1), z1)
            out += [segment(q00, q11, 0.08), segment(q01, q10, 0.08), segment(q10, q11, 0.09)]
    return out


def insulator_string(top: np.ndarray, bottom: np.ndarray) -> Line3D:
    """A chain of disc insulators from ``top`` to ``bottom``: sheds on a thin core."""
    length = float(np.linalg.norm(bottom - top))
    step = SHED_SPACING_M / 5.0
    n = max(int(length / step), 2) + 1
    t = np.linspace(0.0, 1.0, n)[:, None]
    mid = (np.arange(n - 1) + 0.5) * length / (n - 1)
    on_shed = np.mod(mid, SHED_SPACING_M) < 0.25 * SHED_SPACING_M
    widths = np.where(on_shed, SHED_DIAMETER_M, INSULATOR_CORE_M)
    return Line3D(top * (1 - t) + bottom * t, INSULATOR_CORE_M, INSULATOR_BGR, widths)


def _crossarms(t: _Tower, insulators: bool = False) -> tuple[list[Line3D], list[np.ndarray]]:
    """Two crossarms with their insulator strings and the earth-wire peak; the string tips."""
    out: list[Line3D] = []
    tips: list[np.ndarray] = []
    arm_half = t.half_top + 7.0
    for z_arm in (t.z_top, t.z_top - 5.0):
        for d in (0.0, 2 * t.hw(z_arm)):
            out.append(segment(t.point(-arm_half, d, z_arm), t.point(arm_half, d, z_arm), 0.12, 24))
            for lat in (-1, 1):
                out.append(
                    segment(
                        t.point(lat * arm_half, d, z_arm),
                        t.point(lat * t.hw(z_arm - 2.5), d, z_arm - 2.5),
                        0.08,
                    )
                )
        for lat in (-1, 1):
            top = t.point(lat * (arm_half - 0.3), t.hw(z_arm), z_arm)
            tips.append(t.point(lat * (arm_half - 0.3), t.hw(z_arm), z_arm - 2.2))
            if insulators:
                out.append(insulator_string(top, tips[-1]))
            else:
                out.append(segment(top, tips[-1], 0.18, 4))  # insulator string, plain
    peak = t.point(0.0, t.hw(t.z_top), t.z_top + 3.5)
    for lat in (-1, 1):
        for d in (0.0, 2 * t.hw(t.z_top)):
            out.append(segment(t.point(lat * t.half_top, d, t.z_top), peak, 0.1))
    return out, tips


def _conductors(
    t: _Tower, tips: list[np.ndarray], center: np.ndarray
) -> tuple[list[Line3D], list[Line3D]]:
    """(far, near) conductors: from the tips both ways, and the low-voltage line in front."""
    near: list[Line3D] = []
    far: list[Line3D] = []
    for tip in tips:
        near.append(
            Line3D(catenary(tip, tip + SPAN_M * t.f, SAG_M, 240), CONDUCTOR_WIDTH_M, CONDUCTOR_BGR)
        )
        far.append(
            Line3D(catenary(tip, tip - SPAN_M * t.f, SAG_M, 120), CONDUCTOR_WIDTH_M, CONDUCTOR_BGR)
        )
    # A low-voltage line along the face, between the pylon and the UAV: it crosses signs.
    for dz in (2.6, 3.4):
        p = center + 7.0 * t.f + np.array([0, 0, dz])
        near.append(
            Line3D(
                catenary(p - 60.0 * t.a, p + 60.0 * t.a, 2.6, 240),
                LOW_VOLTAGE_WIDTH_M,
                CONDUCTOR_BGR,
            )
        )
    return far, near


def _side_strings(t: _Tower, sign_map: SignMap) -> list[Line3D]:
    """Two insulator strings hanging at the front corners, beside the signs (jumper strings)."""
    z_top = float(sign_map.centers_m()[:, 2].max()) + 1.0
    out = []
    for lat in (-1, 1):
        top = t.point(lat * (t.hw(z_top) + 0.4), -0.1, z_top)
        out.append(insulator_string(top, top - np.array([0.0, 0.0, 1.6])))
    return out


def pylon_lines(sign_map: SignMap, insulators: bool = False) -> PylonLines:
    """Lattice members, far conductors and near conductors of a pylon behind the signs.

    Args:
        sign_map: the signs the pylon carries.
        insulators: draw insulator strings as chains of sheds (and two more beside
            the signs) instead of plain bars.
    """
    tower = _tower(sign_map)
    center = site_frame(sign_map)[0]
    lattice = _tower_members(tower)
    arms, tips = _crossarms(tower, insulators)
    if insulators:
        arms += _side_strings(tower, sign_map)
    far, near = _conductors(tower, tips, center)
    return PylonLines(tuple(lattice + arms), tuple(far), tuple(near))
