"""Point lists in 3D Slicer's markups formats and in plain CSV: read and write.

Three formats, chosen by the file name's suffix (:data:`SUFFIXES`):

- ``.mrk.json`` (also ``.json``): Slicer's markups JSON (schema
  ``markups-schema-v1.0.3``): ``markups[0].controlPoints[i]`` with ``label``,
  ``description`` and ``position``; ``markups[0].coordinateSystem`` ``LPS``
  or ``RAS`` (a file without it is LPS, as Slicer 5 reads it);
- ``.fcsv``: Slicer's fiducial CSV: ``# Markups fiducial file version = 4.11``,
  ``# CoordinateSystem = LPS|RAS`` (``1``/``0`` in older files; a file without
  the line is RAS, as the files before 4.11 were), ``# columns = ...``, then one
  row per point (``id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID``);
- ``.csv``: a header row naming at least ``label,x,y,z`` (other columns are
  kept as text); an optional ``coordinates`` column names the system
  (``LPS``, ``RAS`` or anything else, e.g. a stereotactic frame's name). A file
  without it has no stated system (:attr:`PointList.coordinate_system` None).

Positions are returned as the file holds them, in the system it declares;
:meth:`PointList.positions_lps_mm` converts a scanner point list to LPS.
Every reading fault is a :class:`~chic_register.errors.InputFileError` naming
the file and the key; every write is atomic.
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from chic_register.errors import ChicRegisterError, InputFileError
from chic_register.util.atomic import write_text
from chic_register.util.safeload import read_regular_file

#: The formats, by the suffix that names them.
SUFFIXES = (".mrk.json", ".json", ".fcsv", ".csv")
#: The scanner coordinate systems Slicer knows; any other name is a frame's own and is kept as written.
SLICER_SYSTEMS = ("LPS", "RAS")
MAX_POINT_FILE_BYTES = 16 << 20  # 16 MiB: some 100 000 points
MARKUPS_SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/"
                  "Resources/Schema/markups-schema-v1.0.3.json#")
FCSV_VERSION = "4.11"
FCSV_COLUMNS = ("id", "x", "y", "z", "ow", "ox", "oy", "oz", "vis", "sel", "lock", "label", "desc",
                "associatedNodeID")
#: Old ``.fcsv`` files give the system as a number (vtkMRMLStorageNode: 0 RAS, 1 LPS).
FCSV_SYSTEM_CODES = {"0": "RAS", "1": "LPS", "RAS": "RAS", "LPS": "LPS"}
_FLIP_LPS_RAS = np.array([-1.0, -1.0, 1.0])


@dataclass(frozen=True)
class MarkupPoint:
    """One point: ``label``, ``position_mm`` (3,) in its list's system, a free ``description``, and ``columns``
    (CSV only: further named values, written after x, y, z in their order)."""

    label: str
    position_mm: tuple[float, float, float]
    description: str = ""
    columns: dict = field(default_factory=dict)


@dataclass(frozen=True)
class PointList:
    """Points in one coordinate system: ``LPS`` or ``RAS`` (scanner), another name (a frame's own coordinates,
    e.g. ``leksell``), or None (a CSV file that does not say)."""

    points: tuple[MarkupPoint, ...]
    coordinate_system: str | None = "LPS"

    @property
    def positions_mm(self) -> np.ndarray:
        """The positions as held, (N, 3)."""
        return np.array([p.position_mm for p in self.points], dtype=float).reshape(-1, 3)

    @property
    def labels(self) -> list[str]:
        return [p.label for p in self.points]

    def positions_lps_mm(self, default: str = "LPS") -> np.ndarray:
        """The positions in LPS, (N, 3): RAS ones with x and y negated; a list without a system is taken as
        ``default``; a frame's coordinates are not scanner positions (:class:`ChicRegisterError`)."""
        system = self.coordinate_system or default
        if system not in SLICER_SYSTEMS:
            raise ChicRegisterError(f"points in {system} coordinates are not scanner (LPS or RAS) positions")
        return self.positions_mm * (_FLIP_LPS_RAS if system == "RAS" else 1.0)


def point_format(path) -> str:
    """The format a file name asks for: ``mrk.json``, ``fcsv`` or ``csv``; :class:`ChicRegisterError` otherwise."""
    name = Path(path).name.lower()
    if name.endswith(".json"):
        return "mrk.json"
    if name.endswith(".fcsv"):
        return "fcsv"
    if name.endswith(".csv"):
        return "csv"
    raise ChicRegisterError(f"{path}: a point file ends in .mrk.json, .fcsv or .csv")


