"""From a CHIC spec to its tube centrelines in frame F: D0..D3, H0..H2, O0.. (paper Fig. 1).

The CAD channels, the geometry file and the feasibility checks are all made
from these tube objects.
"""

from __future__ import annotations

import math

from chic_design.families.chic.spec import ChicSpec, quadrant_bounds_deg
from chic_register.model.body import Body
from chic_register.model.tubes import HelixTube, LineTube, Tube


def helix_tube(spec: ChicSpec, k: int) -> HelixTube:
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


def axial_line(tube_id: str, role: str, angle_deg: float, spec: ChicSpec) -> LineTube:
    """A straight channel parallel to the axis at ``angle_deg`` on the channel circle."""
    r = spec.channel_radius
    a = math.radians(angle_deg)
    x, y = r * math.cos(a), r * math.sin(a)
    # exact zeros keep the file readable (cos(90 deg) is 6e-17, not 0)
    x, y = (0.0 if abs(v) < 1e-12 else v for v in (x, y))
    return LineTube(tube_id, role, (x, y, 0.0), (x, y, spec.body.length), spec.channels.diameter)


def chic_tubes(spec: ChicSpec) -> tuple[Tube, ...]:
    """D0..D3 (diametric), H0..H2 (helices), O0.. (orientation), in that order."""
    tubes = [axial_line(f"D{i}", "diametric", a, spec) for i, a in enumerate(spec.markers.diametric_deg)]
    tubes += [helix_tube(spec, k) for k in range(len(spec.markers.helix_quadrants))]
    tubes += [axial_line(f"O{j}", "orientation", a, spec) for j, a in enumerate(spec.markers.orientation_deg)]
    return tuple(tubes)


def chic_body(spec: ChicSpec) -> Body:
    """The annular body."""
    return Body(spec.body.length, spec.body.outer_diameter, spec.body.inner_diameter)
