"""The build's checks of its own output files, before it declares success.

Checks (each a named :class:`Check`):

- every STL (and 3MF) mesh is watertight, consistently wound and a volume;
- every mesh volume agrees with its CAD solid within :data:`VOLUME_REL_TOL`;
- cross-sections of ``body.stl`` at heights where no two channels touch
  (:func:`~chic_design.feasibility.sections.section_heights`) show exactly the bore plus one hole per tube of
  ``geometry.yaml``, each hole's centroid within :data:`CENTROID_TOL_MM` of
  ``tube.point_at_z(z)`` and its area within :data:`AREA_REL_TOL` of the
  channel's section ``pi a^2 / cos(tilt)``;
- the caps do not overlap the body, both as exact CAD solids and as meshes.

:func:`verify_export` runs them all and raises
:class:`~chic_design.errors.BuildCheckError` naming every failed check.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import manifold3d
import numpy as np
import trimesh

from chic_design.cad import PART_NAMES
from chic_design.errors import BuildCheckError
from chic_design.feasibility.sections import section_heights, tube_slope_cos
from chic_register.model.geometry import FiducialGeometry, load_geometry

#: Mesh vs CAD volume, for the export's tessellation (:data:`chic_design.cad.export.STL_TOLERANCE_MM`).
#: Facets inscribed in a circle of radius R with chord deviation delta span alpha = 2 acos(1 - delta / R) and lose alpha^2 / 6 of its area: 0.09 % for R = 15 mm,
#: 0.17 % for R = 8 mm at delta = 0.01 mm (measured: -0.06 % for the neuro body). 0.5 % leaves
#: headroom and still catches a missing or extra channel (one 3 mm channel is 2 % of the neuro
#: body, one 1.6 mm channel 1.5 % of the needle-guide body).
VOLUME_REL_TOL = 0.005
#: Hole centroid vs tube centreline: the printed channel must sit where geometry.yaml says; measured < 0.005 mm.
CENTROID_TOL_MM = 0.05
#: Hole area vs pi a^2 / cos(tilt): a 0.1 mm error in a 3 mm channel's diameter is 6.7 % in area.
AREA_REL_TOL = 0.03
#: Largest allowed cap/body intersection volume (mm^3) for solids that only touch.
OVERLAP_TOL_MM3 = 1e-3


@dataclass(frozen=True)
class Check:
    """One named output check: ``ok`` and a one-line ``detail`` with the measured value."""

    name: str
    ok: bool
    detail: str

    def to_dict(self) -> dict:
        return {"name": self.name, "ok": bool(self.ok), "detail": self.detail}


@dataclass(frozen=True)
class VerifyResult:
    """All checks of one export."""

    checks: tuple[Check, ...]
    section_heights_mm: tuple[float, ...] = ()

    @property
    def ok(self) -> bool:
        return all(c.ok for c in self.checks)

    @property
    def failed(self) -> tuple[Check, ...]:
        return tuple(c for c in self.checks if not c.ok)

    def raise_if_failed(self) -> None:
        if not self.ok:
            names = "; ".join(f"{c.name}: {c.detail}" for c in self.failed)
            raise BuildCheckError(f"{len(self.failed)} output check(s) failed: {names}")

    def markdown(self) -> str:
        lines = ["| check | result | detail |", "|---|---|---|"]
        lines += [f"| {c.name} | {'pass' if c.ok else 'FAIL'} | {c.detail} |" for c in self.checks]
        return "\n".join(lines)


def section_loops(mesh: trimesh.Trimesh, z_mm: float) -> list[tuple[float, np.ndarray]]:
    """Closed loops of the mesh's section by the plane ``z = z_mm``: ``[(|area| mm^2, centroid (2,))]``.

    Raises ValueError if the section has open (dangling) curves: a mesh with a hole.
    """
    sec = mesh.section(plane_origin=[0.0, 0.0, z_mm], plane_normal=[0.0, 0.0, 1.0])
    if sec is None:
        return []
    if len(sec.dangling):
        raise ValueError(f"section at z={z_mm:g} has {len(sec.dangling)} open curve(s)")
    out = []
    for loop in sec.discrete:
        x, y = loop[:, 0], loop[:, 1]
        x1, y1 = np.roll(x, -1), np.roll(y, -1)
        cross = x * y1 - x1 * y
        area = cross.sum() / 2
        if abs(area) < 1e-12:
            continue
        cx = ((x + x1) * cross).sum() / (6 * area)
        cy = ((y + y1) * cross).sum() / (6 * area)
        out.append((abs(float(area)), np.array([cx, cy])))
    return out


# ---------------------------------------------------------------- checks


def check_mesh(name: str, mesh: trimesh.Trimesh, cad_volume_mm3: float | None,
               rel_tol: float = VOLUME_REL_TOL) -> list[Check]:
    """Watertight, consistently wound, a volume; and its volume vs the CAD solid's."""
    checks = [
        Check(f"{name} watertight", bool(mesh.is_watertight), f"{len(mesh.faces)} faces"),
        Check(f"{name} winding consistent", bool(mesh.is_winding_consistent), ""),
        Check(f"{name} is a volume", bool(mesh.is_volume), "outward normals, positive volume"),
    ]
    if cad_volume_mm3 is not None:
        rel = (float(mesh.volume) - cad_volume_mm3) / cad_volume_mm3 if mesh.is_volume else float("nan")
        checks.append(Check(
            f"{name} volume matches CAD",
            bool(abs(rel) <= rel_tol),
            f"mesh {float(mesh.volume):.1f} mm^3 vs CAD {cad_volume_mm3:.1f} mm^3 "
            f"({100 * rel:+.3f} %, allowed +-{100 * rel_tol:g} %)",
        ))
    return checks


