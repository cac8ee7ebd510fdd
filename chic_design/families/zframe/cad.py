"""The Z-frame's shape for the CAD model: a square frame blank and square caps.

The frame is the square ring ``inner_side..outer_side`` (walls of
``frame.wall`` centred on the rod planes), ``z = 0..height``. The rods are
swept by the generic :func:`chic_design.cad.parts.build_parts`; each diagonal
meets the axial rods at its two corners in the end faces, so the seven
channels form one network that fills from the top, and a diagonal's opening
shares its corner rod's fill port.
"""

from __future__ import annotations

from dataclasses import dataclass

from build123d import Box, Part

from chic_design.cad.parts import ALIGN_BOTTOM, CapDims, FiducialParts, build_parts
from chic_register.model.geometry import FiducialGeometry


def square_ring(outer: float, inner: float, height: float) -> Part:
    """A square ring of outside width ``outer`` and bore ``inner``, ``z = 0..height``."""
    return Box(outer, outer, height, align=ALIGN_BOTTOM) - Box(inner, inner, height, align=ALIGN_BOTTOM)


@dataclass(frozen=True)
class SquareCapDims(CapDims):
    """A square cap: ``inner_side`` = the bore, the skirt's inside ``body_side + 2 clearance``."""

    inner_side: float
    body_side: float

    @property
    def skirt_inner_side(self) -> float:
        return self.body_side + 2 * self.clearance

    @property
    def outer_side(self) -> float:
        return self.skirt_inner_side + 2 * self.skirt_wall

    @classmethod
    def from_spec(cls, spec, geometry: FiducialGeometry) -> "SquareCapDims":
        c = spec.caps
        return cls(thickness=c.thickness, clearance=c.clearance, skirt_height=c.skirt_height,
                   skirt_wall=c.skirt_wall, port_diameter=c.fill_port_diameter,
                   inner_side=geometry.body.inner_side, body_side=geometry.body.outer_side)

    def plate(self) -> Part:
        return square_ring(self.outer_side, self.inner_side, self.thickness)

    def skirt(self) -> Part:
        return square_ring(self.outer_side, self.skirt_inner_side, self.skirt_height)


def zframe_parts(spec, geometry: FiducialGeometry) -> FiducialParts:
    """Body, top cap (a fill port over each distinct rod opening) and bottom cap (solid)."""
    b = geometry.body
    return build_parts(square_ring(b.outer_side, b.inner_side, b.length), SquareCapDims.from_spec(spec, geometry),
                       geometry)
