"""The static part of a simulated flight: sign faces in 3D, the pylon, the textures.

World frame: the map's (z up, metres). Each sign's face is built in its own
frame (``frontend.sign``: x right, y up, z out of the face) and moved into
the world once per flight; dirt and opaque bars lie on or just in front of
the face. ``signpose.sim.frame`` projects all of it per pose.

Conditions (``SceneOptions``, each off by default and recorded per sign in
``boxes.jsonl``, see ``signpose.io.boxes``):
    dirt        stains on 70 % of the faces (grime or pale deposits).
    occlusion   an opaque bar on the face of 40 % of the signs, clear of the centre.
    members     share of signs with a lattice member (angle steel 60-120 mm wide,
                0.15-0.6 m in front of the face) crossing the disc at a random
                place and angle; it may cover any part, the centre included.
    conductors  extra conductors strung across the signs' height 2-8 m in front
                of the face (20-30 mm thick), so that they cross signs from most views.
    insulators  the crossarm insulator strings drawn as chains of sheds, and two
                more strings hanging beside the signs.
    faded       share of faces whose paint has faded: black and white pulled
                toward grey by 0.15-0.5 (``SignTruth.fade``).
    glare       share of faces with a specular highlight whose strength follows
                the view direction (``SignTruth.glare_dn``, the peak in DN).
    photo       real photographs behind the pylon instead of the procedural sky and
                ground (``signpose.sim.photos``; procedural when scikit-image is missing).

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
from signpose.sim.photos import available_photos, load_photo
from signpose.sim.pylon import (
    CONDUCTOR_BGR,
    LATTICE_BGR,
    Line3D,
    catenary,
    pylon_lines,
    segment,
)
from signpose.sim.render import Backdrop, PhotoBackdrop
from signpose.sim.trajectories import site_frame

BAR_DEPTH_M = 0.08  # opaque bars stand this far in front of the face
STAIN_DEPTH_M = 0.001  # stains lie on the face (lifted off it against z-fighting)
MEMBER_DEPTH_M = (0.15, 0.6)  # a lattice member in front of a face: distance range [m]
MEMBER_WIDTH_M = (0.06, 0.12)  # angle steel L60..L120
MEMBER_HALF_LENGTH_M = 1.5  # well past the disc: the member crosses the rim
CONDUCTOR_FRONT_M = (2.0, 8.0)  # extra conductors: distance in front of the face [m]
CONDUCTOR_FRONT_WIDTH_M = (0.02, 0.03)
CONDUCTOR_FRONT_SAG_M = (1.0, 2.5)
CONDUCTOR_FRONT_HALF_SPAN_M = 60.0
GLINT_TIP_DEG = (5.0, 25.0)  # angle between a face's normal and where it mirrors the sun
GLARE_RADIUS_R = (0.2, 0.45)  # highlight radius, in disc radii
FADE_RANGE = (0.15, 0.5)
GLARE_PEAK_DN = (60.0, 160.0)
# Glare strength is peak * max(0, glint . view)^GLARE_SHARPNESS: a lobe of ~10 deg.
GLARE_SHARPNESS = 60.0


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
    members: float = 0.0
    conductors: int = 0
    insulators: bool = False
    faded: float = 0.0
    glare: float = 0.0
    photo: bool = False


@dataclass(frozen=True)
class FaceGlare:
    """A specular highlight on a face, in the world frame.

    Attributes:
        center_m: (3,) centre of the highlight on the face [m].
        radius_m: its 1-sigma radius [m].
        glint: (3,) unit direction into which the face mirrors the sun.
        peak_dn: strength when looking straight along ``glint`` [DN].
    """

    center_m: np.ndarray
    radius_m: float
    glint: np.ndarray
    peak_dn: float

    def strength_dn(self, view: np.ndarray) -> float:
        """Peak added this frame for a unit direction ``view`` from the face to the camera."""
        c = max(0.0, float(self.glint @ view))
        return self.peak_dn * c**GLARE_SHARPNESS


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
        parts_m: part name (``signpose.io.boxes.PART_NAMES``) -> (P, 3) outline [m]
            of every part, white or black, for the covered-part truth.
        fade: paint fading, 0 = fresh.
        glare: the face's specular highlight, None = none.
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
    parts_m: dict[str, np.ndarray] | None = None
    fade: float = 0.0
    glare: FaceGlare | None = None


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
        backdrop: sky/ground textures (or a photograph) and noise bank
            (``signpose.sim.render``).
        members: lattice members in front of signs (drawn even without background).
        background: what the backdrop shows: ``procedural``, ``flat`` or ``photo:<name>``.
    """

    sign_map: SignMap
    camera: CameraModel
    signs: tuple[SignModel, ...]
    lines_behind: tuple[Line3D, ...]
    lines_front: tuple[Line3D, ...]
    center_m: np.ndarray
    backdrop: Backdrop
    members: tuple[Line3D, ...] = ()
    background: str = "procedural"


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
    every_part = sign_shape("1111", s.diameter_m).white_parts
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
        parts_m={k: world(densify(c, 6)) for k, c in every_part.items()},
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


