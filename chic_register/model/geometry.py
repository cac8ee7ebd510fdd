"""The fiducial's geometry: tube centrelines in the fiducial frame F, and the geometry file.

This module is the single source of truth shared by the CAD model (which sweeps
its channels along these objects), the geometry file (written from them) and the
solver (which predicts image points from them). It holds
:class:`FiducialGeometry` and the file format (hash, YAML writing, loading and
validation); the tube objects live in :mod:`chic_register.model.tubes`, the body
and tool frame in :mod:`chic_register.model.body`, and are importable from here.

Frame F (docs/interfaces.md section 1): millimetres, origin on the cylinder axis in the
bottom end face, +z along the axis to the top face, +x toward tube ``D0``;
angles counter-clockwise about +z from +x. For the ``zframe`` family (the
seven-rod Z-frame), +z runs along the axial rods, the origin is on the frame's
central axis in its bottom face, x and y as in 3D Slicer's Z-frame ``z001``.

Geometry file (docs/interfaces.md section 2): YAML with ``format: chic-geometry``,
``version: 1``, ``name``, ``family`` (only when not ``chic``), ``units``,
``body``, ``tubes``, ``source`` and ``sha256``. The hash is the SHA-256 of the canonical JSON of every other key
(see :func:`content_sha256`).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from chic_register.errors import GeometryFileError, InputFileError
from chic_register.model.body import BODY_SHAPES, Body, FrameCoordinates, ToolFrame, rigid_4x4
from chic_register.model.tubes import HelixTube, LineTube, Tube
from chic_register.util.atomic import write_text
from chic_register.util.safeload import load_yaml_file

#: Plausibility bounds of a geometry file (mm): a fiducial that fits in an MRI bore.
MAX_EXTENT_MM = 1000.0
MAX_TUBE_DIAMETER_MM = 50.0
MAX_TUBES = 16  # CHIC has 9, a Z-frame 7; the solver's work grows fast with the count
MAX_HELIX_TURNS = 10.0
MAX_SOURCE_CHARS = 10_000  # the canonical JSON of ``source``

FORMAT = "chic-geometry"
VERSION = 1
ROLES = ("diametric", "helix", "orientation", "axial", "diagonal", "other")
#: Fiducial families (docs/interfaces.md section 1); a file without ``family`` is ``chic``.
FAMILIES = ("chic", "zframe", "nlocalizer")


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
    frame_coordinates: FrameCoordinates | None = None

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
        if self.frame_coordinates is not None:
            out["frame_coordinates"] = self.frame_coordinates.to_dict()
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
    if shape == "box":
        sizes = []
        for k in ("outer_size", "inner_size"):
            v = _require(path, b, k, "body.")
            if not isinstance(v, list) or len(v) != 2:
                raise GeometryFileError(path, f"body.{k} must be a list of 2 numbers (x, y), got {_short(v)}")
            sizes.append(tuple(_positive(path, f"body.{k}[{i}]", x) for i, x in enumerate(v)))
        if not all(i < o for i, o in zip(sizes[1], sizes[0])):
            raise GeometryFileError(path, "body.inner_size must be smaller than body.outer_size along x and y")
        return Body(*dims, shape, outer_size=sizes[0], inner_size=sizes[1])
    sides = [_positive(path, f"body.{k}", _require(path, b, k, "body.")) for k in ("outer_side", "inner_side")]
    if sides[1] >= sides[0]:
        raise GeometryFileError(path, "body.inner_side must be smaller than body.outer_side")
    return Body(*dims, shape, *sides)


def tool_from_dict(data, path="<geometry>") -> ToolFrame:
    """Parse the optional ``tool`` entry: ``{T_fiducial_from_tool: 4x4}``."""
    if not isinstance(data, dict) or set(data) != {"T_fiducial_from_tool"}:
        raise GeometryFileError(path, f"tool must be a mapping with the one key T_fiducial_from_tool, got {_short(data)}")
    T = rigid_4x4(data["T_fiducial_from_tool"])
    if T is None:
        raise GeometryFileError(path, "tool.T_fiducial_from_tool must be a rigid 4x4 matrix "
                                "(orthonormal rotation, det +1, last row 0 0 0 1)")
    return ToolFrame(T)


def frame_coordinates_from_dict(data, path="<geometry>") -> FrameCoordinates:
    """Parse the optional ``frame_coordinates`` entry: ``{system, T_frame_from_fiducial, axes, reference}``."""
    allowed = {"system", "T_frame_from_fiducial", "axes", "reference"}
    if not isinstance(data, dict) or not {"system", "T_frame_from_fiducial"} <= set(data) <= allowed:
        raise GeometryFileError(path, "frame_coordinates must be a mapping with system and T_frame_from_fiducial "
                                f"(and optional axes, reference), got {_short(data)}")
    for k in ("axes", "reference"):
        if not isinstance(data.get(k, ""), str) or len(data.get(k, "")) > 2000:
            raise GeometryFileError(path, f"frame_coordinates.{k} must be a string of at most 2000 characters")
    try:
        return FrameCoordinates(data["system"], data["T_frame_from_fiducial"], data.get("axes", ""),
                                data.get("reference", ""))
    except (ValueError, TypeError) as exc:
        raise GeometryFileError(path, str(exc)) from None


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
    frame = frame_coordinates_from_dict(data["frame_coordinates"], path) if "frame_coordinates" in data else None
    try:
        geom = FiducialGeometry(str(name), body, tuple(tubes), source, units, tool=tool, family=family,
                                frame_coordinates=frame)
    except ValueError as exc:
        raise GeometryFileError(path, str(exc)) from None
    check_plausible(geom, path)
    return geom


def load_geometry(path, check_hash: bool = True) -> FiducialGeometry:
    """Load and check a geometry file (format, version, sha256, every key).

    Raises :class:`GeometryFileError` with a one-line message naming the file
    and the fault.
    """
    p = Path(path)
    try:
        data = load_yaml_file(p, "geometry file")
    except InputFileError as exc:
        raise GeometryFileError(p, exc.detail) from None
    return geometry_from_dict(data, p, check_hash=check_hash)


def scaled_geometry(geom: FiducialGeometry, factor: float, calibration: dict) -> FiducialGeometry:
    """``geom`` with every length in F multiplied by ``factor`` (the body, the tube centrelines and diameters; a
    helix keeps its turn, so its pitch per mm divides by ``factor``), and ``calibration`` (a JSON-ready record of
    where the factor came from) in its ``source``. The tool frame is the tool's, and stays as it is."""
    k = float(factor)
    if not (math.isfinite(k) and 0.5 < k < 2.0):
        raise ValueError(f"a calibration factor must lie in (0.5, 2), got {factor!r}")
    b = geom.body
    body = dataclasses.replace(
        b, length=b.length * k, outer_diameter=b.outer_diameter * k, inner_diameter=b.inner_diameter * k,
        outer_side=None if b.outer_side is None else b.outer_side * k,
        inner_side=None if b.inner_side is None else b.inner_side * k,
        outer_size=None if b.outer_size is None else tuple(k * v for v in b.outer_size),
        inner_size=None if b.inner_size is None else tuple(k * v for v in b.inner_size))
    tubes = []
    for t in geom.tubes:
        if isinstance(t, LineTube):
            tubes.append(dataclasses.replace(t, p0=tuple(k * v for v in t.p0), p1=tuple(k * v for v in t.p1),
                                             diameter=t.diameter * k))
        else:
            tubes.append(dataclasses.replace(t, radius=t.radius * k, pitch_deg_per_mm=t.pitch_deg_per_mm / k,
                                             z0=t.z0 * k, z1=t.z1 * k, diameter=t.diameter * k))
    source = {**(geom.source or {}), "calibration": calibration}
    return dataclasses.replace(geom, body=body, tubes=tuple(tubes), source=source)
