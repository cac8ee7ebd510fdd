"""``plate.3mf``: the parts laid on the printer's bed in their print orientation, as a PrusaSlicer project.

Read and written here together. The body stands on its bottom end face, turned
about its axis so that the rear of its outer wall (where the slicer puts the
seam) is as far as it can be from every channel; the caps lie plate-down (the
top cap turned over). Each part's mesh is stored in frame F and placed by its
build item's transform, so :func:`read_plate` gives back exactly where every
channel is on the bed. The project carries the slicer settings
(``Metadata/Slic3r_PE.config``) and the part names (``Metadata/Slic3r_PE_model.config``).
"""

from __future__ import annotations

import io
import json
import math
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from xml.etree import ElementTree as ET

import numpy as np

from chic_design.errors import PrintFileError
from chic_design.printing.settings import PrintSettings, prusa_config
from chic_register.model.geometry import FiducialGeometry

#: Gap between parts on the bed (mm): room for the skirt line and the nozzle's travel.
PART_GAP_MM = 10.0
#: Heights (mm) at which the seam's distance from the channels is judged, as shares of the body length.
SEAM_SAMPLES = 41
#: The project's own part of the 3MF (slicers ignore it): what the print check needs besides the parts.
INFO_NAME = "Metadata/chic_print.json"
CORE_NS = "http://schemas.microsoft.com/3dmanufacturing/core/2015/02"
SLIC3R_NS = "http://schemas.slic3r.org/3mf/2017/06"
CONTENT_TYPES = ('<?xml version="1.0" encoding="UTF-8"?>\n'
                 '<Types xmlns="http://schemas.openxmlformats.org/package/2006/content-types">'
                 '<Default Extension="rels" ContentType="application/vnd.openxmlformats-package.relationships+xml"/>'
                 '<Default Extension="model" ContentType="application/vnd.ms-package.3dmanufacturing-3dmodel+xml"/>'
                 '</Types>\n')
RELS = ('<?xml version="1.0" encoding="UTF-8"?>\n'
        '<Relationships xmlns="http://schemas.openxmlformats.org/package/2006/relationships">'
        '<Relationship Target="/3D/3dmodel.model" Id="rel-1" '
        'Type="http://schemas.microsoft.com/3dmanufacturing/2013/01/3dmodel"/></Relationships>\n')


@dataclass(frozen=True)
class Placement:
    """Where one part lies on the bed: ``T_bed_from_F`` (4, 4) maps its frame-F points to bed mm."""

    name: str
    T_bed_from_F: np.ndarray

    def to_bed(self, points_mm) -> np.ndarray:
        """Frame-F points (N, 3) in bed coordinates (N, 3), mm."""
        p = np.atleast_2d(np.asarray(points_mm, dtype=float))
        return p @ self.T_bed_from_F[:3, :3].T + self.T_bed_from_F[:3, 3]


@dataclass(frozen=True)
class Plate:
    """A print plate: the placed parts, the slicer configuration, the bed (mm) it was laid out on.

    ``info`` is what the print check needs beyond the parts (``Metadata/chic_print.json``):
    the design, its settings and reasons, the top cap's fill ports.
    """

    placements: tuple[Placement, ...]
    config: dict[str, str]
    bed_mm: tuple[float, float]
    fits_bed: bool
    info: dict = field(default_factory=dict)

    def placement(self, name: str) -> Placement:
        for p in self.placements:
            if p.name == name:
                return p
        raise KeyError(name)


