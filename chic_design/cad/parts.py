"""The CAD model of any family: a body with swept channels and two caps, as build123d parts in frame F.

Every channel is a circle swept along a tube object of
:mod:`chic_register.model.geometry` (via :func:`centreline_edge`), so the
printed channels and ``geometry.yaml`` cannot disagree. A family supplies only
its shape: the body *blank* (the solid before the channels are cut) and its
:class:`CapDims` (how to make a cap's plate and skirt); :func:`build_parts`
makes the rest the same way for every family:

- :class:`ChannelledBody`: the blank minus every channel. Channels run the
  full length and open at both end faces (each is swept a little past the
  faces along its own centreline, so the cut is clean and has no coplanar end disks).
- :class:`Cap`: a plate of ``thickness`` over one end face (the bore stays
  open) plus a skirt that slips over the outside of the body with a
  ``clearance`` (a glued slip fit). The plate touches the end face; the parts
  do not overlap. The top cap has a fill port over each channel opening.
"""

from __future__ import annotations

import dataclasses
import math
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from build123d import (
    Align,
    Axis,
    BasePartObject,
    Box,
    Circle,
    Compound,
    Cylinder,
    Edge,
    Helix,
    Line,
    Mode,
    Part,
    Plane,
    Pos,
    Rot,
    sweep,
)

from chic_design.cad import PART_NAMES
from chic_design.cad.channels import channel_openings_xy, distinct_points, extended_tube, fill_ports_xy
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.tubes import Tube

#: Centred in x and y, standing on z = 0: how every blank, plate and skirt is made.
ALIGN_BOTTOM = (Align.CENTER, Align.CENTER, Align.MIN)

class _EdgeBuilder:
    """Makes the build123d edge a tube asks for in :meth:`~chic_register.model.geometry.Tube.sweep_path`."""

    @staticmethod
    def line(p0, p1) -> Edge:
        return Line(p0, p1)

    @staticmethod
    def helix(pitch: float, height: float, radius: float, lefthand: bool, theta0_deg: float, z0: float) -> Edge:
        """build123d's Helix starts at ``(radius, 0, 0)``: rotated to ``theta0_deg``, moved to ``z0``."""
        helix = Helix(pitch=pitch, height=height, radius=radius, lefthand=lefthand)
        return helix.rotate(Axis.Z, theta0_deg).translate((0, 0, z0))


def centreline_edge(tube: Tube) -> Edge:
    """A tube's centreline as a build123d edge: a :class:`Line` or a :class:`Helix`, in F.

    build123d's Helix starts at ``(radius, 0, 0)`` turning counter-clockwise
    (clockwise if ``lefthand``); it is rotated to ``theta0_deg`` and moved to ``z0``.
    """
    return tube.sweep_path(_EdgeBuilder)


def channel_solid(tube: Tube, ext_mm: float | None = None) -> Part:
    """The channel of ``tube``: its circle swept along its (extended) centreline.

    The default extension, one diameter in z past each end face, puts the swept
    end disk (z-extent <= its radius) wholly outside the body.
    """
    if ext_mm is None:  # one diameter past each end face, in z
        cos_min = float(np.min(np.abs(tube.tangents(np.linspace(0.0, 1.0, 9))[:, 2])))
        ext_mm = tube.diameter / max(cos_min, 1e-3)
    path = centreline_edge(extended_tube(tube, ext_mm))
    profile = Plane(origin=path @ 0, z_dir=path % 0) * Circle(tube.diameter / 2)
    return sweep(profile, path, is_frenet=True)


@dataclass(frozen=True)
class CapDims(ABC):
    """Named dimensions of a cap (mm) from the spec's ``caps``; a family's subclass adds its shape.

    The subclass holds the sizes of its outline (radii, sides) and makes the
    cap's two rings, both standing on z = 0 (:data:`ALIGN_BOTTOM`).
    """

    thickness: float
    clearance: float
    skirt_height: float
    skirt_wall: float
    port_diameter: float

    @abstractmethod
    def plate(self) -> Part:
        """The plate: ``thickness`` high, over the body's end face, the bore left open."""

    @abstractmethod
    def skirt(self) -> Part:
        """The skirt: ``skirt_height`` high, around the body's outside with ``clearance``."""