# --------------------------------------------------------------------------- reading


def _position(path, where: str, value) -> tuple[float, float, float]:
    try:
        p = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        p = ()
    if len(p) != 3 or not all(math.isfinite(v) for v in p):
        raise InputFileError(path, f"{where} must be three finite numbers (mm)")
    return p


def _text(path, what: str) -> str:
    try:
        return read_regular_file(path, what, max_bytes=MAX_POINT_FILE_BYTES).decode("utf-8-sig")
    except UnicodeDecodeError:
        raise InputFileError(path, f"is not a UTF-8 text {what}") from None


def read_mrk_json(path) -> PointList:
    """A Slicer markups JSON file's first markup: its control points and coordinate system."""
    try:
        doc = json.loads(_text(path, "markups file"))
    except (json.JSONDecodeError, RecursionError) as exc:
        raise InputFileError(path, f"not a JSON file ({str(exc).splitlines()[0][:100]})") from None
    markups = doc.get("markups") if isinstance(doc, dict) else None
    if not isinstance(markups, list) or not markups or not isinstance(markups[0], dict):
        raise InputFileError(path, "needs key 'markups' holding a list of markups (Slicer's markups JSON)")
    first = markups[0]
    system = first.get("coordinateSystem", "LPS")
    if system not in SLICER_SYSTEMS:
        raise InputFileError(path, f"markups[0].coordinateSystem is {str(system)[:20]!r}; allowed: LPS, RAS")
    cps = first.get("controlPoints", [])
    if not isinstance(cps, list):
        raise InputFileError(path, "markups[0].controlPoints must be a list")
    points = []
    for i, cp in enumerate(cps):
        where = f"markups[0].controlPoints[{i}]"
        if not isinstance(cp, dict) or "position" not in cp:
            raise InputFileError(path, f"{where} needs key 'position'")
        if cp.get("positionStatus", "defined") != "defined":
            continue  # a point placed in Slicer's list but not yet given a position
        points.append(MarkupPoint(str(cp.get("label", f"P{i + 1}")), _position(path, f"{where}.position", cp["position"]),
                                  str(cp.get("description", ""))))
    return PointList(tuple(points), system)


def read_fcsv(path) -> PointList:
    """A Slicer fiducial CSV file: its points and coordinate system."""
    system, columns, rows = "RAS", list(FCSV_COLUMNS), []
    for n, line in enumerate(_text(path, "fiducial file").splitlines(), 1):
        if line.startswith("#"):
            key, _, value = line[1:].partition("=")
            key, value = key.strip().lower(), value.strip()
            if key == "coordinatesystem":
                if value.upper() not in FCSV_SYSTEM_CODES:
                    raise InputFileError(path, f"line {n}: CoordinateSystem is {value[:20]!r}; allowed: LPS, RAS, 0, 1")
                system = FCSV_SYSTEM_CODES[value.upper()]
            elif key == "columns":
                columns = [c.strip() for c in value.split(",")]
            continue
        if line.strip():
            rows.append((n, line))
    missing = [c for c in ("x", "y", "z") if c not in columns]
    if missing:
        raise InputFileError(path, f"the '# columns =' line lacks {', '.join(missing)}")
    points = []
    for (n, _), row in zip(rows, csv.reader(line for _, line in rows)):
        values = dict(zip(columns, row))
        if any(c not in values for c in ("x", "y", "z")):
            raise InputFileError(path, f"line {n}: needs columns x, y, z (found {len(row)} values)")
        pos = _position(path, f"line {n}: x, y, z", (values["x"], values["y"], values["z"]))
        points.append(MarkupPoint(values.get("label", "") or f"P{len(points) + 1}", pos, values.get("desc", "")))
    return PointList(tuple(points), system)


