"""The printed N-localizer's shape for the CAD model: a rectangular ring blank and rectangular caps.

The frame is the ring ``inner_size..outer_size`` of :func:`~chic_design.families.nlocalizer.layout.nlocalizer_body`
(walls of ``frame.wall`` centred on the rod planes; a side without a plate is a
plain connecting wall), ``z = 0..height``. The rods are swept by the generic
:func:`chic_design.cad.parts.build_parts`; each diagonal meets its plate's two
vertical rods at the end faces, so a plate's three channels form one network
that fills from the top, and a diagonal's opening shares its rod's fill port.
"""

from __future__ import annotations

from dataclasses import dataclass

from build123d import Box, Part

from chic_design.cad.parts import ALIGN_BOTTOM, CapDims, FiducialParts, build_parts
from chic_register.model.geometry import FiducialGeometry


def rect_ring(outer: tuple[float, float], inner: tuple[float, float], height: float) -> Part:
    """A rectangular ring of outside ``outer`` (x, y) and bore ``inner`` (x, y), ``z = 0..height``."""
    return (Box(outer[0], outer[1], height, align=ALIGN_BOTTOM)
            - Box(inner[0], inner[1], height, align=ALIGN_BOTTOM))


@dataclass(frozen=True)
class BoxCapDims(CapDims):
    """A rectangular cap: ``inner_size`` = the bore, the skirt's inside ``body_size + 2 clearance``."""

    inner_size: tuple[float, float]
    body_size: tuple[float, float]

    @property
    def skirt_inner_size(self) -> tuple[float, float]:
        return tuple(v + 2 * self.clearance for v in self.body_size)

    @property
    def outer_size(self) -> tuple[float, float]:
        return tuple(v + 2 * self.skirt_wall for v in self.skirt_inner_size)

    @classmethod
    def from_spec(cls, spec, geometry: FiducialGeometry) -> "BoxCapDims":
        c, b = spec.caps, geometry.body
        return cls(thickness=c.thickness, clearance=c.clearance, skirt_height=c.skirt_height,
                   skirt_wall=c.skirt_wall, port_diameter=c.fill_port_diameter,
                   inner_size=tuple(b.inner_size), body_size=tuple(b.outer_size))

    def plate(self) -> Part:
        return rect_ring(self.outer_size, self.inner_size, self.thickness)

    def skirt(self) -> Part:
        return rect_ring(self.outer_size, self.skirt_inner_size, self.skirt_height)


def nlocalizer_parts(spec, geometry: FiducialGeometry) -> FiducialParts:
    """Body, top cap (a fill port over each distinct rod opening) and bottom cap (solid)."""
    if not spec.printed:
        raise ValueError(f"{spec.name} is commercial hardware: it has no printed parts")
    b = geometry.body
    return build_parts(rect_ring(b.outer_size, b.inner_size, b.length), BoxCapDims.from_spec(spec, geometry),
                       geometry)
