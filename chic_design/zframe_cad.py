"""The Z-frame's CAD model: a square frame body and two caps, in frame F, assembled.

Same construction as the CHIC parts (:mod:`chic_design.cad`): every rod is a
circle swept along its tube object (:func:`chic_design.cad.channel_solid`,
extended past both end faces), so the printed channels and ``geometry.yaml``
cannot disagree.

- :class:`ZFrameBody`: the square ring ``inner_side..outer_side`` (walls of
  ``frame.wall`` centred on the rod planes), ``z = 0..height``, minus every rod.
  Rods open at both end faces; each diagonal meets the axial rods at its two
  corners there, so the seven channels form one network that fills from the top.
- :class:`SquareCap`: a plate of ``caps.thickness`` over one end face (the bore
  stays open) plus a skirt around the outside with a ``caps.clearance`` slip
  fit, as the CHIC caps. The top cap has one fill port over each distinct
  channel opening (a diagonal's opening at a corner shares the axial rod's port).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from build123d import Align, BasePartObject, Box, Mode

from chic_register.model.geometry import FiducialGeometry

from .cad import FiducialParts, assemble_parts, channel_openings_xy, channel_solid, place_cap

_BOTTOM = (Align.CENTER, Align.CENTER, Align.MIN)


@dataclass(frozen=True)
class SquareCapDims:
    """Named dimensions of a square cap (mm) from the body and the spec's ``caps``."""

    inner_side: float
    body_side: float
    thickness: float
    clearance: float
    skirt_height: float
    skirt_wall: float
    port_diameter: float

    @property
    def skirt_inner_side(self) -> float:
        return self.body_side + 2 * self.clearance

    @property
    def outer_side(self) -> float:
        return self.skirt_inner_side + 2 * self.skirt_wall

    @classmethod
    def from_spec(cls, spec, geometry: FiducialGeometry) -> "SquareCapDims":
        c = spec.caps
        return cls(geometry.body.inner_side, geometry.body.outer_side, c.thickness, c.clearance,
                   c.skirt_height, c.skirt_wall, c.fill_port_diameter)


def _square_ring(outer: float, inner: float, height: float):
    return Box(outer, outer, height, align=_BOTTOM) - Box(inner, inner, height, align=_BOTTOM)


class ZFrameBody(BasePartObject):
    """The Z-frame body: square ring from ``geometry.body`` minus every rod of ``geometry.tubes``."""

    def __init__(self, geometry: FiducialGeometry, mode: Mode = Mode.ADD):
        b = geometry.body
        solid = _square_ring(b.outer_side, b.inner_side, b.length)
        solid -= [channel_solid(t) for t in geometry.tubes]
        super().__init__(part=solid, rotation=(0, 0, 0), align=None, mode=mode)
        self.label = "body"


class SquareCap(BasePartObject):
    """An end cap of the square frame at ``end`` ("top": z = length, "bottom": z = 0)."""

    def __init__(self, dims: SquareCapDims, length_mm: float, end: str, ports_xy=(), mode: Mode = Mode.ADD):
        plate = _square_ring(dims.outer_side, dims.inner_side, dims.thickness)
        skirt = _square_ring(dims.outer_side, dims.skirt_inner_side, dims.skirt_height)
        solid = place_cap(plate, skirt, dims, length_mm, end, ports_xy)
        super().__init__(part=solid, rotation=(0, 0, 0), align=None, mode=mode)
        self.label = f"cap_{end}"


def distinct_points(points, tol_mm: float = 1e-6) -> list[np.ndarray]:
    """``points`` with (near) duplicates dropped, first occurrence kept."""
    out: list[np.ndarray] = []
    for p in points:
        if all(np.linalg.norm(p - q) > tol_mm for q in out):
            out.append(np.asarray(p))
    return out


def build_zframe_parts(spec, geometry: FiducialGeometry) -> FiducialParts:
    """Body, top cap (a fill port over each distinct rod opening) and bottom cap (solid)."""
    dims = SquareCapDims.from_spec(spec, geometry)
    ports = distinct_points(channel_openings_xy(geometry, geometry.body.length).values())
    return assemble_parts(ZFrameBody(geometry), SquareCap, dims, geometry, ports)
