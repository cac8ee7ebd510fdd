"""The N-localizer design spec (``family: nlocalizer``): Brown-Roberts-Wells "N" plates around the head.

Each plate carries two parallel vertical rods and a diagonal between them (the
"N"); a slice across the plates shows three dots per plate, and where the
middle dot sits between the outer two gives the slice's height. The spec
describes the plates in frame F (see :mod:`chic_design.families.nlocalizer.layout`),
the rods, optional edge rods (the Leksell MR box's rods along the plates' top
and bottom edges), the frame's own stereotactic coordinates and whether the
hardware is printed here or is a commercial frame described for the solver only.

A printed N-localizer is a rectangular ring (walls of ``frame.wall`` centred
on the rod planes, the rods as fluid channels inside) with a cap at each end,
so its plates must face along the x and y axes, opposite plates at one
distance.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from chic_design.families.sections import (
    MAX_CHANNEL_MM,
    MAX_LENGTH_MM,
    MAX_NAME_CHARS,
    NAME_PATTERN,
    Angle360,
    CapSpec,
    ImagingSpec,
    PositiveMM,
    PrintSpec,
    Strict,
    ToolSpec,
)
from chic_register.model.body import rigid_4x4
from chic_register.model.geometry import MAX_TUBES

#: Plate names become tube id prefixes (``<name>_a``); tube ids are at most 32 characters.
MAX_PLATE_NAME_CHARS = 20
#: Largest rod-plane distance from the axis and plate width (mm): a head frame in an MRI bore.
MAX_PLATE_DISTANCE_MM = 200.0
MAX_PLATE_WIDTH_MM = 300.0
#: A printed frame's plates face along x or y: azimuths within this of a multiple of 90 deg.
AXIS_TOLERANCE_DEG = 1e-6


class PlateSpec(Strict):
    """One N-plate: where it stands around the z axis and which way its diagonal runs."""

    name: str = Field(pattern=r"^[A-Za-z][A-Za-z0-9]*$", max_length=MAX_PLATE_NAME_CHARS, strict=True,
                      description="Plate name (letters and digits), the prefix of its rods' ids: <name>_a, "
                      "<name>_d, <name>_b.")
    azimuth_deg: Angle360 = Field(description="Direction of the plate's outward normal in F's xy plane (deg; "
                                  "0 = +x, counter-clockwise).")
    distance: PositiveMM = Field(le=MAX_PLATE_DISTANCE_MM, description="Distance from the z axis to the plate's "
                                 "rod plane (mm).")
    width: PositiveMM = Field(le=MAX_PLATE_WIDTH_MM, description="Distance between the plate's two vertical rods "
                              "(mm).")
    diagonal_from: Literal["left", "right"] = Field(
        description="End of the plate (seen from outside, z up) where the diagonal starts at the bottom "
        "(z = 0); it runs to the other rod's top.")

    @property
    def normal(self) -> np.ndarray:
        """Unit outward normal (x, y)."""
        a = math.radians(self.azimuth_deg)
        return np.array([math.cos(a), math.sin(a)])

    @property
    def right(self) -> np.ndarray:
        """Unit vector (x, y) toward the plate's right end seen from outside: z x normal (counter-clockwise)."""
        a = math.radians(self.azimuth_deg)
        return np.array([-math.sin(a), math.cos(a)])

    @property
    def axis(self) -> int | None:
        """0 (x) or 1 (y) if the normal lies along that axis, else None."""
        r = self.azimuth_deg % 90.0
        if min(r, 90.0 - r) > AXIS_TOLERANCE_DEG:
            return None
        return int(round(self.azimuth_deg / 90.0)) % 2


class FrameSpec(Strict):
    """The plates' height and thickness."""

    height: PositiveMM = Field(120.0, le=MAX_LENGTH_MM, description="Rod length along z (mm): the plates' height.")
    wall: PositiveMM = Field(8.0, le=MAX_CHANNEL_MM * 2, description="Plate thickness (mm), centred on the rod "
                             "plane; the rods run inside it.")


class RodSpec(Strict):
    """The rods (fluid channels, or the commercial frame's rods)."""

    diameter: PositiveMM = Field(3.0, le=MAX_CHANNEL_MM, description="Rod (channel) diameter (mm).")


class CoordinatesSpec(Strict):
    """The frame's own stereotactic coordinates, written to geometry.yaml as ``frame_coordinates``."""

    system: Literal["leksell", "brw", "custom"] = Field(
        description="leksell: computed (X patient right to left, Y posterior to anterior, Z superior to "
        "inferior, frame centre at (100, 100, 100) mm; F must be the Leksell presets' F); brw or custom: "
        "give T_frame_from_fiducial.")
    T_frame_from_fiducial: list[list[float]] | None = Field(
        None, description="Rigid 4x4 (row-major, mm) from F to the frame's coordinates; required for brw and "
        "custom, computed for leksell.")
    reference: str = Field("", max_length=500, strict=True, description="Where the convention is defined "
                           "(written to geometry.yaml; leksell has its own).")

    @model_validator(mode="after")
    def _matrix(self):
        if self.system == "leksell":
            if self.T_frame_from_fiducial is not None:
                raise ValueError("T_frame_from_fiducial is computed for system leksell; give it only for brw "
                                 "or custom")
            return self
        if self.T_frame_from_fiducial is None:
            raise ValueError(f"system {self.system} needs T_frame_from_fiducial (a rigid 4x4 from F)")
        if rigid_4x4(self.T_frame_from_fiducial) is None:
            raise ValueError("T_frame_from_fiducial must be a rigid 4x4 matrix (orthonormal rotation, det +1, "
                             "last row [0, 0, 0, 1])")
        return self