def check_body_sections(mesh: trimesh.Trimesh, geometry: FiducialGeometry, heights_mm,
                        name: str = "body.stl", tol_mm: float = CENTROID_TOL_MM) -> list[Check]:
    """At each height: loops = outer skin + bore + one per tube, each tube's hole where the file says."""
    checks = []
    body = geometry.body
    if len(heights_mm) == 0:
        return [Check(f"{name} sections", False, "no height where the channels are apart: cannot check")]
    for z in heights_mm:
        label = f"{name} section z={z:.2f}"
        try:
            loops = section_loops(mesh, z)
        except ValueError as exc:
            checks.append(Check(label, False, str(exc)))
            continue
        expected = len(geometry.tubes) + 2
        if len(loops) != expected:
            checks.append(Check(
                f"{label} hole count", False,
                f"{len(loops) - 1} holes, expected {expected - 1} ({len(geometry.tubes)} tubes + bore)",
            ))
            continue
        loops = sorted(loops, key=lambda l: -l[0])  # the outer skin encloses the largest area
        (a_out, c_out), inner = loops[0], loops[1:]
        k_bore = int(np.argmin([np.linalg.norm(c) for _, c in inner]))  # the bore is on the axis
        (a_in, c_in), holes = inner[k_bore], inner[:k_bore] + inner[k_bore + 1:]
        ring_ok = (
            np.linalg.norm(c_out) < tol_mm and np.linalg.norm(c_in) < tol_mm
            and abs(a_out / body.outline_area_mm2 - 1) < AREA_REL_TOL
            and abs(a_in / body.bore_area_mm2 - 1) < AREA_REL_TOL
        )
        if body.shape == "square":
            size = f"sides {math.sqrt(a_out):.3f} / {math.sqrt(a_in):.3f} mm"
        elif body.shape == "box":
            size = f"outline / bore areas {a_out:.1f} / {a_in:.1f} mm^2"
        else:
            size = f"diameters {2 * math.sqrt(a_out / math.pi):.3f} / {2 * math.sqrt(a_in / math.pi):.3f} mm"
        checks.append(Check(
            f"{label} outer wall and bore", bool(ring_ok),
            f"{size}, centres off axis by {np.linalg.norm(c_out):.4f} / {np.linalg.norm(c_in):.4f} mm",
        ))
        centroids = np.array([c for _, c in holes])
        areas = np.array([a for a, _ in holes])
        used: set[int] = set()
        for tube in geometry.tubes:
            want = tube.point_at_z(z)[0, :2]
            dist = np.linalg.norm(centroids - want, axis=1)
            k = int(np.argmin(dist))
            area_want = math.pi * (tube.diameter / 2) ** 2 / float(tube_slope_cos(tube, z)[0])
            area_rel = areas[k] / area_want - 1
            ok = dist[k] <= tol_mm and k not in used and abs(area_rel) <= AREA_REL_TOL
            used.add(k)
            checks.append(Check(
                f"{label} {tube.id}", bool(ok),
                f"hole centroid {dist[k]:.4f} mm from centreline (allowed {tol_mm:g}), "
                f"area {100 * area_rel:+.2f} % (allowed +-{100 * AREA_REL_TOL:g} %)",
            ))
    return checks


