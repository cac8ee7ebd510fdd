"""The spec sections every family shares (caps, printer, imaging, tool) and the value types they are made of.

All lengths are millimetres, angles degrees. Each family's spec model
(``chic_design.families.<name>.spec``) is built from these plus its own
shape sections; the generic code reads only ``name``, ``description``,
``caps``, ``print``, ``imaging`` and ``tool`` (:class:`DesignSpec`).
"""

from __future__ import annotations

import math
from typing import Annotated, Literal, Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

#: Physical ranges (mm, deg) of the spec's values; documented in the JSON Schema.
MAX_LENGTH_MM = 200.0  # body length: an MRI head/knee coil is ~250 mm; check time grows with it
MAX_DIAMETER_MM = 150.0
MAX_CHANNEL_MM = 20.0
MAX_CAP_MM = 20.0
MAX_PITCH_DEG_PER_MM = 90.0
MAX_HELIX_TURN_DEG = 360.0  # |pitch| * length: more is outside its quadrant anyway
MAX_NAME_CHARS = 64
#: A design name: the export folder's name.
NAME_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9_.-]*$"

#: A finite number (no .inf/.nan), never a bool or a string: YAML ``yes`` or ``"5"`` is a type error.
Number = Annotated[float, Field(strict=True, allow_inf_nan=False)]
PositiveMM = Annotated[Number, Field(gt=0)]
Angle360 = Annotated[Number, Field(ge=0, lt=360)]
SignedAngle = Annotated[Number, Field(gt=-360, lt=360)]
Quadrant = Annotated[int, Field(strict=True, ge=0, le=3)]


class Strict(BaseModel):
    """A spec section: unknown keys are errors, and the values are frozen once validated."""

    model_config = ConfigDict(extra="forbid", frozen=True)


class CapSpec(Strict):
    """The two caps that seal the channels (see README: filling)."""

    thickness: PositiveMM = Field(2.0, le=MAX_CAP_MM, description="Thickness of the cap plate over the end face (mm).")
    clearance: Number = Field(
        0.2, ge=0, le=1.0, description="Radial fit clearance between cap skirt and body (mm)."
    )
    skirt_height: PositiveMM = Field(4.0, le=MAX_LENGTH_MM / 2,
                                     description="How far the cap's skirt reaches down the body (mm).")
    skirt_wall: PositiveMM = Field(1.6, le=MAX_CAP_MM, description="Wall thickness of the cap's skirt (mm).")
    fill_port_diameter: Number = Field(
        1.2, ge=0, le=MAX_CHANNEL_MM, description="Diameter of the fill port over each channel in the top cap (mm); "
        "0 gives a top cap without ports (fill before capping).",
    )


class PrintSpec(Strict):
    """The printer: its limits the design is checked against, and what the print plate is set up for."""

    min_wall: PositiveMM = Field(0.8, ge=0.1, le=10.0,
                                 description="Thinnest wall the printer makes watertight (mm).")
    max_overhang_deg: Number = Field(
        45.0, gt=0, lt=90, description="Steepest overhang from the build direction (the axis) (deg)."
    )
    printer: Literal["fdm", "resin"] = Field(
        "fdm", description="Kind of printer plate.3mf is set up for: fdm (filament, PrusaSlicer FFF profile) "
        "or resin (masked SLA, PrusaSlicer SLA profile).")
    nozzle_diameter: Number = Field(0.4, ge=0.1, le=1.2, description="FDM nozzle diameter (mm); ignored for resin.")
    layer_height: Number | None = Field(
        None, ge=0.01, le=0.8, description="Layer height (mm); default: from the smallest channel "
        "(about a tenth of its diameter, at most half the nozzle; 0.05 mm for resin).")

    @model_validator(mode="after")
    def _layer(self):
        if self.printer == "fdm" and self.layer_height is not None and self.layer_height > 0.8 * self.nozzle_diameter:
            raise ValueError(f"layer_height ({self.layer_height:g}) must be at most 0.8 x nozzle_diameter "
                             f"({0.8 * self.nozzle_diameter:g} mm): a thicker layer does not bond")
        return self


class ImagingSpec(Strict):
    """The imaging protocol the feasibility checks assume."""

    pixel_size: Number = Field(0.5, ge=0, le=10.0, description="In-plane pixel size (mm); 0 = ideal.")
    slice_thickness: Number = Field(2.0, ge=0, le=20.0, description="Slice thickness (mm); 0 = ideal.")


class ToolSpec(Strict):
    """Where the tool tip is, relative to the fiducial frame F (optional; give one of the two keys)."""

    tip_offset_mm: float | None = Field(
        None, description="Tip on the axis at this z of F (mm; negative: below the bottom end face); "
        "tool axes = F's axes.")
    T_fiducial_from_tool: list[list[float]] | None = Field(
        None, description="Full rigid transform from the tool frame (origin = tip) to F, 4x4 row-major (mm).")

    @model_validator(mode="after")
    def _one(self):
        if (self.tip_offset_mm is None) == (self.T_fiducial_from_tool is None):
            raise ValueError("give exactly one of tip_offset_mm and T_fiducial_from_tool")
        if self.tip_offset_mm is not None and not math.isfinite(self.tip_offset_mm):
            raise ValueError("tip_offset_mm must be a finite number")
        if self.T_fiducial_from_tool is not None:
            T = np.asarray(self.T_fiducial_from_tool, dtype=float) if all(
                isinstance(r, list) and len(r) == 4 for r in self.T_fiducial_from_tool) else np.zeros(0)
            ok = T.shape == (4, 4) and np.all(np.isfinite(T)) and np.allclose(T[3], [0, 0, 0, 1])
            if ok:
                R = T[:3, :3]
                ok = np.allclose(R.T @ R, np.eye(3), atol=1e-6) and np.linalg.det(R) > 0
            if not ok:
                raise ValueError("T_fiducial_from_tool must be a rigid 4x4 matrix (orthonormal rotation, "
                                 "det +1, last row [0, 0, 0, 1])")
        return self


class DesignSpec(Protocol):
    """What the generic code reads of any family's spec."""

    family: str
    name: str
    description: str
    caps: CapSpec
    print: PrintSpec
    imaging: ImagingSpec
    tool: ToolSpec | None