class NLocalizerSpec(Strict):
    """An N-localizer design (``family: nlocalizer``)."""

    family: Literal["nlocalizer"]
    name: str = Field(pattern=NAME_PATTERN, max_length=MAX_NAME_CHARS, strict=True,
                      description="Design name: the export folder (letters, digits, _ . -).")
    description: str = Field("", max_length=2000, strict=True)
    hardware: Literal["printed", "commercial"] = Field(
        "printed", description="printed: build the frame's parts (STL, STEP, 3MF, print plate); commercial: a "
        "frame bought ready-made (a Leksell box), described for the solver only (geometry.yaml, report, check).")
    plates: tuple[PlateSpec, ...] = Field(min_length=2, max_length=5, description="The N-plates (at least 2).")
    frame: FrameSpec = Field(default_factory=FrameSpec)
    rods: RodSpec = Field(default_factory=RodSpec)
    edge_rods: bool = Field(False, strict=True, description="Also rods along each plate's bottom and top edges "
                            "(<plate>_bottom, <plate>_top; the Leksell MR box has them); commercial hardware only.")
    coordinates: CoordinatesSpec | None = Field(None, description="The frame's stereotactic coordinates "
                                                "(optional).")
    caps: CapSpec = Field(default_factory=CapSpec)
    print: PrintSpec = Field(default_factory=PrintSpec)
    imaging: ImagingSpec = Field(default_factory=ImagingSpec)
    tool: ToolSpec | None = Field(None, description="Where the tool tip is in F (optional): written to "
                                  "geometry.yaml so the solver can report the tip's pose.")

    @model_validator(mode="after")
    def _fits(self):
        f, d = self.frame, self.rods.diameter
        names = [p.name for p in self.plates]
        if len(set(names)) != len(names):
            raise ValueError(f"plates must have different names, got {names}")
        n_tubes = len(self.plates) * (5 if self.edge_rods else 3)
        if n_tubes > MAX_TUBES:
            raise ValueError(f"{len(self.plates)} plates make {n_tubes} rods; a geometry file holds at most "
                             f"{MAX_TUBES}")
        if not d < f.wall:
            raise ValueError(f"rods.diameter ({d:g}) must be smaller than frame.wall ({f.wall:g}): "
                             "the rods run inside the plates")
        for p in self.plates:
            if not p.width > 2 * d:
                raise ValueError(f"plate {p.name}: width ({p.width:g}) must be more than twice rods.diameter "
                                 f"({d:g})")
            if not p.distance > f.wall:
                raise ValueError(f"plate {p.name}: distance ({p.distance:g}) must be more than frame.wall "
                                 f"({f.wall:g}): the frame needs an open bore")
        ends = [(p.name, p.distance * p.normal + s * p.width / 2 * p.right) for p in self.plates for s in (-1, 1)]
        for i, (na, a) in enumerate(ends):
            for nb, b in ends[i + 1:]:
                if na != nb and np.linalg.norm(a - b) < 2 * d:
                    raise ValueError(f"plates {na} and {nb} have rods {np.linalg.norm(a - b):.1f} mm apart: "
                                     f"keep them at least 2 x rods.diameter ({2 * d:g} mm) apart")
        if self.hardware == "printed":
            self._printable()
        return self

    def _printable(self) -> None:
        """A printed frame is a rectangular ring: plates along x or y, opposite plates at one distance."""
        if self.edge_rods:
            raise ValueError("edge_rods need hardware: commercial (a rod along an end face cannot be printed "
                             "as a channel)")
        dist: dict[int, float] = {}
        for p in self.plates:
            if p.axis is None:
                raise ValueError(f"plate {p.name}: azimuth_deg ({p.azimuth_deg:g}) must be 0, 90, 180 or 270 for "
                                 "printed hardware (the printed frame is a rectangular ring)")
            if dist.setdefault(p.axis, p.distance) != p.distance:
                raise ValueError(f"plate {p.name}: distance ({p.distance:g}) must equal the opposite plate's "
                                 f"({dist[p.axis]:g}) for printed hardware (the ring is centred on z)")
        if self.caps.fill_port_diameter >= self.rods.diameter:
            raise ValueError(f"caps.fill_port_diameter ({self.caps.fill_port_diameter:g}) must be smaller "
                             f"than rods.diameter ({self.rods.diameter:g})")

    @property
    def printed(self) -> bool:
        """True when the frame's parts are built here."""
        return self.hardware == "printed"

    @property
    def length(self) -> float:
        """Frame height along z (mm); what ``body.length`` is for a CHIC spec."""
        return self.frame.height
