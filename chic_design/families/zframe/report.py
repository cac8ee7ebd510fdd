"""The Z-frame part of ``report.md``: title, frame F in words and the dimension table."""

from __future__ import annotations

from chic_design.cad.channels import fill_ports_xy
from chic_design.families.base import ReportHead
from chic_design.families.zframe.spec import ZFrameSpec
from chic_register.model.geometry import FiducialGeometry


def zframe_report_head(spec: ZFrameSpec, geometry: FiducialGeometry, dims) -> ReportHead:
    """The Z-frame build's head; ``dims``: its caps' :class:`~chic_design.families.zframe.cad.SquareCapDims`."""
    b = geometry.body
    ports = len(fill_ports_xy(geometry)) if dims.port_diameter > 0 else 0
    rows = (
        f"| rod spacing (side) / height | {spec.frame.side:g} / {spec.frame.height:g} mm |",
        f"| frame outside / bore (square) | {b.outer_side:g} / {b.inner_side:g} mm (walls {spec.frame.wall:g} mm) |",
        f"| rod diameter | {spec.rods.diameter:g} mm |",
        f"| diagonal rods on faces | {', '.join(spec.diagonals.faces)}"
        + (f" (reversed: {', '.join(spec.diagonals.reversed_faces)})" if spec.diagonals.reversed_faces else "")
        + " |",
        f"| cap plate thickness | {dims.thickness:g} mm |",
        f"| cap skirt: inner side / wall / height | {dims.skirt_inner_side:g} / {dims.skirt_wall:g} / "
        f"{dims.skirt_height:g} mm (clearance {dims.clearance:g} mm per side) |",
        f"| fill ports (top cap) | {ports} x {dims.port_diameter:g} mm (a diagonal shares its corner's port) |",
        f"| assembled height | {b.length + 2 * dims.thickness:g} mm |",
    )
    frame = ("mm; origin on the frame's central axis in the bottom face, +z along the axial rods, "
             "x and y as in Slicer's Z-frame z001: a pose differs from z001's by half the height along z")
    return ReportHead("Z-frame fiducial", frame, rows)
