"""Load, validate and write sign maps (schema in ``maps/SCHEMA.md``).

World frame: the map's ``frame``, z up, metres. With an ``origin`` (WGS84) the
world frame is ENU at that origin (x east, y north, z up; ``maps.geodesy``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from importlib import resources
from pathlib import Path

import numpy as np
import yaml
from signpose.frontend.sign import ALL_CODES, sign_keypoints
from signpose.maps.geodesy import GeoOrigin, enu_from_geodetic

from signpose.core.errors import InputError
from signpose.core.fileio import atomic_write
from signpose.core.nesting import check_nesting, safe_load_unique

ORTHOGONALITY_TOL_DEG = 1.0
# A map holds at most 16 signs (one per code), a few kB; anything far larger is
# not a map and PyYAML would take minutes and gigabytes on it (issue 15 #21).
MAX_MAP_BYTES = 1_000_000
# |coordinate| of a sign centre [m]: 10,000 km, beyond any site frame.
MAX_COORDINATE_M = 1e7
# Sign diameter and survey sigma [m]: above this the number is a unit mistake.
MAX_LENGTH_M = 100.0
TOP_LEVEL_KEYS = ("frame", "signs", "origin")
ORIGIN_KEYS = ("lat_deg", "lon_deg", "height_m")
# Ellipsoidal heights of the origin [m]: below the Dead Sea's geoid, above Everest.
MAX_ORIGIN_HEIGHT_M = 10_000.0
SIGN_KEYS = {"code", "center_m", "center_wgs84", "normal", "up", "diameter_m", "sigma_m"}


@dataclass(frozen=True)
class MapSign:
    """One surveyed sign.

    Attributes:
        code: "0000".."1111".
        center_m: (3,) disc centre in the world frame [m].
        normal: (3,) unit normal out of the face, world frame, or None.
        up: (3,) unit vector from the centre toward the directional rectangle,
            world frame, or None.
        diameter_m: disc diameter [m].
        sigma_m: survey standard deviation of each coordinate [m].
    """

    code: str
    center_m: np.ndarray
    normal: np.ndarray | None
    up: np.ndarray | None
    diameter_m: float
    sigma_m: float

    @property
    def oriented(self) -> bool:
        return self.normal is not None

    def world_R_sign(self) -> np.ndarray:
        """(3, 3) rotation whose columns are the sign's x (right), y (up), z (normal)."""
        if self.normal is None or self.up is None:
            raise ValueError(f"sign {self.code} has no orientation")
        right = np.cross(self.up, self.normal)
        return np.stack([right, self.up, self.normal], axis=1)

    def world_T_sign(self) -> np.ndarray:
        """(4, 4) pose of the sign frame in the world frame."""
        T = np.eye(4)
        T[:3, :3] = self.world_R_sign()
        T[:3, 3] = self.center_m
        return T

    def keypoints_world(self) -> dict[str, np.ndarray]:
        """Named keypoints (3,) in the world frame [m] (read-only arrays).

        A centre-only sign gives only ``center``; an oriented sign gives every
        keypoint that ``frontend.sign.sign_keypoints`` defines for its code.
        """
        return dict(self._keypoints_world)

    @cached_property
    def _keypoints_world(self) -> dict[str, np.ndarray]:
        # Computed once per sign: building the sign's geometry costs about
        # 0.5 ms, and the per-frame solvers ask for it for every observed sign.
        if not self.oriented:
            points = {"center": self.center_m.copy()}
        else:
            R = self.world_R_sign()
            points = {
                name: self.center_m + R @ p
                for name, p in sign_keypoints(self.code, self.diameter_m).items()
            }
        for p in points.values():
            p.flags.writeable = False
        return points


@dataclass(frozen=True)
class SignMap:
    """A site's surveyed signs.

    Attributes:
        frame: name of the world frame (z up).
        signs: the signs, in file order, codes unique.
        source: the file it was read from ("" when built in code).
        origin: the WGS84 anchor of the world frame (then ENU at it), or None
            when the map is in a site frame only.
    """

    frame: str
    signs: tuple[MapSign, ...]
    source: str = ""
    origin: GeoOrigin | None = None

    @property
    def codes(self) -> tuple[str, ...]:
        return tuple(s.code for s in self.signs)

    def sign(self, code: str) -> MapSign | None:
        for s in self.signs:
            if s.code == code:
                return s
        return None

    def centers_m(self) -> np.ndarray:
        """(N, 3) sign centres [m], world frame, in ``signs`` order."""
        return np.array([s.center_m for s in self.signs]).reshape(-1, 3)


def bundled_map_path(name: str = "demo_pylon") -> Path:
    """Path of a map shipped with the package (``maps/<name>.yaml``)."""
    return Path(str(resources.files("signpose.maps").joinpath(f"{name}.yaml")))


