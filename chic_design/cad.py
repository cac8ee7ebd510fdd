"""The CAD model: body and caps as build123d parts, in frame F, in assembled position.

Every channel is a circle swept along a tube object of
:mod:`chic_register.model.tubes` (via :func:`centreline_edge`), so the printed
channels and ``geometry.yaml`` cannot disagree.

- :class:`FiducialBody`: the annulus ``inner_diameter..outer_diameter``,
  ``z = 0..length``, minus every channel. Channels run the full length and open
  at both end faces (each is swept a little past the faces along its own
  centreline, so the cut is clean and has no coplanar end disks).
- :class:`Cap`: a plate of ``thickness`` over one end face (the bore stays
  open) plus a skirt that slips over the outside of the body with a radial
  ``clearance`` (a glued slip fit). The plate touches the end face; the parts do
  not overlap. The top cap has one fill port over each channel opening.

The pure-math helpers (:func:`extended_tube`, :func:`channel_openings_xy`,
:func:`channel_volume_mm3`, :func:`annulus_volume_mm3`, :class:`CapDims`) need
no CAD kernel and are tested on their own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from build123d import (
    Align,
    Axis,
    BasePartObject,
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
    sweep,
)

from chic_register.model.geometry import FiducialGeometry
from chic_register.model.tubes import Tube

_BOTTOM = (Align.CENTER, Align.CENTER, Align.MIN)


# ---------------------------------------------------------------- pure math


def extended_tube(tube: Tube, ext_mm: float) -> Tube:
    """The same centreline continued by ``ext_mm`` (arc length) past both ends: ``tube.extended``.

    Sweeping the extended tube and cutting it with the body gives channels
    whose openings are exactly the tube's sections by the end-face planes.
    """
    return tube.extended(ext_mm)


def channel_openings_xy(geometry: FiducialGeometry, z_mm: float) -> dict[str, np.ndarray]:
    """Centre ``(x, y)`` (mm, shape (2,)) of every channel's opening in the end face at ``z_mm``.

    A helix's opening at the top is at angle ``theta0 + pitch * length``.
    """
    return {t.id: t.point_at_z(z_mm)[0, :2] for t in geometry.tubes}


def channel_volume_mm3(tube: Tube, z_lo_mm: float, z_hi_mm: float) -> float:
    """Fluid volume of one channel between two heights (mm^3): pi a^2 times the centreline length.

    Exact for a straight channel cut by parallel planes (Cavalieri), and for a
    helix to within its curvature (radius of curvature >> channel radius):
    ``tube.fluid_volume_mm3``. Overlaps with other channels are not subtracted
    (see :func:`annulus_volume_mm3`).
    """
    return tube.fluid_volume_mm3(z_lo_mm, z_hi_mm)


def annulus_volume_mm3(geometry: FiducialGeometry) -> float:
    """Volume of the body before the channels are cut (mm^3): an annulus, or a square frame."""
    b = geometry.body
    return (b.outline_area_mm2 - b.bore_area_mm2) * b.length


@dataclass(frozen=True)
class CapDims:
    """Named dimensions of a cap (mm), derived from the body and the spec's ``caps``.

    ``inner_radius`` = body bore radius; the skirt's inside is
    ``outer_diameter / 2 + clearance``, its wall ``skirt_wall``.
    """

    inner_radius: float
    body_radius: float
    thickness: float
    clearance: float
    skirt_height: float
    skirt_wall: float
    port_diameter: float

    @property
    def skirt_inner_radius(self) -> float:
        return self.body_radius + self.clearance

    @property
    def outer_radius(self) -> float:
        return self.skirt_inner_radius + self.skirt_wall

    @classmethod
    def from_spec(cls, spec, geometry: FiducialGeometry) -> "CapDims":
        c = spec.caps
        return cls(
            inner_radius=geometry.body.inner_diameter / 2,
            body_radius=geometry.body.outer_diameter / 2,
            thickness=c.thickness,
            clearance=c.clearance,
            skirt_height=c.skirt_height,
            skirt_wall=c.skirt_wall,
            port_diameter=c.fill_port_diameter,
        )

    def bbox(self, length_mm: float, end: str) -> tuple[np.ndarray, np.ndarray]:
        """Expected axis-aligned bounding box (min (3,), max (3,)) of the cap at ``end``."""
        r = self.outer_radius
        if end == "top":
            z = (length_mm - self.skirt_height, length_mm + self.thickness)
        else:
            z = (-self.thickness, self.skirt_height)
        return np.array([-r, -r, z[0]]), np.array([r, r, z[1]])


# ---------------------------------------------------------------- CAD


class _EdgeBuilder:
    """Makes the build123d edge a tube asks for in :meth:`~chic_register.model.tubes.Tube.sweep_path`."""

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
    ext = ext_mm
    path = centreline_edge(extended_tube(tube, ext))
    profile = Plane(origin=path @ 0, z_dir=path % 0) * Circle(tube.diameter / 2)
    return sweep(profile, path, is_frenet=True)


class FiducialBody(BasePartObject):
    """The CHIC body: annulus from ``geometry.body`` minus every channel of ``geometry.tubes``.

    Args:
        geometry: tube centrelines and body dimensions in frame F.
    """


    def __init__(self, geometry: FiducialGeometry, mode: Mode = Mode.ADD):
        b = geometry.body
        solid = Cylinder(b.outer_diameter / 2, b.length, align=_BOTTOM)
        solid -= Cylinder(b.inner_diameter / 2, b.length, align=_BOTTOM)
        solid -= [channel_solid(t) for t in geometry.tubes]
        super().__init__(part=solid, rotation=(0, 0, 0), align=None, mode=mode)
        self.label = "body"


def place_cap(plate: Part, skirt: Part, dims, length_mm: float, end: str, ports_xy=()) -> Part:
    """A cap from its ``plate`` and ``skirt`` (both made at z = 0 upward), put at ``end``, ports drilled.

    The plate lies on the end face (outside the body), the skirt reaches
    ``dims.skirt_height`` along the body; ports of ``dims.port_diameter`` go
    through the plate at ``ports_xy``. Shared by the CHIC and Z-frame caps.
    """
    if end not in ("top", "bottom"):
        raise ValueError(f"end must be 'top' or 'bottom', got {end!r}")
    d = dims
    if end == "top":
        solid = Pos(0, 0, length_mm) * plate + Pos(0, 0, length_mm - d.skirt_height) * skirt
        z_plate = length_mm
    else:
        solid = Pos(0, 0, -d.thickness) * plate + skirt
        z_plate = -d.thickness
    if d.port_diameter > 0 and len(ports_xy):
        solid -= [
            Pos(float(x), float(y), z_plate) * Cylinder(d.port_diameter / 2, d.thickness, align=_BOTTOM)
            for x, y in ports_xy
        ]
    return solid


def assemble_parts(body: Part, cap_class, dims, geometry: FiducialGeometry, ports_xy) -> "FiducialParts":
    """Body plus a top cap with ``ports_xy`` and a solid bottom cap of ``cap_class(dims, ...)``."""
    length = geometry.body.length
    return FiducialParts(body=body, cap_top=cap_class(dims, length, "top", ports_xy=ports_xy),
                         cap_bottom=cap_class(dims, length, "bottom"))


class Cap(BasePartObject):
    """An end cap: plate over the end face at ``end`` ("top" z = length, "bottom" z = 0) plus skirt.

    Args:
        dims: cap dimensions.
        length_mm: body length (where the top end face is).
        end: "top" or "bottom".
        ports_xy: fill-port centres (mm, each (x, y)); drilled through the plate
            with ``dims.port_diameter``; empty for a solid cap.
    """


    def __init__(self, dims: CapDims, length_mm: float, end: str, ports_xy=(), mode: Mode = Mode.ADD):
        d = dims
        plate = Cylinder(d.outer_radius, d.thickness, align=_BOTTOM)
        plate -= Cylinder(d.inner_radius, d.thickness, align=_BOTTOM)
        skirt = Cylinder(d.outer_radius, d.skirt_height, align=_BOTTOM)
        skirt -= Cylinder(d.skirt_inner_radius, d.skirt_height, align=_BOTTOM)
        solid = place_cap(plate, skirt, d, length_mm, end, ports_xy)
        super().__init__(part=solid, rotation=(0, 0, 0), align=None, mode=mode)
        self.label = f"cap_{end}"


@dataclass(frozen=True)
class FiducialParts:
    """The three printed parts, in F, assembled."""

    body: Part
    cap_top: Part
    cap_bottom: Part

    def items(self) -> tuple[tuple[str, Part], ...]:
        return (("body", self.body), ("cap_top", self.cap_top), ("cap_bottom", self.cap_bottom))

    def assembly(self, name: str) -> Compound:
        """A compound with the three labelled parts as children (for ``assembly.step``)."""
        return Compound(label=name, children=[p for _, p in self.items()])


def build_parts(spec, geometry: FiducialGeometry) -> FiducialParts:
    """Body, top cap (one fill port over each channel's top opening) and bottom cap (solid)."""
    dims = CapDims.from_spec(spec, geometry)
    ports = list(channel_openings_xy(geometry, geometry.body.length).values())
    return assemble_parts(FiducialBody(geometry), Cap, dims, geometry, ports)
