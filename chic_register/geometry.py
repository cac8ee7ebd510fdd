"""The fiducial's geometry: tube centrelines in the fiducial frame F, and the geometry file.

This module is the single source of truth shared by the CAD model (which sweeps
its channels along these objects), the geometry file (written from them) and the
solver (which predicts image points from them).

Frame F (CONTRACT.md section 1): millimetres, origin on the cylinder axis in the
bottom end face, +z along the axis to the top face, +x toward tube ``D0``;
angles counter-clockwise about +z from +x. For the ``zframe`` family (the
seven-rod Z-frame), +z runs along the axial rods, the origin is on the frame's
central axis in its bottom face, x and y as in 3D Slicer's Z-frame ``z001``.

Geometry file (CONTRACT.md section 2): YAML with ``format: chic-geometry``,
``version: 1``, ``name``, ``family`` (only when not ``chic``), ``units``,
``body``, ``tubes``, ``source`` and ``sha256``. The hash is the SHA-256 of the canonical JSON of every other key
(see :func:`content_sha256`).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from .atomic import write_text
from .errors import GeometryFileError, InputFileError

#: Plausibility bounds of a geometry file (mm): a fiducial that fits in an MRI bore.
MAX_EXTENT_MM = 1000.0
MAX_TUBE_DIAMETER_MM = 50.0
MAX_TUBES = 16  # CHIC has 9, a Z-frame 7; the solver's work grows fast with the count
MAX_HELIX_TURNS = 10.0
MAX_SOURCE_CHARS = 10_000  # the canonical JSON of ``source``

FORMAT = "chic-geometry"
VERSION = 1
ROLES = ("diametric", "helix", "orientation", "axial", "diagonal", "other")
#: Fiducial families (CONTRACT.md section 1); a file without ``family`` is ``chic``.
FAMILIES = ("chic", "zframe")
#: Body cross-sections: a round annulus (CHIC) or a square frame (Z-frame).
BODY_SHAPES = ("annulus", "square")


def _vec3(values) -> tuple[float, float, float]:
    a = np.asarray(values, dtype=float).reshape(3)
    return (float(a[0]), float(a[1]), float(a[2]))


@dataclass(frozen=True)
class Body:
    """The body: ``length`` along z from 0, and its cross-section (mm).

    ``shape="annulus"`` (CHIC): a ring of ``outer_diameter`` / ``inner_diameter``.
    ``shape="square"`` (Z-frame): a square frame of outside side ``outer_side``
    around a square bore of side ``inner_side``, both centred on the z axis;
    its ``outer_diameter`` is then the circumscribed circle of the outside and
    ``inner_diameter`` the circle inscribed in the bore, so a reader that knows
    only circles still gets one enclosing the body and one inside the bore.
    """

    length: float
    outer_diameter: float
    inner_diameter: float
    shape: str = "annulus"
    outer_side: float | None = None
    inner_side: float | None = None

    @classmethod
    def square(cls, length: float, outer_side: float, inner_side: float) -> "Body":
        """A square frame body (see the class docstring for its diameters)."""
        return cls(float(length), float(outer_side) * math.sqrt(2.0), float(inner_side), "square",
                   float(outer_side), float(inner_side))

    def bore_gap_mm(self, xy) -> np.ndarray:
        """Distance (mm) from in-body points ``xy`` (N, 2) to the bore surface; shape (N,)."""
        xy = np.atleast_2d(np.asarray(xy, dtype=float))
        if self.shape == "square":
            h = self.inner_side / 2
            return np.hypot(np.maximum(np.abs(xy[:, 0]) - h, 0.0), np.maximum(np.abs(xy[:, 1]) - h, 0.0))
        return np.hypot(xy[:, 0], xy[:, 1]) - self.inner_diameter / 2

    def outside_gap_mm(self, xy) -> np.ndarray:
        """Distance (mm) from in-body points ``xy`` (N, 2) to the outside surface; shape (N,)."""
        xy = np.atleast_2d(np.asarray(xy, dtype=float))
        if self.shape == "square":
            return self.outer_side / 2 - np.max(np.abs(xy), axis=1)
        return self.outer_diameter / 2 - np.hypot(xy[:, 0], xy[:, 1])

    @property
    def outline_area_mm2(self) -> float:
        """Area enclosed by the outside surface in a section across z."""
        if self.shape == "square":
            return self.outer_side ** 2
        return math.pi * self.outer_diameter ** 2 / 4

    @property
    def bore_area_mm2(self) -> float:
        """Area of the bore in a section across z."""
        if self.shape == "square":
            return self.inner_side ** 2
        return math.pi * self.inner_diameter ** 2 / 4

    def to_dict(self) -> dict:
        out = {
            "length": float(self.length),
            "outer_diameter": float(self.outer_diameter),
            "inner_diameter": float(self.inner_diameter),
        }
        if self.shape != "annulus":  # CHIC files keep their content (and hash) unchanged
            out.update(shape=self.shape, outer_side=float(self.outer_side), inner_side=float(self.inner_side))
        return out


@dataclass(frozen=True)
class LineTube:
    """A straight channel: centreline from ``p0`` to ``p1`` (mm, frame F)."""

    id: str
    role: str
    p0: tuple[float, float, float]
    p1: tuple[float, float, float]
    diameter: float
    kind: str = field(default="line", init=False)

    def __post_init__(self):
        object.__setattr__(self, "p0", _vec3(self.p0))
        object.__setattr__(self, "p1", _vec3(self.p1))

    @property
    def direction(self) -> np.ndarray:
        """Unit vector from p0 to p1, shape (3,)."""
        d = np.subtract(self.p1, self.p0)
        return d / np.linalg.norm(d)

    @property
    def length_mm(self) -> float:
        return float(np.linalg.norm(np.subtract(self.p1, self.p0)))

    @property
    def z_range(self) -> tuple[float, float]:
        return (min(self.p0[2], self.p1[2]), max(self.p0[2], self.p1[2]))

    def points(self, t) -> np.ndarray:
        """Centreline points at parameters ``t`` in [0, 1]; shape (N, 3)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))[:, None]
        return np.asarray(self.p0) + t * np.subtract(self.p1, self.p0)

    def tangents(self, t) -> np.ndarray:
        """Unit tangents at parameters ``t``; shape (N, 3)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return np.tile(self.direction, (t.size, 1))

    def point_at_z(self, z_mm) -> np.ndarray:
        """Centreline points at heights ``z_mm`` (the line must not be horizontal); shape (N, 3)."""
        dz = self.p1[2] - self.p0[2]
        if abs(dz) < 1e-12:
            raise ValueError(f"tube {self.id} is horizontal: no unique point at a given z")
        return self.points((np.atleast_1d(z_mm) - self.p0[2]) / dz)

    def tangents_at_z(self, z_mm) -> np.ndarray:
        """Unit tangents at heights ``z_mm`` (toward p1); shape (N, 3)."""
        return np.tile(self.direction, (np.atleast_1d(z_mm).size, 1))

    def extended(self, ext_mm: float) -> "LineTube":
        """The same line continued by ``ext_mm`` of length past both ends."""
        d = self.direction
        return LineTube(self.id, self.role, np.asarray(self.p0) - ext_mm * d, np.asarray(self.p1) + ext_mm * d,
                        self.diameter)

    def intersect_plane(self, origin, normal) -> np.ndarray:
        """Where the centreline crosses the plane through ``origin`` with ``normal``.

        Returns shape (K, 3), K = 0 or 1: empty when the crossing lies outside
        the tube's extent or the line is parallel to the plane.
        """
        n = np.asarray(normal, dtype=float)
        p0 = np.asarray(self.p0)
        d = np.subtract(self.p1, self.p0)
        denom = float(n @ d)
        if abs(denom) < 1e-12:
            return np.empty((0, 3))
        t = float(n @ (np.asarray(origin, dtype=float) - p0)) / denom
        if t < -1e-12 or t > 1 + 1e-12:
            return np.empty((0, 3))
        return (p0 + t * d)[None, :]

    def to_dict(self) -> dict:
        return {
            "id": self.id,
            "role": self.role,
            "kind": "line",
            "p0": list(self.p0),
            "p1": list(self.p1),
            "diameter": float(self.diameter),
        }


@dataclass(frozen=True)
class HelixTube:
    """A helical channel about the z axis of F.

    The centreline at height z (``z0 <= z <= z1``) is at angle
    ``theta0_deg + pitch_deg_per_mm * (z - z0)`` and distance ``radius`` from the axis.
    """

    id: str
    role: str
    radius: float
    theta0_deg: float
    pitch_deg_per_mm: float
    z0: float
    z1: float
    diameter: float
    kind: str = field(default="helix", init=False)

    @property
    def z_range(self) -> tuple[float, float]:
        return (self.z0, self.z1)

    @property
    def length_mm(self) -> float:
        """Arc length of the centreline."""
        slope = self.radius * math.radians(self.pitch_deg_per_mm)
        return (self.z1 - self.z0) * math.hypot(1.0, slope)

    @property
    def theta1_deg(self) -> float:
        """Angle of the centreline at ``z1``."""
        return self.angle_deg_at(self.z1)

    def angle_deg_at(self, z_mm):
        """Centreline angle (degrees, unwrapped) at height ``z_mm``."""
        return self.theta0_deg + self.pitch_deg_per_mm * (np.asarray(z_mm, dtype=float) - self.z0)

    def z_at_angle(self, theta_deg):
        """Inverse of :meth:`angle_deg_at`: the height where the centreline has angle ``theta_deg``."""
        return self.z0 + (np.asarray(theta_deg, dtype=float) - self.theta0_deg) / self.pitch_deg_per_mm

    def point_at_z(self, z_mm) -> np.ndarray:
        """Centreline points at heights ``z_mm``; shape (N, 3)."""
        z = np.atleast_1d(np.asarray(z_mm, dtype=float))
        th = np.radians(self.angle_deg_at(z))
        return np.stack([self.radius * np.cos(th), self.radius * np.sin(th), z], axis=1)

    def points(self, t) -> np.ndarray:
        """Centreline points at parameters ``t`` in [0, 1] (z = z0 + t (z1 - z0)); shape (N, 3)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return self.point_at_z(self.z0 + t * (self.z1 - self.z0))

    def tangents(self, t) -> np.ndarray:
        """Unit tangents (pointing toward increasing z) at parameters ``t``; shape (N, 3)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        th = np.radians(self.angle_deg_at(self.z0 + t * (self.z1 - self.z0)))
        w = math.radians(self.pitch_deg_per_mm) * self.radius
        v = np.stack([-w * np.sin(th), w * np.cos(th), np.ones_like(th)], axis=1)
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    def tangents_at_z(self, z_mm) -> np.ndarray:
        """Unit tangents at heights ``z_mm`` (toward increasing z); shape (N, 3)."""
        return self.tangents((np.atleast_1d(np.asarray(z_mm, dtype=float)) - self.z0) / (self.z1 - self.z0))

    def extended(self, ext_mm: float) -> "HelixTube":
        """The same helix continued by ``ext_mm`` of arc length past both ends."""
        dz = ext_mm * (self.z1 - self.z0) / self.length_mm
        return HelixTube(self.id, self.role, self.radius, float(self.angle_deg_at(self.z0 - dz)),
                         self.pitch_deg_per_mm, self.z0 - dz, self.z1 + dz, self.diameter)

    def intersect_plane(self, origin, normal) -> np.ndarray:
        """Every crossing of the centreline with the plane through ``origin`` with ``normal``.

        Returns shape (K, 3), sorted by z. A helix can cross a steep plane
        more than once; all crossings inside ``[z0, z1]`` are returned.
        """
        n = np.asarray(normal, dtype=float)
        o = np.asarray(origin, dtype=float)

        def f(z):
            return float(n @ (self.point_at_z(z)[0] - o))

        turns = abs(self.pitch_deg_per_mm) * (self.z1 - self.z0) / 360.0
        zs = np.linspace(self.z0, self.z1, int(64 * max(1.0, turns)) + 2)
        vals = (self.point_at_z(zs) - o) @ n
        roots = []
        for i in range(len(zs) - 1):
            a, b = vals[i], vals[i + 1]
            if a == 0.0:
                roots.append(zs[i])
            elif a * b < 0:
                roots.append(bracketed_root(f, zs[i], zs[i + 1], a, b, xtol=1e-12))
        if vals[-1] == 0.0:
            roots.append(zs[-1])
        if not roots:
            return np.empty((0, 3))
        return self.point_at_z(np.array(roots))

    def to_dict(self) -> dict:
        return {
            "id": self.id,
            "role": self.role,
            "kind": "helix",
            "radius": float(self.radius),
            "theta0_deg": float(self.theta0_deg),
            "pitch_deg_per_mm": float(self.pitch_deg_per_mm),
            "z0": float(self.z0),
            "z1": float(self.z1),
            "diameter": float(self.diameter),
        }


Tube = LineTube | HelixTube


def bracketed_root(f, a: float, b: float, fa: float, fb: float, *, xtol: float = 1e-12, max_iter: int = 100) -> float:
    """A root of ``f`` in ``[a, b]`` given ``f(a) = fa`` and ``f(b) = fb`` of opposite signs.

    The Illinois variant of regula falsi (superlinear on smooth functions,
    never leaves the bracket), falling back to bisection when a secant step
    shrinks the bracket too little. Stops when the bracket is below ``xtol``
    (or a value is exactly 0). A few lines instead of ``scipy.optimize``,
    whose import costs a third of a second on the solver's start-up path.
    """
    a, b, fa, fb = float(a), float(b), float(fa), float(fb)
    if fa == 0.0:
        return a
    if fb == 0.0:
        return b
    if fa * fb > 0:
        raise ValueError(f"f({a}) = {fa} and f({b}) = {fb} do not bracket a root")
    side = 0
    for _ in range(max_iter):
        width = abs(b - a)
        if width <= xtol:
            break
        c = (a * fb - b * fa) / (fb - fa)
        if not (min(a, b) < c < max(a, b)):
            c = 0.5 * (a + b)
        fc = float(f(c))
        if fc == 0.0:
            return c
        if fc * fb < 0:  # root between c and b: c replaces a
            a, fa = b, fb
            b, fb = c, fc
            side = 0
        else:  # root between a and c: c replaces b; halve the stale end's value (Illinois)
            b, fb = c, fc
            fa *= 0.5
            side += 1
            if side > 2:  # the same end stuck three times: bisect
                m = 0.5 * (a + b)
                fm = float(f(m))
                if fm == 0.0:
                    return m
                if fm * fb < 0:
                    a, fa = m, fm
                else:
                    b, fb = m, fm
                side = 0
    return b if abs(fb) <= abs(fa) else a


def _rigid_4x4(values) -> np.ndarray | None:
    """``values`` as a proper rigid 4x4 matrix (last row 0 0 0 1), or None."""
    try:
        T = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        return None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.allclose(T[3], [0, 0, 0, 1]):
        return None
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        return None
    return T


@dataclass(frozen=True, eq=False)
class ToolFrame:
    """The tool's frame relative to F: ``T_fiducial_from_tool`` (4x4, mm); its origin is the tool tip.

    Optional key ``tool`` of the geometry file (written only when the spec
    has a tool, so files without it keep their hash).
    """

    T_fiducial_from_tool: np.ndarray

    def __post_init__(self):
        T = _rigid_4x4(self.T_fiducial_from_tool)
        if T is None:
            raise ValueError("tool.T_fiducial_from_tool must be a rigid 4x4 matrix (rotation, translation, 0 0 0 1)")
        object.__setattr__(self, "T_fiducial_from_tool", T)

    @classmethod
    def tip_offset(cls, tip_offset_mm: float) -> "ToolFrame":
        """A tool whose axes are F's and whose tip is on the axis at z = ``tip_offset_mm``."""
        T = np.eye(4)
        T[2, 3] = float(tip_offset_mm)
        return cls(T)

    @property
    def tip_mm(self) -> np.ndarray:
        """The tip in F (mm)."""
        return self.T_fiducial_from_tool[:3, 3].copy()

    def to_dict(self) -> dict:
        return {"T_fiducial_from_tool": [[float(v) for v in row] for row in self.T_fiducial_from_tool]}


