"""The Z-frame design spec (``family: zframe``): the classic seven-rod Z-frame as a printable part.

Default = configuration ``z001`` of 3D Slicer's ZFrameRegistration: rods on a
60 mm cube, four axial rods at the corners x, y = +-30 mm and three diagonal
rods on the faces x = +30, y = +30 and x = -30 (see :mod:`chic_design.families.zframe.layout`).

The printed part is a square frame: four walls of thickness ``frame.wall``,
centred on the rod planes x, y = +-side/2, with the rods as fluid channels
inside the walls, and a cap at each end like the CHIC body's.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from chic_design.families.sections import (
    MAX_CHANNEL_MM,
    MAX_DIAMETER_MM,
    MAX_LENGTH_MM,
    MAX_NAME_CHARS,
    NAME_PATTERN,
    CapSpec,
    ImagingSpec,
    PositiveMM,
    PrintSpec,
    Strict,
    ToolSpec,
)

#: The four side faces of the frame, by the axis their outward normal points along.
FACES = ("+x", "+y", "-x", "-y")
Face = Literal["+x", "+y", "-x", "-y"]


class FrameSpec(Strict):
    """The frame: rod spacing, height and wall thickness."""

    side: PositiveMM = Field(60.0, le=MAX_DIAMETER_MM, description="Distance between opposite rod planes (mm): the axial "
                             "rods sit at x, y = +-side/2.")
    height: PositiveMM = Field(60.0, le=MAX_LENGTH_MM, description="Frame height along z (mm): rod length.")
    wall: PositiveMM = Field(7.0, le=MAX_CHANNEL_MM * 2, description="Wall thickness (mm), centred on the rod planes; the "
                             "rods run inside the walls.")


class RodSpec(Strict):
    """The fluid channels (rods)."""

    diameter: PositiveMM = Field(3.0, le=MAX_CHANNEL_MM, description="Rod (channel) diameter (mm).")


class DiagonalSpec(Strict):
    """Which faces carry a diagonal rod, and which way each runs."""

    faces: tuple[Face, ...] = Field(
        ("+x", "+y", "-x"), min_length=1, max_length=4,
        description="Faces with a diagonal rod (z001: +x, +y, -x). On each face the diagonal runs "
        "from the corner at the counter-clockwise end of the face (seen from +z) at the bottom to "
        "the other corner at the top, as in z001.",
    )
    reversed_faces: tuple[Face, ...] = Field(
        (), description="Faces whose diagonal runs the other way (clockwise end at the bottom). "
        "z001 has none; reversing -x breaks z001's two-fold symmetry.",
    )

    @model_validator(mode="after")
    def _faces(self):
        if len(set(self.faces)) != len(self.faces):
            raise ValueError(f"faces must be different, got {list(self.faces)}")
        extra = sorted(set(self.reversed_faces) - set(self.faces))
        if extra:
            raise ValueError(f"reversed_faces {extra} carry no diagonal; allowed: faces listed in faces")
        return self


class ZFrameSpec(Strict):
    """A Z-frame fiducial design (``family: zframe``)."""

    family: Literal["zframe"]
    name: str = Field(pattern=NAME_PATTERN, max_length=MAX_NAME_CHARS, strict=True,
                      description="Design name: the export folder (letters, digits, _ . -).")
    description: str = Field("", max_length=2000, strict=True)
    frame: FrameSpec = Field(default_factory=FrameSpec)
    rods: RodSpec = Field(default_factory=RodSpec)
    diagonals: DiagonalSpec = Field(default_factory=DiagonalSpec)
    caps: CapSpec = Field(default_factory=CapSpec)
    print: PrintSpec = Field(default_factory=PrintSpec)
    imaging: ImagingSpec = Field(default_factory=ImagingSpec)
    tool: ToolSpec | None = Field(None, description="Where the tool tip is in F (optional): written to "
                                  "geometry.yaml so the solver can report the tip's pose.")

    @model_validator(mode="after")
    def _fits(self):
        f, d = self.frame, self.rods.diameter
        if not d < f.wall:
            raise ValueError(f"rods.diameter ({d:g}) must be smaller than frame.wall ({f.wall:g}): "
                             "the rods run inside the walls")
        if not f.wall < f.side:
            raise ValueError(f"frame.wall ({f.wall:g}) must be smaller than frame.side ({f.side:g}): "
                             "the frame needs an open bore")
        if self.caps.fill_port_diameter >= d:
            raise ValueError(f"caps.fill_port_diameter ({self.caps.fill_port_diameter:g}) must be smaller "
                             f"than rods.diameter ({d:g})")
        return self

    @property
    def outer_side(self) -> float:
        """Outside width of the frame (mm)."""
        return self.frame.side + self.frame.wall

    @property
    def inner_side(self) -> float:
        """Width of the square bore (mm)."""
        return self.frame.side - self.frame.wall

    @property
    def length(self) -> float:
        """Frame height along z (mm); what ``body.length`` is for a CHIC spec."""
        return self.frame.height
