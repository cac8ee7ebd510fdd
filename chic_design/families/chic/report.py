"""The CHIC part of ``report.md``: title, frame F in words and the dimension table."""

from __future__ import annotations

from chic_design.cad.channels import fill_ports_xy
from chic_design.families.base import ReportHead
from chic_design.families.chic.spec import ChicSpec
from chic_register.model.geometry import FiducialGeometry


def chic_report_head(spec: ChicSpec, geometry: FiducialGeometry, dims) -> ReportHead:
    """The CHIC build's head; ``dims`` are its round caps' :class:`~chic_design.families.chic.cad.RoundCapDims`."""
    b = geometry.body
    ports = len(fill_ports_xy(geometry)) if dims.port_diameter > 0 else 0
    rows = (
        f"| body length | {b.length:g} mm |",
        f"| outer / inner diameter | {b.outer_diameter:g} / {b.inner_diameter:g} mm |",
        f"| channel diameter | {spec.channels.diameter:g} mm |",
        f"| channel circle diameter | {2 * spec.channel_radius:g} mm |",
        f"| cap plate thickness | {dims.thickness:g} mm |",
        f"| cap skirt: inner diameter / wall / height | {2 * dims.skirt_inner_radius:g} / {dims.skirt_wall:g} / "
        f"{dims.skirt_height:g} mm (radial clearance {dims.clearance:g} mm) |",
        f"| fill ports (top cap) | {ports} x {dims.port_diameter:g} mm |",
        f"| assembled height | {b.length + 2 * dims.thickness:g} mm |",
    )
    frame = "mm; origin on the axis in the bottom end face, +z to the top face, +x toward D0"
    return ReportHead("CHIC fiducial", frame, rows)