class ChannelledBody(BasePartObject):
    """The body: a family's ``blank`` minus the channel of every tube of ``geometry``.

    Args:
        blank: the body's solid before any channel is cut, in F.
        geometry: tube centrelines in frame F.
    """

    def __init__(self, blank: Part, geometry: FiducialGeometry, mode: Mode = Mode.ADD):
        solid = blank
        solid -= [channel_solid(t) for t in geometry.tubes]
        super().__init__(part=solid, rotation=(0, 0, 0), align=None, mode=mode)
        self.label = "body"


class Cap(BasePartObject):
    """An end cap: plate over the end face at ``end`` ("top" z = length, "bottom" z = 0) plus skirt.

    Args:
        dims: cap dimensions (and shape).
        length_mm: body length (where the top end face is).
        end: "top" or "bottom".
        ports_xy: fill-port centres (mm, each (x, y)); drilled through the plate
            with ``dims.port_diameter``; empty for a solid cap.
    """

    def __init__(self, dims: CapDims, length_mm: float, end: str, ports_xy=(), mode: Mode = Mode.ADD):
        if end not in ("top", "bottom"):
            raise ValueError(f"end must be 'top' or 'bottom', got {end!r}")
        d = dims
        plate, skirt = d.plate(), d.skirt()
        if end == "top":
            solid = Pos(0, 0, length_mm) * plate + Pos(0, 0, length_mm - d.skirt_height) * skirt
            z_plate = length_mm
        else:
            solid = Pos(0, 0, -d.thickness) * plate + skirt
            z_plate = -d.thickness
        if d.port_diameter > 0 and len(ports_xy):
            solid -= [
                Pos(float(x), float(y), z_plate) * Cylinder(d.port_diameter / 2, d.thickness, align=ALIGN_BOTTOM)
                for x, y in ports_xy
            ]
        super().__init__(part=solid, rotation=(0, 0, 0), align=None, mode=mode)
        self.label = f"cap_{end}"


@dataclass(frozen=True)
class FiducialParts:
    """The three printed parts, in F, assembled, and the cap dimensions they were made with."""

    body: Part
    cap_top: Part
    cap_bottom: Part
    cap_dims: CapDims

    def items(self) -> tuple[tuple[str, Part], ...]:
        return tuple((name, getattr(self, name)) for name in PART_NAMES)

    def assembly(self, name: str) -> Compound:
        """A compound with the three labelled parts as children (for ``assembly.step``)."""
        return Compound(label=name, children=[p for _, p in self.items()])


def build_parts(blank: Part, cap_dims: CapDims, geometry: FiducialGeometry) -> FiducialParts:
    """Body (``blank`` minus the channels), top cap with a fill port over each opening, solid bottom cap."""
    length = geometry.body.length
    body = ChannelledBody(blank, geometry)
    return FiducialParts(body=body, cap_top=Cap(cap_dims, length, "top", ports_xy=fill_ports_xy(geometry)),
                         cap_bottom=Cap(cap_dims, length, "bottom"), cap_dims=cap_dims)


#: Resin vents: a groove in the body's bottom end face from each channel opening out through the side wall.
#: On a resin printer that face lies on the build plate, which seals every channel's lower end: at each peel
#: the channel is a cup under suction. The groove lets air in; the bottom cap's glue fills it afterwards.
VENT_WIDTH_MM = 1.0
VENT_DEPTH_MM = 0.6


def vent_grooves(geometry: FiducialGeometry) -> list[Part]:
    """One groove (``VENT_WIDTH_MM`` wide, ``VENT_DEPTH_MM`` deep from z = 0) per distinct channel opening in the
    bottom face, running radially outward from the opening's centre to beyond the body's outside."""
    b = geometry.body
    h = b.outer_half_mm
    reach = (float(np.hypot(*h)) if h is not None else b.outer_diameter / 2) + 2.0
    grooves = []
    for xy in distinct_points(channel_openings_xy(geometry, 0.0).values()):
        r = float(np.hypot(*xy))
        angle = math.degrees(math.atan2(xy[1], xy[0]))
        length = reach - r
        box = Box(length, VENT_WIDTH_MM, VENT_DEPTH_MM, align=(Align.MIN, Align.CENTER, Align.MIN))
        grooves.append(Pos(float(xy[0]), float(xy[1]), 0.0) * (Rot(0, 0, angle) * box))
    return grooves


def with_resin_vents(parts: FiducialParts, geometry: FiducialGeometry) -> FiducialParts:
    """``parts`` with the body's vent grooves cut (:func:`vent_grooves`), for a resin printer."""
    body = parts.body - vent_grooves(geometry)
    body.label = "body"
    return dataclasses.replace(parts, body=body)
