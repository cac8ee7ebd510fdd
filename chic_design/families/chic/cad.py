"""The CHIC family's shape for the CAD model: an annular body blank and round caps.

The channels, the caps' placement and fill ports are the generic
:func:`chic_design.cad.parts.build_parts`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from build123d import Cylinder, Part

from chic_design.cad.parts import ALIGN_BOTTOM, CapDims, FiducialParts, build_parts
from chic_register.model.geometry import FiducialGeometry


def _ring(outer_radius: float, inner_radius: float, height: float) -> Part:
    ring = Cylinder(outer_radius, height, align=ALIGN_BOTTOM)
    ring -= Cylinder(inner_radius, height, align=ALIGN_BOTTOM)
    return ring


@dataclass(frozen=True)
class RoundCapDims(CapDims):
    """A round cap: ``inner_radius`` = the body's bore, the skirt's inside ``body_radius + clearance``."""

    inner_radius: float
    body_radius: float

    @property
    def skirt_inner_radius(self) -> float:
        return self.body_radius + self.clearance

    @property
    def outer_radius(self) -> float:
        return self.skirt_inner_radius + self.skirt_wall

    @classmethod
    def from_spec(cls, spec, geometry: FiducialGeometry) -> "RoundCapDims":
        c = spec.caps
        return cls(thickness=c.thickness, clearance=c.clearance, skirt_height=c.skirt_height,
                   skirt_wall=c.skirt_wall, port_diameter=c.fill_port_diameter,
                   inner_radius=geometry.body.inner_diameter / 2, body_radius=geometry.body.outer_diameter / 2)

    def plate(self) -> Part:
        return _ring(self.outer_radius, self.inner_radius, self.thickness)

    def skirt(self) -> Part:
        return _ring(self.outer_radius, self.skirt_inner_radius, self.skirt_height)

    def bbox(self, length_mm: float, end: str) -> tuple[np.ndarray, np.ndarray]:
        """Expected axis-aligned bounding box (min (3,), max (3,)) of the cap at ``end``."""
        r = self.outer_radius
        if end == "top":
            z = (length_mm - self.skirt_height, length_mm + self.thickness)
        else:
            z = (-self.thickness, self.skirt_height)
        return np.array([-r, -r, z[0]]), np.array([r, r, z[1]])


def annulus_blank(geometry: FiducialGeometry) -> Part:
    """The annulus ``inner_diameter..outer_diameter``, ``z = 0..length``."""
    b = geometry.body
    return _ring(b.outer_diameter / 2, b.inner_diameter / 2, b.length)


def chic_parts(spec, geometry: FiducialGeometry) -> FiducialParts:
    """Body, top cap (a fill port over each channel's top opening) and bottom cap (solid)."""
    return build_parts(annulus_blank(geometry), RoundCapDims.from_spec(spec, geometry), geometry)
