"""The static part of a simulated flight: sign faces in 3D, the pylon, the textures.

World frame: the map's (z up, metres). Each sign's face is built in its own
frame (``frontend.sign``: x right, y up, z out of the face) and moved into
the world once per flight; dirt and opaque bars lie on or just in front of
the face. ``signpose.sim.frame`` projects all of it per pose.

Randomness: one stream per purpose, seeded from the flight's seed, so that
switching one condition on does not move the draws of another.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from signpose.estimator.camera import CameraModel
from signpose.frontend.sign import sign_keypoints, sign_shape
from signpose.maps.loader import MapSign, SignMap
from signpose.sim.pylon import Line3D, pylon_lines
from signpose.sim.render import Backdrop
from signpose.sim.trajectories import site_frame

BAR_DEPTH_M = 0.08  # opaque bars stand this far in front of the face
STAIN_DEPTH_M = 0.001  # stains lie on the face (lifted off it against z-fighting)


@dataclass(frozen=True)
class SceneOptions:
    """What the static scene holds (defaults: clean faces on a full pylon).

    Attributes:
        dirt: stains on some sign faces.
        occlusion: opaque bars (brackets, bird diverters) in front of some faces.
        background: build the pylon, conductors and textures (False: signs only).
    """

    dirt: bool = False
    occlusion: bool = False
    background: bool = True


@dataclass(frozen=True)
class SignModel:
    """One sign's drawable geometry in the world frame (built once per flight).

    Attributes:
        code: the sign's code.
        center_m: (3,) disc centre [m], world.
        normal: (3,) unit face normal, world (assumed for centre-only map signs).
        diameter_m: disc diameter [m].
        disc_m: (N, 3) disc outline [m], world.
        white_m: (M_k, 3) white rectangle outlines (edges densified) [m], world.
        keypoints_m: keypoint name -> (3,) [m], world.
        dirt_m: (polygon (P, 3) [m] world, intensity, opacity) stains.
        occluders_m: (polygon (P, 3) [m] world, intensity) bars in front of the face.
        shade: reflectance/illumination factor of the face (1 = nominal paint).
    """

    code: str
    center_m: np.ndarray
    normal: np.ndarray
    diameter_m: float
    disc_m: np.ndarray
    white_m: tuple[np.ndarray, ...]
    keypoints_m: dict[str, np.ndarray]
    dirt_m: tuple[tuple[np.ndarray, float, float], ...]
    occluders_m: tuple[tuple[np.ndarray, float], ...]
    shade: float = 1.0


@dataclass(frozen=True)
class Scene:
    """Everything static in a simulated flight.

    Attributes:
        sign_map: the map.
        camera: the simulated camera (with its distortion).
        signs: drawable sign geometry, map order.
        lines_behind: lattice members and far conductors (drawn behind signs).
        lines_front: conductors between the pylon and the camera.
        center_m: (3,) mean sign centre [m], used for the background motion.
        backdrop: sky/ground textures and noise bank (``signpose.sim.render``).
    """

    sign_map: SignMap
    camera: CameraModel
    signs: tuple[SignModel, ...]
    lines_behind: tuple[Line3D, ...]
    lines_front: tuple[Line3D, ...]
    center_m: np.ndarray
    backdrop: Backdrop


def densify(poly: np.ndarray, pieces: int) -> np.ndarray:
    """Split every edge of closed polygon ``poly`` (N, D) into ``pieces`` parts."""
    nxt = np.roll(poly, -1, axis=0)
    t = np.arange(pieces)[None, :, None] / pieces
    return (poly[:, None, :] * (1 - t) + nxt[:, None, :] * t).reshape(-1, poly.shape[1])


def _ellipse(center: np.ndarray, a: float, b: float, angle: float, n: int = 24) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    c, s = math.cos(angle), math.sin(angle)
    x, y = a * np.cos(t), b * np.sin(t)
    return np.stack([center[0] + c * x - s * y, center[1] + s * x + c * y], axis=1)


def world_R_face(sign: MapSign, facing: np.ndarray) -> np.ndarray:
    """(3, 3) rotation from the sign frame to the world.

    A centre-only landmark is drawn facing the site's viewers (``facing``),
    its directional rectangle up.
    """
    if sign.oriented:
        return sign.world_R_sign()
    up = np.array([0.0, 0.0, 1.0])
    return np.stack([np.cross(up, facing), up, facing], axis=1)


def _stains(rng: np.random.Generator, r: float) -> list[tuple[np.ndarray, float, float]]:
    """(polygon (P, 2) [m] sign plane, intensity, opacity) of 2-5 stains on a face of radius r."""
    out = []
    for _ in range(int(rng.integers(2, 6))):
        c = rng.uniform(-0.8, 0.8, 2) * r
        poly = _ellipse(
            c, rng.uniform(0.05, 0.22) * r, rng.uniform(0.04, 0.12) * r, rng.uniform(0, np.pi)
        )
        # Dark grime or pale deposits (bird droppings, lichen).
        value = rng.uniform(60, 110) if rng.random() < 0.5 else rng.uniform(160, 210)
        out.append((poly, float(value), float(rng.uniform(0.25, 0.7))))
    return out


def _bar(rng: np.random.Generator, r: float) -> tuple[np.ndarray, float]:
    """(polygon (P, 2) [m] sign plane, intensity) of an opaque bar across a face of radius r.

    A bracket or a bird diverter across the face, missing the location square
    so the sign stays locatable though maybe not decodable.
    """
    angle = rng.uniform(0, np.pi)
    normal2d = np.array([-math.sin(angle), math.cos(angle)])
    along = np.array([math.cos(angle), math.sin(angle)])
    off = rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 0.85) * r
    half_w = rng.uniform(0.06, 0.14) * r
    mid = off * normal2d
    corners = np.array(
        [
            mid + sa * 1.3 * r * along + sw * half_w * normal2d
            for sa, sw in ((-1, -1), (1, -1), (1, 1), (-1, 1))
        ]
    )
    return densify(corners, 8), float(rng.uniform(45, 90))


def _sign_model(
    s: MapSign, facing: np.ndarray, rng: np.random.Generator, dirt: bool, occlusion: bool
) -> SignModel:
    R = world_R_face(s, facing)
    shape = sign_shape(s.code, s.diameter_m)
    r = s.diameter_m / 2.0

    def world(xy: np.ndarray, z: float = 0.0) -> np.ndarray:
        p = np.column_stack([xy, np.full(len(xy), z)])
        return s.center_m + p @ R.T

    stains = []
    if dirt and rng.random() < 0.7:
        stains = [(world(p, STAIN_DEPTH_M), v, o) for p, v, o in _stains(rng, r)]
    bars = []
    if occlusion and rng.random() < 0.4:
        poly, value = _bar(rng, r)
        bars.append((world(poly, BAR_DEPTH_M), value))
    kps = sign_keypoints(s.code, s.diameter_m)
    return SignModel(
        code=s.code,
        center_m=np.asarray(s.center_m, float),
        normal=R[:, 2].copy(),
        diameter_m=float(s.diameter_m),
        disc_m=world(shape.disc),
        white_m=tuple(world(densify(c, 6)) for c in shape.white_parts.values()),
        keypoints_m={k: s.center_m + R @ p for k, p in kps.items()},
        dirt_m=tuple(stains),
        occluders_m=tuple(bars),
    )


def _at_least_one_bar(
    signs: tuple[SignModel, ...],
    sign_map: SignMap,
    facing: np.ndarray,
    rng: np.random.Generator,
    seed: int,
) -> tuple[SignModel, ...]:
    """``signs`` with a bar on one of them if none has any (occlusion was asked for)."""
    if any(s.occluders_m for s in signs):
        return signs
    k = int(rng.integers(len(signs)))
    bar_rng = np.random.default_rng([seed, 2])
    bars: tuple = ()
    while not bars:
        bars = _sign_model(sign_map.signs[k], facing, bar_rng, False, True).occluders_m
    return signs[:k] + (replace(signs[k], occluders_m=bars),) + signs[k + 1 :]


def build_scene(
    sign_map: SignMap,
    camera: CameraModel,
    seed: int = 0,
    options: SceneOptions = SceneOptions(),
) -> Scene:
    """The static part of a flight: sign geometry, pylon, conductors, textures.

    Args:
        sign_map: the signs.
        camera: the simulated camera.
        seed: seeds dirt, occluders and the textures.
        options: what the scene holds.
    """
    rng = np.random.default_rng([seed, 7919])
    center, facing, _, _ = site_frame(sign_map)
    signs = tuple(
        _sign_model(s, facing, rng, options.dirt, options.occlusion) for s in sign_map.signs
    )
    if options.occlusion:
        signs = _at_least_one_bar(signs, sign_map, facing, rng, seed)
    # Faces weather and catch the sun differently (own stream: other draws stay put).
    shades = np.random.default_rng([seed, 4242]).uniform(0.85, 1.08, len(signs))
    signs = tuple(replace(s, shade=float(f)) for s, f in zip(signs, shades, strict=True))
    if options.background:
        pylon = pylon_lines(sign_map)
        behind, front = pylon.lattice + pylon.far, pylon.near
    else:
        behind, front = (), ()
    return Scene(
        sign_map=sign_map,
        camera=camera,
        signs=signs,
        lines_behind=behind,
        lines_front=front,
        center_m=center,
        backdrop=Backdrop(camera.width, camera.height, seed=seed),
    )