def _rot_z(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


FLIP_X = np.diag([1.0, -1.0, -1.0])  # a half turn about x: the top cap's plate goes down


def seam_angle_deg(geometry: FiducialGeometry) -> float:
    """The direction in F (deg from +x, about z) farthest, at every height, from every channel's centre.

    The slicer puts each loop's seam at its rear (+y of the bed); turning the
    body so this direction faces the rear keeps the outer wall's seam off the
    thin wall over a channel.
    """
    z = np.linspace(0.0, geometry.body.length, SEAM_SAMPLES)
    angles = np.concatenate([np.degrees(np.arctan2(p[:, 1], p[:, 0]))
                             for p in (t.point_at_z(z) for t in geometry.tubes)])
    candidates = np.arange(0.0, 360.0, 0.5)
    gap = np.abs((candidates[:, None] - angles[None, :] + 180.0) % 360.0 - 180.0).min(axis=1)
    return float(candidates[int(np.argmax(gap))])


def print_rotations(geometry: FiducialGeometry) -> dict[str, np.ndarray]:
    """Each part's rotation (3, 3) from F into its print orientation."""
    body = _rot_z(90.0 - seam_angle_deg(geometry))
    return {"body": body, "cap_top": FLIP_X, "cap_bottom": np.eye(3)}


def lay_out(meshes: dict, geometry: FiducialGeometry, bed_mm: tuple[float, float]
            ) -> tuple[tuple[Placement, ...], tuple[float, float], bool]:
    """Placements of ``meshes`` (name -> vertices (N, 3) in F) in rows centred on the bed.

    Returns ``(placements, bed_mm, fits)``; where the parts do not fit, the bed
    is widened to hold them and ``fits`` is False (print them one at a time).
    """
    rotations = print_rotations(geometry)
    boxes = {}
    for name, v in meshes.items():
        r = np.asarray(v) @ rotations[name].T
        boxes[name] = (r.min(axis=0), r.max(axis=0))
    width = bed_mm[0]
    rows, row, row_w = [], [], 0.0
    for name in meshes:
        w = boxes[name][1][0] - boxes[name][0][0]
        if row and row_w + PART_GAP_MM + w > width:
            rows.append(row)
            row, row_w = [], 0.0
        row_w += (PART_GAP_MM if row else 0.0) + w
        row.append(name)
    rows.append(row)
    sizes = [(sum(boxes[n][1][0] - boxes[n][0][0] for n in r) + PART_GAP_MM * (len(r) - 1),
              max(boxes[n][1][1] - boxes[n][0][1] for n in r)) for r in rows]
    total_w = max(w for w, _ in sizes)
    total_h = sum(h for _, h in sizes) + PART_GAP_MM * (len(rows) - 1)
    fits = bool(total_w <= bed_mm[0] and total_h <= bed_mm[1])
    bed = bed_mm if fits else (max(bed_mm[0], total_w + 2 * PART_GAP_MM), max(bed_mm[1], total_h + 2 * PART_GAP_MM))
    placements = []
    y = (bed[1] + total_h) / 2
    for r, (w_row, h_row) in zip(rows, sizes):
        x = (bed[0] - w_row) / 2
        for name in r:
            lo, hi = boxes[name]
            T = np.eye(4)
            T[:3, :3] = rotations[name]
            # footprint's lower-left at (x, y - h_row), its lowest point on the bed (z = 0)
            T[:3, 3] = [x - lo[0], y - h_row / 2 - (lo[1] + hi[1]) / 2, -lo[2]]
            placements.append(Placement(name, T))
            x += hi[0] - lo[0] + PART_GAP_MM
        y -= h_row + PART_GAP_MM
    return tuple(placements), (float(bed[0]), float(bed[1])), fits


def _transform_text(T: np.ndarray) -> str:
    """3MF's row-vector 4x3 matrix (p' = p M) of the column-vector transform ``T``."""
    R, t = T[:3, :3], T[:3, 3]
    vals = list(R.T.reshape(-1)) + list(t)
    return " ".join(f"{v:.9g}" for v in vals)


def _parse_transform(text: str) -> np.ndarray:
    vals = np.array([float(v) for v in text.split()])
    T = np.eye(4)
    T[:3, :3] = vals[:9].reshape(3, 3).T
    T[:3, 3] = vals[9:12]
    return T


def _model_xml(meshes: dict, faces: dict, placements, title: str) -> bytes:
    out = io.StringIO()
    out.write('<?xml version="1.0" encoding="UTF-8"?>\n'
              f'<model unit="millimeter" xml:lang="en-US" xmlns="{CORE_NS}" xmlns:slic3rpe="{SLIC3R_NS}">\n'
              ' <metadata name="slic3rpe:Version3mf">1</metadata>\n'
              f' <metadata name="Title">{title}</metadata>\n'
              ' <metadata name="Application">chic-design</metadata>\n <resources>\n')
    for k, name in enumerate(meshes, start=1):
        out.write(f'  <object id="{k}" type="model">\n   <mesh>\n    <vertices>\n')
        out.writelines(f'     <vertex x="{x:.7g}" y="{y:.7g}" z="{z:.7g}"/>\n' for x, y, z in meshes[name])
        out.write('    </vertices>\n    <triangles>\n')
        out.writelines(f'     <triangle v1="{a}" v2="{b}" v3="{c}"/>\n' for a, b, c in faces[name])
        out.write('    </triangles>\n   </mesh>\n  </object>\n')
    out.write(' </resources>\n <build>\n')
    for k, p in enumerate(placements, start=1):
        out.write(f'  <item objectid="{k}" transform="{_transform_text(p.T_bed_from_F)}" printable="1"/>\n')
    out.write(' </build>\n</model>\n')
    return out.getvalue().encode("utf-8")


def _objects_config(meshes: dict, faces: dict) -> bytes:
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', "<config>"]
    for k, name in enumerate(meshes, start=1):
        lines += [f' <object id="{k}" instances_count="1">',
                  f'  <metadata type="object" key="name" value="{name}"/>',
                  f'  <volume firstid="0" lastid="{len(faces[name]) - 1}">',
                  f'   <metadata type="volume" key="name" value="{name}"/>',
                  '   <metadata type="volume" key="volume_type" value="ModelPart"/>',
                  "  </volume>", " </object>"]
    lines.append("</config>")
    return ("\n".join(lines) + "\n").encode("utf-8")


def config_text(config: dict[str, str]) -> str:
    """PrusaSlicer's ``; key = value`` lines (the format of its G-code footer and project config)."""
    return "; generated by chic-design\n\n" + "".join(f"; {k} = {v}\n" for k, v in sorted(config.items()))


def make_plate(meshes: dict, geometry: FiducialGeometry, settings: PrintSettings, info: dict | None = None) -> Plate:
    """Lay ``meshes`` (name -> vertices (N, 3) in F) out for ``settings``' printer; ``info`` goes into the project."""
    placements, bed, fits = lay_out(meshes, geometry, settings.bed_mm)
    info = {**(info or {}), "printer": settings.printer, "layer_mm": settings.layer_mm, "nozzle_mm": settings.nozzle_mm,
            "extrusion_width_mm": settings.extrusion_width_mm, "reasons": settings.reasons, "fits_bed": fits}
    return Plate(placements, prusa_config(settings, bed), bed, fits, info)


def write_plate(path, plate: Plate, meshes: dict, faces: dict, title: str) -> Path:
    """Write the project 3MF: meshes (name -> (N, 3) vertices, (M, 3) faces) placed as ``plate`` says."""
    path = Path(path)
    placed = [p.name for p in plate.placements]
    meshes = {n: meshes[n] for n in placed}
    faces = {n: faces[n] for n in placed}
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("[Content_Types].xml", CONTENT_TYPES)
        z.writestr("_rels/.rels", RELS)
        z.writestr("3D/3dmodel.model", _model_xml(meshes, faces, plate.placements, title))
        z.writestr("Metadata/Slic3r_PE.config", config_text(plate.config))
        z.writestr("Metadata/Slic3r_PE_model.config", _objects_config(meshes, faces))
        z.writestr(INFO_NAME, json.dumps(plate.info, indent=2))
    return path


def read_plate(path) -> Plate:
    """The placements, slicer configuration and print information of a plate written by :func:`write_plate`."""
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as z:
            model = ET.fromstring(z.read("3D/3dmodel.model"))
            objects = ET.fromstring(z.read("Metadata/Slic3r_PE_model.config"))
            config_lines = z.read("Metadata/Slic3r_PE.config").decode("utf-8").splitlines()
            info = json.loads(z.read(INFO_NAME))
        names = {o.get("id"): o.find("metadata[@key='name']").get("value") for o in objects.iter("object")}
        ns = {"m": CORE_NS}
        placements = tuple(Placement(names[item.get("objectid")], _parse_transform(item.get("transform")))
                           for item in model.find("m:build", ns).findall("m:item", ns))
    except FileNotFoundError:
        raise PrintFileError(f"{path}: no such plate; chic-design build writes plate.3mf") from None
    except (OSError, zipfile.BadZipFile, KeyError, ET.ParseError, ValueError, AttributeError) as exc:
        raise PrintFileError(f"{path}: not a plate written by chic-design build ({exc})") from None
    config = {}
    for line in config_lines:
        if line.startswith("; ") and " = " in line:
            k, v = line[2:].split(" = ", 1)
            config[k.strip()] = v.strip()
    bed = [tuple(float(c) for c in xy.split("x")) for xy in config.get("bed_shape", "0x0").split(",")]
    bed_mm = (max(x for x, _ in bed), max(y for _, y in bed))
    return Plate(placements, config, bed_mm, bool(info.get("fits_bed", True)), info)
