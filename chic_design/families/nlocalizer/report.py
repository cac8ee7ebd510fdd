"""The N-localizer part of ``report.md``: title, frame F in words and the dimension table."""

from __future__ import annotations

from chic_design.cad.channels import fill_ports_xy
from chic_design.families.base import ReportHead
from chic_design.families.nlocalizer.spec import NLocalizerSpec
from chic_register.model.geometry import FiducialGeometry

FRAME_TEXT = ("mm; origin at the centre of the box's bottom face, +z along the vertical rods; for the Leksell "
              "presets x = patient Left, y = Posterior, z = Superior for a head-first supine patient (the "
              "scanner's LPS axes), z = 0 the box's inferior edge")


def nlocalizer_report_head(spec: NLocalizerSpec, geometry: FiducialGeometry, dims) -> ReportHead:
    """The N-localizer build's head; ``dims``: its caps' :class:`~chic_design.families.nlocalizer.cad.BoxCapDims`,
    or None for commercial hardware (no parts)."""
    b = geometry.body
    plates = "; ".join(f"{p.name}: azimuth {p.azimuth_deg:g} deg, distance {p.distance:g}, width {p.width:g} mm, "
                       f"diagonal from the {p.diagonal_from} end" for p in spec.plates)
    (ox, oy), (ix, iy) = b.outer_size, b.inner_size
    rows = [
        f"| hardware | {spec.hardware} |",
        f"| plates | {plates} |",
        f"| rod height / diameter | {spec.frame.height:g} / {spec.rods.diameter:g} mm |",
        f"| frame outside / bore (x by y) | {ox:g} x {oy:g} / {ix:g} x {iy:g} mm (walls {spec.frame.wall:g} mm) |",
        f"| edge rods | {'yes (along each plate at z = 0 and z = height)' if spec.edge_rods else 'none'} |",
    ]
    fc = geometry.frame_coordinates
    if fc is not None:
        rows.append(f"| frame coordinates | {fc.system}: {fc.axes or 'see geometry.yaml'} |")
    if dims is not None:
        ports = len(fill_ports_xy(geometry)) if dims.port_diameter > 0 else 0
        sx, sy = dims.skirt_inner_size
        rows += [
            f"| cap plate thickness | {dims.thickness:g} mm |",
            f"| cap skirt: inner size / wall / height | {sx:g} x {sy:g} / {dims.skirt_wall:g} / "
            f"{dims.skirt_height:g} mm (clearance {dims.clearance:g} mm per side) |",
            f"| fill ports (top cap) | {ports} x {dims.port_diameter:g} mm (a diagonal shares its rod's port) |",
            f"| assembled height | {b.length + 2 * dims.thickness:g} mm |",
        ]
    return ReportHead("N-localizer", FRAME_TEXT, tuple(rows))