def _member(s: SignModel, R: np.ndarray, rng: np.random.Generator) -> Line3D:
    """A lattice member crossing sign ``s`` (rotation ``R`` sign -> world) in front of its face."""
    r = s.diameter_m / 2.0
    rho, phi = 0.85 * r * math.sqrt(rng.random()), rng.uniform(0, 2 * np.pi)
    through = np.array([rho * math.cos(phi), rho * math.sin(phi)])
    angle = rng.uniform(0, np.pi)
    along = MEMBER_HALF_LENGTH_M * np.array([math.cos(angle), math.sin(angle)])
    depth = rng.uniform(*MEMBER_DEPTH_M)
    ends = [s.center_m + R @ np.array([*(through + k * along), depth]) for k in (-1.0, 1.0)]
    return segment(ends[0], ends[1], float(rng.uniform(*MEMBER_WIDTH_M)), 8, LATTICE_BGR)


def _front_conductors(sign_map: SignMap, n: int, rng: np.random.Generator) -> list[Line3D]:
    """``n`` conductors strung across the signs' height in front of the face."""
    center, facing, right, _ = site_frame(sign_map)
    z = sign_map.centers_m()[:, 2]
    out = []
    for _ in range(n):
        mid = center + rng.uniform(*CONDUCTOR_FRONT_M) * facing
        mid[2] = rng.uniform(z.min() - 0.5, z.max() + 0.5)
        sag = rng.uniform(*CONDUCTOR_FRONT_SAG_M)
        half = CONDUCTOR_FRONT_HALF_SPAN_M * right
        lift = np.array([0.0, 0.0, sag])  # the lowest point, mid span, at ``mid``
        points = catenary(mid - half + lift, mid + half + lift, sag, 240)
        out.append(Line3D(points, float(rng.uniform(*CONDUCTOR_FRONT_WIDTH_M)), CONDUCTOR_BGR))
    return out


def _glare(s: SignModel, R: np.ndarray, rng: np.random.Generator) -> FaceGlare:
    """A highlight on the face of ``s`` whose glint tips 5-25 deg off the face normal."""
    r = s.diameter_m / 2.0
    off = rng.uniform(-0.5, 0.5, 2) * r
    azimuth = rng.uniform(0, 2 * np.pi)  # in the face's plane: the way the glint tips
    axis = R[:, 0] * math.cos(azimuth) + R[:, 1] * math.sin(azimuth)
    tip = math.radians(rng.uniform(*GLINT_TIP_DEG))
    return FaceGlare(
        center_m=s.center_m + R[:, :2] @ off,
        radius_m=float(rng.uniform(*GLARE_RADIUS_R) * r),
        glint=math.cos(tip) * R[:, 2] + math.sin(tip) * axis,
        peak_dn=float(rng.uniform(*GLARE_PEAK_DN)),
    )


def _face_conditions(
    signs: tuple[SignModel, ...], sign_map: SignMap, options: SceneOptions, seed: int
) -> tuple[tuple[SignModel, ...], list[Line3D]]:
    """Signs with fading and glare as ``options`` ask, and the members in front of them."""
    facing = site_frame(sign_map)[1]
    rngs = [np.random.default_rng([seed, 5150, k]) for k in range(3)]
    out, members = [], []
    for s, ms in zip(signs, sign_map.signs, strict=True):
        R = world_R_face(ms, facing)
        if options.members > 0 and rngs[0].random() < options.members:
            members.append(_member(s, R, rngs[0]))
        if options.faded > 0 and rngs[1].random() < options.faded:
            s = replace(s, fade=float(rngs[1].uniform(*FADE_RANGE)))
        if options.glare > 0 and rngs[2].random() < options.glare:
            s = replace(s, glare=_glare(s, R, rngs[2]))
        out.append(s)
    return tuple(out), members


def _backdrop(
    camera: CameraModel, sign_map: SignMap, options: SceneOptions, seed: int
) -> tuple[Backdrop, str]:
    """The flight's backdrop and its name (``procedural``, ``flat`` or ``photo:<name>``)."""
    names = available_photos() if options.photo and options.background else ()
    if not names:
        return Backdrop(camera.width, camera.height, seed=seed), (
            "procedural" if options.background else "flat"
        )
    name = names[int(np.random.default_rng([seed, 1717]).integers(len(names)))]
    facing = site_frame(sign_map)[1]
    photo = PhotoBackdrop(camera.width, camera.height, load_photo(name), -facing, seed=seed)
    return photo, f"photo:{name}"


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
        seed: seeds dirt, occluders, the conditions and the textures.
        options: what the scene holds (see the module docstring).
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
    signs, members = _face_conditions(signs, sign_map, options, seed)
    behind: tuple[Line3D, ...] = ()
    front: tuple[Line3D, ...] = ()
    if options.background:
        pylon = pylon_lines(sign_map, insulators=options.insulators)
        extra = _front_conductors(sign_map, options.conductors, np.random.default_rng([seed, 99]))
        behind, front = pylon.lattice + pylon.far, pylon.near + tuple(extra)
    backdrop, background = _backdrop(camera, sign_map, options, seed)
    return Scene(
        sign_map=sign_map,
        camera=camera,
        signs=signs,
        lines_behind=behind,
        lines_front=front,
        center_m=center,
        backdrop=backdrop,
        members=tuple(members),
        background=background,
    )
