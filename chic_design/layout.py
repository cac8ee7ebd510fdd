"""From a spec to the tube centrelines in frame F: the fiducial's geometry model.

The CAD channels, the geometry file and the feasibility checks are all made
from the :class:`~chic_register.model.geometry.FiducialGeometry` built here.
"""

from __future__ import annotations

import math

from chic_register.version import __version__
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.body import Body, ToolFrame
from chic_register.model.tubes import HelixTube, LineTube

from .spec import Spec, quadrant_bounds_deg


def helix_tube(spec: Spec, k: int) -> HelixTube:
    """Helix ``Hk`` in quadrant ``spec.markers.helix_quadrants[k]``.

    With the default pitch the helix runs from ``offset_deg`` past the
    quadrant's first diametric tube at z = 0 to ``offset_top_deg`` before the
    next one at z = length. A given negative pitch runs the other way: from
    ``offset_deg`` before the quadrant's end at z = 0.
    """
    q = spec.markers.helix_quadrants[k]
    lo, hi = quadrant_bounds_deg(spec.markers.diametric_deg, q)
    length = spec.body.length
    off_bottom = spec.helix.offset_deg
    if spec.helix.pitch_deg_per_mm is None:
        off_top = spec.helix.offset_top_deg if spec.helix.offset_top_deg is not None else off_bottom
        pitch = (hi - lo - off_bottom - off_top) / length
        theta0 = lo + off_bottom
    else:
        pitch = spec.helix.pitch_deg_per_mm
        theta0 = lo + off_bottom if pitch > 0 else hi - off_bottom
    return HelixTube(
        id=f"H{k}",
        role="helix",
        radius=spec.channel_radius,
        theta0_deg=theta0 % 360.0,
        pitch_deg_per_mm=pitch,
        z0=0.0,
        z1=length,
        diameter=spec.channels.diameter,
    )


def axial_line(tube_id: str, role: str, angle_deg: float, spec: Spec) -> LineTube:
    """A straight channel parallel to the axis at ``angle_deg`` on the channel circle."""
    r = spec.channel_radius
    a = math.radians(angle_deg)
    x, y = r * math.cos(a), r * math.sin(a)
    # exact zeros keep the file readable (cos(90 deg) is 6e-17, not 0)
    x, y = (0.0 if abs(v) < 1e-12 else v for v in (x, y))
    return LineTube(tube_id, role, (x, y, 0.0), (x, y, spec.body.length), spec.channels.diameter)


def fiducial_geometry(spec: Spec, source: dict | None = None) -> FiducialGeometry:
    """The geometry model of a spec: D0..D3, H0..H2, O0.. in frame F."""
    tubes = [axial_line(f"D{i}", "diametric", a, spec) for i, a in enumerate(spec.markers.diametric_deg)]
    tubes += [helix_tube(spec, k) for k in range(len(spec.markers.helix_quadrants))]
    tubes += [axial_line(f"O{j}", "orientation", a, spec) for j, a in enumerate(spec.markers.orientation_deg)]
    body = Body(spec.body.length, spec.body.outer_diameter, spec.body.inner_diameter)
    if source is not None:
        source = {**source, "generator": f"chic-design {__version__}"}
    return FiducialGeometry(spec.name, body, tuple(tubes), source, tool=spec_tool_frame(spec))


def spec_tool_frame(spec) -> ToolFrame | None:
    """The tool frame of a spec's optional ``tool`` section (any family), or None."""
    if getattr(spec, "tool", None) is None:
        return None
    if spec.tool.tip_offset_mm is not None:
        return ToolFrame.tip_offset(spec.tool.tip_offset_mm)
    return ToolFrame(spec.tool.T_fiducial_from_tool)


def design_geometry(spec, source: dict | None = None) -> FiducialGeometry:
    """The geometry model of any spec family: CHIC (:func:`fiducial_geometry`) or Z-frame."""
    if getattr(spec, "family", "chic") == "zframe":
        from .zframe_layout import zframe_geometry

        return zframe_geometry(spec, source)
    return fiducial_geometry(spec, source)