def _vector(path: str, where: str, field: str, value, *, nonzero: bool) -> np.ndarray:
    if not isinstance(value, list | tuple) or len(value) != 3:
        raise InputError(f"{path}: {where}: field '{field}' must be a list of 3 numbers")
    try:
        v = np.array([float(x) for x in value])
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{path}: {where}: field '{field}' must hold numbers") from None
    if not np.all(np.isfinite(v)):
        raise InputError(f"{path}: {where}: field '{field}' has a non-finite number")
    if nonzero:
        largest = float(np.max(np.abs(v)))
        if largest < 1e-9:
            raise InputError(f"{path}: {where}: field '{field}' is a zero vector")
        # Scaled by its largest component first: the norm of [1e308, 0, 1e308] overflows.
        v = v / largest
        return v / np.linalg.norm(v)
    if np.max(np.abs(v)) > MAX_COORDINATE_M:
        raise InputError(
            f"{path}: {where}: field '{field}' is beyond {MAX_COORDINATE_M:g} m; "
            "give coordinates in metres in the site frame"
        )
    return v


def _positive(path: str, where: str, field: str, value) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{path}: {where}: field '{field}' must be a number") from None
    if not math.isfinite(x) or x <= 0:
        raise InputError(f"{path}: {where}: field '{field}' must be a finite number > 0")
    if x > MAX_LENGTH_M:
        raise InputError(
            f"{path}: {where}: field '{field}' is {x:g} m, above {MAX_LENGTH_M:g} m; "
            "give it in metres"
        )
    return x


def _origin(source: str, raw) -> GeoOrigin:
    """The map's optional ``origin: {lat_deg, lon_deg, height_m}``, validated."""
    if not isinstance(raw, dict):
        raise InputError(
            f"{source}: field 'origin' must be a mapping {{lat_deg: .., lon_deg: .., height_m: ..}}"
        )
    unknown = sorted(str(k) for k in raw if k not in ORIGIN_KEYS)
    if unknown:
        raise InputError(
            f"{source}: origin: unknown field '{unknown[0]}' (use lat_deg, lon_deg, height_m)"
        )
    values = {}
    limits = {"lat_deg": 90.0, "lon_deg": 180.0, "height_m": MAX_ORIGIN_HEIGHT_M}
    for key in ORIGIN_KEYS:
        if key not in raw:
            raise InputError(f"{source}: origin: missing field '{key}'")
        value = raw[key]
        if isinstance(value, bool):
            value = None
        try:
            x = float(value)
        except (TypeError, ValueError, OverflowError):
            raise InputError(f"{source}: origin: field '{key}' must be a number") from None
        if not math.isfinite(x) or abs(x) > limits[key]:
            raise InputError(
                f"{source}: origin: field '{key}' must be a finite number within "
                f"+-{limits[key]:g} (WGS84 degrees; ellipsoidal height in metres)"
            )
        values[key] = x
    return GeoOrigin(**values)


def _center(source: str, where: str, raw: dict, origin: GeoOrigin | None) -> np.ndarray:
    """A sign's centre in the world frame: ``center_m``, or ``center_wgs84`` converted."""
    has_m, has_geo = "center_m" in raw, "center_wgs84" in raw
    if has_m and has_geo:
        raise InputError(f"{source}: {where}: give 'center_m' or 'center_wgs84', not both")
    if not has_geo:
        if not has_m:
            raise InputError(f"{source}: {where}: missing field 'center_m'")
        return _vector(source, where, "center_m", raw["center_m"], nonzero=False)
    if origin is None:
        raise InputError(
            f"{source}: {where}: field 'center_wgs84' needs the map's 'origin' "
            "(add origin: {lat_deg: .., lon_deg: .., height_m: ..})"
        )
    geo = _vector(source, where, "center_wgs84", raw["center_wgs84"], nonzero=False)
    if abs(geo[0]) > 90.0 or abs(geo[1]) > 180.0:
        raise InputError(
            f"{source}: {where}: field 'center_wgs84' must be [lat_deg, lon_deg, height_m] "
            "with latitude within +-90 and longitude within +-180"
        )
    center = enu_from_geodetic(origin, geo[0], geo[1], geo[2])[0]
    if np.max(np.abs(center)) > MAX_COORDINATE_M:
        raise InputError(f"{source}: {where}: field 'center_wgs84' is too far from the origin")
    return center