@dataclass(frozen=True)
class FiducialGeometry:
    """Everything the solver knows about a fiducial: its body and its tube centrelines."""

    name: str
    body: Body
    tubes: tuple[Tube, ...]
    source: dict | None = None
    units: str = "mm"
    tool: ToolFrame | None = None
    family: str = "chic"

    def __post_init__(self):
        object.__setattr__(self, "tubes", tuple(self.tubes))
        if self.family not in FAMILIES:
            raise ValueError(f"family is {self.family!r}; allowed: {', '.join(FAMILIES)}")
        ids = [t.id for t in self.tubes]
        dupes = sorted({i for i in ids if ids.count(i) > 1})
        if dupes:
            raise ValueError(f"duplicate tube ids: {', '.join(dupes)}")

    @property
    def ids(self) -> tuple[str, ...]:
        return tuple(t.id for t in self.tubes)

    def tube(self, tube_id: str) -> Tube:
        for t in self.tubes:
            if t.id == tube_id:
                return t
        raise KeyError(tube_id)

    def by_role(self, role: str) -> tuple[Tube, ...]:
        return tuple(t for t in self.tubes if t.role == role)

    def intersect_plane(self, origin, normal) -> dict[str, np.ndarray]:
        """Crossings of every tube centreline with a plane: ``{id: (K, 3) array}``."""
        return {t.id: t.intersect_plane(origin, normal) for t in self.tubes}

    def content(self) -> dict:
        """The file content without ``sha256`` (what the hash covers)."""
        out = {
            "format": FORMAT,
            "version": VERSION,
            "name": self.name,
            **({"family": self.family} if self.family != "chic" else {}),
            "units": self.units,
            "body": self.body.to_dict(),
            "tubes": [t.to_dict() for t in self.tubes],
        }
        if self.source is not None:
            out["source"] = dict(self.source)
        if self.tool is not None:
            out["tool"] = self.tool.to_dict()
        return out

    def to_dict(self) -> dict:
        content = self.content()
        content["sha256"] = content_sha256(content)
        return content