def read_csv(path) -> PointList:
    """A CSV file whose header row names ``label,x,y,z`` (and optionally ``coordinates``); other columns kept."""
    reader = csv.reader(io.StringIO(_text(path, "CSV file")))
    header = next(reader, None)
    header = [h.strip() for h in header] if header else []
    missing = [c for c in ("label", "x", "y", "z") if c not in header]
    if missing:
        raise InputFileError(path, f"the header row lacks column {', '.join(missing)} (needs label,x,y,z)")
    points, systems = [], set()
    for n, row in enumerate(reader, 2):
        if not any(v.strip() for v in row):
            continue
        values = dict(zip(header, (v.strip() for v in row)))
        if len(row) < len(header):
            raise InputFileError(path, f"line {n}: {len(row)} values for {len(header)} columns")
        pos = _position(path, f"line {n}: x, y, z", (values["x"], values["y"], values["z"]))
        if values.get("coordinates"):
            systems.add(values["coordinates"])
        extra = {k: v for k, v in values.items() if k not in ("label", "x", "y", "z", "coordinates")}
        points.append(MarkupPoint(values["label"] or f"P{len(points) + 1}", pos, columns=extra))
    if len(systems) > 1:
        raise InputFileError(path, f"column 'coordinates' names several systems: {', '.join(sorted(systems))}")
    return PointList(tuple(points), systems.pop() if systems else None)


def read_points(path) -> PointList:
    """The points of a ``.mrk.json``, ``.fcsv`` or ``.csv`` file (by its suffix), in the system it declares."""
    kind = point_format(path)
    return {"mrk.json": read_mrk_json, "fcsv": read_fcsv, "csv": read_csv}[kind](path)


# --------------------------------------------------------------------------- writing


def _fcsv_system(system: str | None) -> str:
    if system not in SLICER_SYSTEMS:
        raise ChicRegisterError(f"a Slicer point file is LPS or RAS, not {system!r}")
    return system


def mrk_json_text(points: PointList) -> str:
    """Slicer's markups JSON (one Fiducial markup) of a point list in LPS or RAS."""
    system = _fcsv_system(points.coordinate_system)
    cps = [{"id": str(i + 1), "label": p.label, "description": p.description,
            "position": [float(v) for v in p.position_mm], "positionStatus": "defined", "locked": True,
            "visibility": True} for i, p in enumerate(points.points)]
    doc = {"@schema": MARKUPS_SCHEMA,
           "markups": [{"type": "Fiducial", "coordinateSystem": system, "coordinateUnits": "mm", "locked": True,
                        "labelFormat": "%N-%d", "controlPoints": cps}]}
    return json.dumps(doc, indent=2) + "\n"


def fcsv_text(points: PointList) -> str:
    """Slicer's fiducial CSV (version 4.11) of a point list in LPS or RAS."""
    system = _fcsv_system(points.coordinate_system)
    out = io.StringIO()
    out.write(f"# Markups fiducial file version = {FCSV_VERSION}\n# CoordinateSystem = {system}\n"
              f"# columns = {','.join(FCSV_COLUMNS)}\n")
    w = csv.writer(out, lineterminator="\n")
    for i, p in enumerate(points.points):
        w.writerow([f"vtkMRMLMarkupsFiducialNode_{i}", *(repr(float(v)) for v in p.position_mm), 0, 0, 0, 1, 1, 1, 1,
                    p.label, p.description, ""])
    return out.getvalue()


def csv_text(points: PointList) -> str:
    """CSV: ``label,x,y,z,coordinates`` then every further column of the points (in first-seen order)."""
    extra = list(dict.fromkeys(k for p in points.points for k in p.columns))
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(["label", "x", "y", "z", "coordinates", *extra])
    for p in points.points:
        w.writerow([p.label, *(repr(float(v)) for v in p.position_mm), points.coordinate_system or "",
                    *(_cell(p.columns.get(k, "")) for k in extra)])
    return out.getvalue()


def _cell(value) -> str:
    if isinstance(value, float):
        return repr(value)
    return str(value)


def point_file_text(points: PointList, path) -> str:
    """The text of ``points`` in the format ``path``'s suffix names."""
    kind = point_format(path)
    return {"mrk.json": mrk_json_text, "fcsv": fcsv_text, "csv": csv_text}[kind](points)


def write_points(points: PointList, path) -> Path:
    """Write ``points`` atomically in the format ``path``'s suffix names (a Slicer format needs LPS or RAS)."""
    return write_text(path, point_file_text(points, path))


def as_system(points: PointList, system: str) -> PointList:
    """A scanner point list (LPS or RAS) re-expressed in ``system`` (LPS or RAS): x and y negated when they differ."""
    src, dst = _fcsv_system(points.coordinate_system), _fcsv_system(system)
    if src == dst:
        return points
    return PointList(tuple(replace(p, position_mm=tuple(float(v) for v in np.asarray(p.position_mm) * _FLIP_LPS_RAS))
                           for p in points.points), dst)