def _manifold(mesh: trimesh.Trimesh):
    return manifold3d.Manifold(manifold3d.Mesh(
        vert_properties=np.asarray(mesh.vertices, dtype=np.float32),
        tri_verts=np.asarray(mesh.faces, dtype=np.uint32),
    ))


def check_no_overlap(body_mesh: trimesh.Trimesh, cap_mesh: trimesh.Trimesh, cap_name: str,
                     cad_overlap_mm3: float | None = None) -> list[Check]:
    """The cap and the body share no volume (they only touch at the end face)."""
    checks = []
    if cad_overlap_mm3 is not None:
        checks.append(Check(
            f"{cap_name} does not overlap body (CAD)", bool(cad_overlap_mm3 <= OVERLAP_TOL_MM3),
            f"intersection {cad_overlap_mm3:.2e} mm^3 (allowed {OVERLAP_TOL_MM3:g})",
        ))
    vol = float((_manifold(body_mesh) ^ _manifold(cap_mesh)).volume())
    checks.append(Check(
        f"{cap_name} does not overlap body (mesh)", bool(vol <= OVERLAP_TOL_MM3),
        f"intersection {vol:.2e} mm^3 (allowed {OVERLAP_TOL_MM3:g})",
    ))
    return checks


def _load_stl(path: Path) -> trimesh.Trimesh:
    return trimesh.load_mesh(path, file_type="stl", process=True)


def _load_3mf(path: Path, part: str) -> tuple[trimesh.Trimesh | None, str]:
    scene = trimesh.load(path, file_type="3mf")
    geoms = getattr(scene, "geometry", {part: scene})
    if list(geoms) != [part]:
        return None, f"objects {list(geoms)}, expected ['{part}']"
    return next(iter(geoms.values())), ""


def verify_export(folder, cad_volumes_mm3: dict[str, float],
                  cad_overlaps_mm3: dict[str, float] | None = None,
                  n_sections: int = 5, raise_on_failure: bool = True, printed: bool = True) -> VerifyResult:
    """Check every part file in ``folder`` against ``geometry.yaml`` in it and the CAD volumes.

    ``printed=False`` (hardware described for the solver only): ``geometry.yaml`` alone, no part files.

    Args:
        folder: export folder with ``geometry.yaml`` and ``<part>.stl/.step/.3mf``.
        cad_volumes_mm3: ``{part: CAD solid volume}`` for body, cap_top, cap_bottom.
        cad_overlaps_mm3: ``{cap: exact CAD intersection volume with the body}`` (optional).
        n_sections: how many body sections to check.
        raise_on_failure: raise :class:`BuildCheckError` naming every failed check.
    """
    folder = Path(folder)
    checks: list[Check] = []
    geometry = load_geometry(folder / "geometry.yaml")
    checks.append(Check("geometry.yaml loads and its hash checks", True, f"{len(geometry.tubes)} tubes"))
    meshes: dict[str, trimesh.Trimesh] = {}
    for part in PART_NAMES if printed else ():
        for ext in ("stl", "step", "3mf"):
            path = folder / f"{part}.{ext}"
            if not path.is_file() or path.stat().st_size == 0:
                checks.append(Check(f"{part}.{ext} written", False, "missing or empty"))
        stl = folder / f"{part}.stl"
        if stl.is_file():
            meshes[part] = _load_stl(stl)
            checks += check_mesh(f"{part}.stl", meshes[part], cad_volumes_mm3.get(part))
        three = folder / f"{part}.3mf"
        if three.is_file():
            mesh, why = _load_3mf(three, part)
            if mesh is None:
                checks.append(Check(f"{part}.3mf named part", False, why))
            else:
                checks += check_mesh(f"{part}.3mf", mesh, cad_volumes_mm3.get(part))
    heights = section_heights(geometry, n_sections) if printed else ()
    if "body" in meshes:
        checks += check_body_sections(meshes["body"], geometry, heights)
        for cap in ("cap_top", "cap_bottom"):
            if cap in meshes and meshes[cap].is_volume and meshes["body"].is_volume:
                checks += check_no_overlap(meshes["body"], meshes[cap], cap,
                                           (cad_overlaps_mm3 or {}).get(cap))
    result = VerifyResult(tuple(checks), tuple(float(z) for z in heights))
    if raise_on_failure:
        result.raise_if_failed()
    return result