def parse_map(data, source: str = "<map>") -> SignMap:
    """Validate a map already parsed from YAML; raise InputError on any problem."""
    if not isinstance(data, dict):
        raise InputError(f"{source}: not a sign map (expected keys 'frame' and 'signs')")
    unknown_top = sorted(str(k) for k in data if k not in TOP_LEVEL_KEYS)
    if unknown_top:
        raise InputError(
            f"{source}: unknown top-level key '{unknown_top[0]}' (a map has only "
            "'frame', 'signs' and the optional 'origin')"
        )
    frame = data.get("frame")
    if not isinstance(frame, str) or not frame:
        raise InputError(f"{source}: missing field 'frame' (the world frame's name)")
    raw_signs = data.get("signs")
    if not isinstance(raw_signs, list) or not raw_signs:
        raise InputError(f"{source}: field 'signs' must be a non-empty list")
    origin = _origin(source, data["origin"]) if "origin" in data else None
    signs: list[MapSign] = []
    seen: set[str] = set()
    for i, raw in enumerate(raw_signs):
        where = f"sign #{i + 1}"
        if not isinstance(raw, dict):
            raise InputError(f"{source}: {where}: must be a mapping of fields")
        code = raw.get("code")
        if code is None:
            raise InputError(f"{source}: {where}: missing field 'code'")
        if isinstance(code, int) and not isinstance(code, bool):
            raise InputError(
                f"{source}: {where}: field 'code' must be a quoted string such as \"0101\""
            )
        if code not in ALL_CODES:
            raise InputError(f"{source}: {where}: unknown code {code!r} (use '0000' to '1111')")
        where = f"sign {code}"
        if code in seen:
            raise InputError(f"{source}: {where}: duplicate code")
        seen.add(code)
        unknown = set(raw) - SIGN_KEYS
        if unknown:
            raise InputError(f"{source}: {where}: unknown field '{sorted(unknown)[0]}'")
        center = _center(source, where, raw, origin)
        for field in ("diameter_m", "sigma_m"):
            if field not in raw:
                raise InputError(f"{source}: {where}: missing field '{field}'")
        has_n, has_u = "normal" in raw, "up" in raw
        if has_n != has_u:
            missing = "up" if has_n else "normal"
            raise InputError(
                f"{source}: {where}: missing field '{missing}' ('normal' and 'up' go together)"
            )
        normal = up = None
        if has_n:
            normal = _vector(source, where, "normal", raw["normal"], nonzero=True)
            up = _vector(source, where, "up", raw["up"], nonzero=True)
            angle = math.degrees(math.acos(min(1.0, abs(float(normal @ up)))))
            if abs(90.0 - angle) > ORTHOGONALITY_TOL_DEG:
                raise InputError(
                    f"{source}: {where}: field 'up' is not orthogonal to 'normal' "
                    f"({angle:.1f} degrees apart)"
                )
            # Remove the small allowed non-orthogonality so world_R_sign is a rotation.
            up = up - (up @ normal) * normal
            up = up / np.linalg.norm(up)
        diameter = _positive(source, where, "diameter_m", raw["diameter_m"])
        sigma = _positive(source, where, "sigma_m", raw["sigma_m"])
        signs.append(MapSign(code, center, normal, up, diameter, sigma))
    return SignMap(frame=frame, signs=tuple(signs), source=source, origin=origin)


def load_map(path: str | Path) -> SignMap:
    """Read and validate a map file; raise InputError naming the file on any problem."""
    p = Path(path)
    try:
        size = p.stat().st_size
        if size > MAX_MAP_BYTES:
            raise InputError(
                f"{p}: {size} bytes is not a sign map (at most {MAX_MAP_BYTES} bytes: "
                "16 signs take a few kB); pass the map YAML"
            )
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(f"{p}: map file not found") from None
    except IsADirectoryError:
        raise InputError(f"{p}: is a folder; pass the map YAML file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"{p}: cannot read map file ({exc})") from None
    check_nesting(text, p)
    try:
        data = safe_load_unique(text)
    except yaml.YAMLError as exc:
        raise InputError(_yaml_problem(p, exc)) from None
    return parse_map(data, str(p))


def _yaml_problem(p: Path, exc: yaml.YAMLError) -> str:
    """One line for a map that safe_load refused: a tag it will not run, or bad syntax."""
    line = getattr(getattr(exc, "problem_mark", None), "line", None)
    at = f" at line {line + 1}" if line is not None else ""
    problem = str(getattr(exc, "problem", "") or "")
    if isinstance(exc, yaml.constructor.ConstructorError) and "tag" in problem:
        tag = problem.split("tag", 1)[1].strip(" '").replace("tag:yaml.org,2002:", "!!")
        return f"{p}: the tag {tag}{at} is not allowed (a map is plain YAML: no tags); remove it"
    if isinstance(exc, yaml.constructor.ConstructorError) and "duplicate key" in problem:
        return f"{p}: {problem}{at}; keep one of them"
    return f"{p}: not valid YAML{at}; fix the map syntax"


def map_to_dict(sign_map: SignMap) -> dict:
    """Plain-data form of a map, as written to YAML."""
    out = []
    for s in sign_map.signs:
        d = {"code": s.code, "center_m": [round(float(x), 6) for x in s.center_m]}
        if s.oriented:
            d["normal"] = [round(float(x), 9) for x in s.normal]
            d["up"] = [round(float(x), 9) for x in s.up]
        d["diameter_m"] = s.diameter_m
        d["sigma_m"] = s.sigma_m
        out.append(d)
    d = {"frame": sign_map.frame}
    if sign_map.origin is not None:
        o = sign_map.origin
        d["origin"] = {"lat_deg": o.lat_deg, "lon_deg": o.lon_deg, "height_m": o.height_m}
    d["signs"] = out
    return d


def write_map(path: str | Path, sign_map: SignMap) -> None:
    """Write ``sign_map`` as YAML (atomically)."""
    with atomic_write(path) as f:
        yaml.safe_dump(map_to_dict(sign_map), f, sort_keys=False, default_flow_style=None)