def _canonical(obj, key: str | None = None):
    """Numbers as floats (except ``version``), so that ``50`` and ``50.0`` hash alike."""
    if isinstance(obj, dict):
        return {str(k): _canonical(v, str(k)) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_canonical(v, key) for v in obj]
    if isinstance(obj, bool) or obj is None or isinstance(obj, str):
        return obj
    if isinstance(obj, (int, float, np.integer, np.floating)):
        return int(obj) if key == "version" else float(obj)
    return obj


def content_sha256(content: dict) -> str:
    """SHA-256 (hex) of a geometry file's content, ``sha256`` key excluded.

    Canonical form: JSON with sorted keys, no whitespace, UTF-8, every number
    except ``version`` written as a float.
    """
    body = {k: v for k, v in content.items() if k != "sha256"}
    text = json.dumps(_canonical(body), sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


class _GeometryDumper(yaml.SafeDumper):
    """Block style, except that lists of numbers (points) stay on one line."""


def _represent_list(dumper, data):
    flow = all(isinstance(v, (int, float)) for v in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)


_GeometryDumper.add_representer(list, _represent_list)


def geometry_to_yaml(geom: FiducialGeometry) -> str:
    """The geometry file's text (keys in the contract's order)."""
    return yaml.dump(geom.to_dict(), Dumper=_GeometryDumper, sort_keys=False, width=100)


def write_geometry(geom: FiducialGeometry, path) -> Path:
    """Write ``geom`` to ``path`` atomically (temporary file, then rename)."""
    return write_text(path, geometry_to_yaml(geom))


def _number(path, where: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise GeometryFileError(path, f"{where} must be a finite number, got {value!r}")
    return float(value)


def _positive(path, where: str, value, upper: float = MAX_EXTENT_MM) -> float:
    v = _number(path, where, value)
    if not 0 < v <= upper:
        raise GeometryFileError(path, f"{where} must be > 0 and <= {upper:g} mm, got {value!r}")
    return v


def _coordinate(path, where: str, value) -> float:
    v = _number(path, where, value)
    if abs(v) > MAX_EXTENT_MM:
        raise GeometryFileError(path, f"{where} must lie within +-{MAX_EXTENT_MM:g} mm, got {value!r}")
    return v


def _point(path, where: str, value) -> tuple[float, float, float]:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise GeometryFileError(path, f"{where} must be a list of 3 numbers, got {_short(value)}")
    return tuple(_coordinate(path, f"{where}[{i}]", v) for i, v in enumerate(value))


def _short(value, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _json_value(path, where: str, value, depth: int = 0):
    """``source`` values as JSON-ready data (str keys; str, finite number, bool, None, list, mapping)."""
    if depth > 8:
        raise GeometryFileError(path, f"{where} is nested too deeply")
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, (int, float)):
        if not math.isfinite(value):
            raise GeometryFileError(path, f"{where} must be finite, got {value!r}")
        return value
    if isinstance(value, list):
        return [_json_value(path, f"{where}[{i}]", v, depth + 1) for i, v in enumerate(value)]
    if isinstance(value, dict):
        out = {}
        for k, v in value.items():
            if not isinstance(k, str):
                raise GeometryFileError(path, f"{where} has a non-string key {_short(k)}")
            out[k] = _json_value(path, f"{where}.{k}", v, depth + 1)
        return out
    raise GeometryFileError(path, f"{where} holds a {type(value).__name__} ({_short(value)}); allowed: "
                                  "strings, numbers, true/false, null, lists and mappings")


def _require(path, mapping: dict, key: str, where: str):
    if key not in mapping:
        raise GeometryFileError(path, f"missing key '{where}{key}'")
    return mapping[key]


def tube_from_dict(data: dict, path="<geometry>", where: str = "tubes[?]") -> Tube:
    """Parse one ``tubes`` entry; raises :class:`GeometryFileError` naming the key."""
    if not isinstance(data, dict):
        raise GeometryFileError(path, f"{where} must be a mapping, got {type(data).__name__}")
    tid = _require(path, data, "id", where + ".")
    if not isinstance(tid, str) or not tid or len(tid) > 32 or not tid.isprintable():
        raise GeometryFileError(path, f"{where}.id must be a printable string of 1..32 characters, got {_short(tid)}")
    role = _require(path, data, "role", where + ".")
    if not isinstance(role, str) or role not in ROLES:
        raise GeometryFileError(path, f"{where}.role is {_short(role)}; allowed: {', '.join(ROLES)}")
    kind = _require(path, data, "kind", where + ".")
    diameter = _positive(path, f"{where}.diameter", _require(path, data, "diameter", where + "."),
                         MAX_TUBE_DIAMETER_MM)
    if kind == "line":
        p0 = _point(path, f"{where}.p0", _require(path, data, "p0", where + "."))
        p1 = _point(path, f"{where}.p1", _require(path, data, "p1", where + "."))
        if np.allclose(p0, p1):
            raise GeometryFileError(path, f"{where}: p0 and p1 are the same point")
        return LineTube(tid, role, p0, p1, diameter)
    if kind == "helix":
        vals = {
            k: _coordinate(path, f"{where}.{k}", _require(path, data, k, where + "."))
            for k in ("radius", "theta0_deg", "pitch_deg_per_mm", "z0", "z1")
        }
        if vals["radius"] <= 0:
            raise GeometryFileError(path, f"{where}.radius must be > 0")
        if vals["z1"] <= vals["z0"]:
            raise GeometryFileError(path, f"{where}: z1 must be greater than z0")
        if vals["pitch_deg_per_mm"] == 0:
            raise GeometryFileError(path, f"{where}.pitch_deg_per_mm must not be 0 (use a line)")
        turns = abs(vals["pitch_deg_per_mm"]) * (vals["z1"] - vals["z0"]) / 360.0
        if turns > MAX_HELIX_TURNS:
            raise GeometryFileError(path, f"{where} turns {turns:.3g} times between z0 and z1; "
                                          f"allowed at most {MAX_HELIX_TURNS:g}")
        return HelixTube(tid, role, diameter=diameter, **vals)
    raise GeometryFileError(path, f"{where}.kind is {_short(kind)}; allowed: line, helix")


def check_plausible(geom: "FiducialGeometry", path="<geometry>") -> None:
    """Refuse a geometry no fiducial can have: a bore wider than the body, tubes far outside it.

    Every tube centreline must stay within one outer diameter of the axis and
    within one body length beyond either end face (generous: other families
    may place tubes differently, but not elsewhere in the scanner).
    """
    b = geom.body
    if not b.inner_diameter < b.outer_diameter:
        raise GeometryFileError(path, f"body.inner_diameter ({b.inner_diameter:g}) must be smaller than "
                                      f"body.outer_diameter ({b.outer_diameter:g})")
    for t in geom.tubes:
        pts = t.points(np.linspace(0.0, 1.0, 65))
        rho = float(np.max(np.hypot(pts[:, 0], pts[:, 1])))
        z_lo, z_hi = float(pts[:, 2].min()), float(pts[:, 2].max())
        if rho > b.outer_diameter or z_lo < -b.length or z_hi > 2 * b.length:
            raise GeometryFileError(
                path, f"tube {t.id} reaches {rho:.4g} mm from the axis and z {z_lo:.4g}..{z_hi:.4g} mm: outside "
                f"the plausible space of this body (within {b.outer_diameter:g} mm of the axis, z "
                f"{-b.length:g}..{2 * b.length:g} mm)")
        if t.diameter >= b.outer_diameter:
            raise GeometryFileError(path, f"tube {t.id} diameter ({t.diameter:g}) is not smaller than "
                                          f"body.outer_diameter ({b.outer_diameter:g})")


def _body_from_dict(path, b: dict) -> Body:
    """The ``body`` mapping: an annulus (default) or a square frame (``shape: square``)."""
    dims = [_positive(path, f"body.{k}", _require(path, b, k, "body."))
            for k in ("length", "outer_diameter", "inner_diameter")]
    shape = b.get("shape", "annulus")
    if shape not in BODY_SHAPES:
        raise GeometryFileError(path, f"body.shape is {_short(shape)}; allowed: {', '.join(BODY_SHAPES)}")
    if shape == "annulus":
        return Body(*dims)
    sides = [_positive(path, f"body.{k}", _require(path, b, k, "body.")) for k in ("outer_side", "inner_side")]
    if sides[1] >= sides[0]:
        raise GeometryFileError(path, "body.inner_side must be smaller than body.outer_side")
    return Body(*dims, shape, *sides)


def tool_from_dict(data, path="<geometry>") -> ToolFrame:
    """Parse the optional ``tool`` entry: ``{T_fiducial_from_tool: 4x4}``."""
    if not isinstance(data, dict) or set(data) != {"T_fiducial_from_tool"}:
        raise GeometryFileError(path, f"tool must be a mapping with the one key T_fiducial_from_tool, got {_short(data)}")
    T = _rigid_4x4(data["T_fiducial_from_tool"])
    if T is None:
        raise GeometryFileError(path, "tool.T_fiducial_from_tool must be a rigid 4x4 matrix "
                                "(orthonormal rotation, det +1, last row 0 0 0 1)")
    return ToolFrame(T)


def geometry_from_dict(data, path="<geometry>", check_hash: bool = True) -> FiducialGeometry:
    """Validate a parsed geometry file and build the :class:`FiducialGeometry`."""
    if not isinstance(data, dict):
        raise GeometryFileError(path, "not a chic-geometry file (top level is not a mapping)")
    if data.get("format") != FORMAT:
        if "format" not in data and ("channels" in data or "markers" in data or "tubes" not in data):
            raise GeometryFileError(path, "not a geometry file (no 'format: chic-geometry'); it looks like a design "
                                    "spec: run 'chic-design build SPEC' and pass exports/<name>/geometry.yaml")
        raise GeometryFileError(path, f"format is {data.get('format')!r}; expected '{FORMAT}'")
    version = data.get("version")
    if type(version) is not int or version != VERSION:  # 1.0 and true are not the integer 1
        raise GeometryFileError(
            path, f"version is {_short(version)}; this solver reads version {VERSION} (an integer)"
        )
    source = data.get("source")
    if source is not None:
        if not isinstance(source, dict):
            raise GeometryFileError(path, f"source must be a mapping, got {type(source).__name__}")
        source = _json_value(path, "source", source)
        if len(json.dumps(source)) > MAX_SOURCE_CHARS:
            raise GeometryFileError(path, f"source is longer than {MAX_SOURCE_CHARS} characters")
    if check_hash:
        stored = data.get("sha256")
        if not isinstance(stored, str):
            raise GeometryFileError(path, "missing key 'sha256' (the content hash)")
        try:
            actual = content_sha256(data)
        except (TypeError, ValueError) as exc:  # a value JSON cannot hold (from a Python caller)
            raise GeometryFileError(path, f"content cannot be hashed ({exc})") from None
        if stored != actual:
            raise GeometryFileError(
                path, "sha256 does not match the content: the file was edited or damaged; rebuild it"
            )
    name = _require(path, data, "name", "")
    if not isinstance(name, (str, int, float)) or isinstance(name, bool) or len(str(name)) > 200:
        raise GeometryFileError(path, f"name must be a short string, got {_short(name)}")
    units = data.get("units", "mm")
    if units != "mm":
        raise GeometryFileError(path, f"units is {_short(units)}; allowed: mm")
    b = _require(path, data, "body", "")
    if not isinstance(b, dict):
        raise GeometryFileError(path, "body must be a mapping")
    family = data.get("family", "chic")
    if family not in FAMILIES:
        raise GeometryFileError(path, f"family is {_short(family)}; allowed: {', '.join(FAMILIES)}")
    body = _body_from_dict(path, b)
    tubes_raw = _require(path, data, "tubes", "")
    if not isinstance(tubes_raw, list) or not tubes_raw or len(tubes_raw) > MAX_TUBES:
        raise GeometryFileError(path, f"tubes must be a list of 1..{MAX_TUBES} tubes")
    tubes = [tube_from_dict(t, path, f"tubes[{i}]") for i, t in enumerate(tubes_raw)]
    tool = tool_from_dict(data["tool"], path) if "tool" in data else None
    try:
        geom = FiducialGeometry(str(name), body, tuple(tubes), source, units, tool=tool, family=family)
    except ValueError as exc:
        raise GeometryFileError(path, str(exc)) from None
    check_plausible(geom, path)
    return geom


def load_geometry(path, check_hash: bool = True) -> FiducialGeometry:
    """Load and check a geometry file (format, version, sha256, every key).

    Raises :class:`GeometryFileError` with a one-line message naming the file
    and the fault.
    """
    from .safeload import load_yaml_file

    p = Path(path)
    try:
        data = load_yaml_file(p, "geometry file")
    except InputFileError as exc:
        raise GeometryFileError(p, exc.detail) from None
    return geometry_from_dict(data, p, check_hash=check_hash)


def sample_centreline(tube: Tube, step_mm: float = 0.5) -> np.ndarray:
    """Centreline polyline with points no more than ``step_mm`` apart; shape (N, 3)."""
    n = max(2, int(math.ceil(tube.length_mm / step_mm)) + 1)
    return tube.points(np.linspace(0.0, 1.0, n))

