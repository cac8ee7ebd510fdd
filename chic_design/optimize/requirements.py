"""The optimiser's input: what the tool, the printer and the scanner allow, and what must work.

A YAML file validated by pydantic; :func:`load_requirements` raises a one-line
:class:`~chic_design.optimize.errors.RequirementsError` naming the file, the
key and what is allowed. Lengths in mm, angles in degrees, positions in the
fiducial frame F (origin on the axis in the bottom end face, +z to the top).
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Annotated

from pydantic import Field, ValidationError, model_validator

from chic_design.families.sections import Strict
from chic_design.optimize.errors import RequirementsError
from chic_design.spec import format_validation_error
from chic_register.errors import InputFileError
from chic_register.util.safeload import load_yaml_file

#: A positive number (ints and floats alike: requirements are not as strict as a spec).
Positive = Annotated[float, Field(gt=0)]


class ToolReq(Strict):
    """The tool the fiducial mounts on: a bore diameter, or the tool's diameter plus a clearance."""

    bore_diameter: Positive | None = Field(None, description="Diameter of the central bore (mm).")
    outer_diameter: Positive | None = Field(None, description="The tool's outer diameter (mm).")
    clearance: float = Field(0.0, ge=0, le=2, description="Radial clearance around the tool (mm).")

    @model_validator(mode="after")
    def _one(self):
        if (self.bore_diameter is None) == (self.outer_diameter is None):
            raise ValueError("give either bore_diameter or outer_diameter (+ clearance), not both or neither")
        if self.bore_diameter is not None and self.clearance:
            raise ValueError("clearance goes with outer_diameter; bore_diameter is the finished bore")
        return self

    @property
    def bore_mm(self) -> float:
        if self.bore_diameter is not None:
            return float(self.bore_diameter)
        return float(self.outer_diameter + 2 * self.clearance)


class LimitsReq(Strict):
    """Size limits: the outer diameter of the assembly (caps' skirts included) and the body length."""

    max_outer_diameter: Positive = Field(description="Largest outside diameter, cap skirts included (mm).")
    max_length: Positive = Field(description="Longest body (mm).")
    min_length: Positive | None = Field(None, description="Shortest body (mm); default: the required "
                                          "depth range's end plus 5 mm.")


class PrinterReq(Strict):
    """What the printer makes reliably."""

    min_wall: Positive = Field(0.8, description="Thinnest watertight wall (mm).")
    max_overhang_deg: float = Field(45.0, gt=0, lt=90, description="Steepest overhang from the axis (deg).")
    min_channel_diameter: Positive = Field(1.0, description="Narrowest channel that fills reliably (mm).")
    max_channel_diameter: Positive = Field(4.0, description="Widest channel to consider (mm).")

    @model_validator(mode="after")
    def _channels(self):
        if self.max_channel_diameter < self.min_channel_diameter:
            raise ValueError(f"max_channel_diameter ({self.max_channel_diameter:g}) must be >= "
                             f"min_channel_diameter ({self.min_channel_diameter:g})")
        return self


class ImagingReq(Strict):
    """The scanner protocol the design must work with."""

    pixel_size: Positive = Field(description="In-plane pixel size (mm).")
    slice_thickness: Positive = Field(description="Slice thickness (mm).")
    snr: float = Field(20.0, gt=0, description="Fluid signal over noise SD (Rician).")
    n_slices: int = Field(1, ge=1, le=64, description="Parallel slices registered together.")
    slice_spacing: Positive | None = Field(None, description="Centre spacing of the slices (mm); "
                                             "default: the slice thickness.")


class RequiredReq(Strict):
    """What must work: every depth in ``depth_mm`` at every tilt up to ``tilt_deg[1]``; the target point."""

    depth_mm: tuple[float, float] = Field(description="Depth range (z in F, mm) that must register.")
    tilt_deg: tuple[float, float] = Field(description="Tilt range (deg) that must register at those depths.")
    target_mm: tuple[float, float, float] = Field(
        description="Point whose registration error matters (F, mm), e.g. the needle tip below the body.")

    @model_validator(mode="after")
    def _ranges(self):
        d0, d1 = self.depth_mm
        if not 0 <= d0 < d1:
            raise ValueError(f"depth_mm must be [low, high] with 0 <= low < high, got {list(self.depth_mm)}")
        t0, t1 = self.tilt_deg
        if not 0 <= t0 <= t1 < 80:
            raise ValueError(f"tilt_deg must be [low, high] with 0 <= low <= high < 80, got {list(self.tilt_deg)}")
        if not all(math.isfinite(v) for v in self.target_mm):
            raise ValueError(f"target_mm must be three finite numbers, got {list(self.target_mm)}")
        return self


class CapsReq(Strict):
    """Cap dimensions used for every candidate (see the design spec's ``caps``)."""

    thickness: Positive = 1.5
    clearance: float = Field(0.15, ge=0, le=1.0)
    skirt_height: Positive = 3.0
    skirt_wall: Positive = 1.2


class SearchReq(Strict):
    """Search settings (the command line overrides ``trials``)."""

    trials: int = Field(240, ge=1, le=100000, description="Candidates to evaluate.")
    population: int = Field(24, ge=2, le=1000, description="NSGA-II population (one batch per generation).")
    baseline: str | None = Field(None, description="A design spec to compare with and start from "
                                 "(path relative to this file).")
    confirm: int = Field(3, ge=0, le=20, description="Pareto designs confirmed by the simulation study.")
    confirm_draws: int = Field(4, ge=1, le=100, description="Noise draws per pose in the confirmation study.")


class Requirements(Strict):
    """Everything ``chic-design optimize`` needs."""

    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$", description="Names the output and the designs.")
    description: str = ""
    tool: ToolReq
    limits: LimitsReq
    printer: PrinterReq = Field(default_factory=PrinterReq)
    imaging: ImagingReq
    required: RequiredReq
    caps: CapsReq = Field(default_factory=CapsReq)
    search: SearchReq = Field(default_factory=SearchReq)

    @model_validator(mode="after")
    def _consistent(self):
        if self.required.depth_mm[1] > self.limits.max_length:
            raise ValueError(f"required.depth_mm ends at {self.required.depth_mm[1]:g} mm, beyond "
                             f"limits.max_length ({self.limits.max_length:g})")
        if self.length_range_mm[0] > self.limits.max_length:
            raise ValueError(f"limits.min_length ({self.length_range_mm[0]:g}) exceeds limits.max_length "
                             f"({self.limits.max_length:g})")
        if 2 * self.caps.skirt_height >= self.length_range_mm[0]:
            raise ValueError(f"caps.skirt_height ({self.caps.skirt_height:g}) must be less than half of "
                             f"the shortest body ({self.length_range_mm[0]:g} mm)")
        lo, hi = self.body_od_range_mm
        if lo > hi:
            raise ValueError(
                f"limits.max_outer_diameter ({self.limits.max_outer_diameter:g}) leaves a body of at most "
                f"{hi:g} mm outside the caps, but the bore ({self.tool.bore_mm:g}) plus two walls and the "
                f"narrowest channel need {lo:g} mm")
        return self

    @property
    def cap_allowance_mm(self) -> float:
        """How much wider the assembly is than the body (cap skirts and their clearance, both sides)."""
        return 2 * (self.caps.clearance + self.caps.skirt_wall)

    @property
    def body_od_range_mm(self) -> tuple[float, float]:
        p = self.printer
        lo = self.tool.bore_mm + 2 * (2 * p.min_wall + p.min_channel_diameter)
        return lo, self.limits.max_outer_diameter - self.cap_allowance_mm

    @property
    def length_range_mm(self) -> tuple[float, float]:
        if self.limits.min_length is not None:
            return float(self.limits.min_length), float(self.limits.max_length)
        lo = min(self.required.depth_mm[1] + 5.0, self.limits.max_length)
        return float(lo), float(self.limits.max_length)

    def scoring_dict(self) -> dict:
        """The parts of the requirements that change a candidate's score (the store's key)."""
        return self.model_dump(exclude={"name", "description", "search"})

    def scoring_sha256(self) -> str:
        return hashlib.sha256(json.dumps(self.scoring_dict(), sort_keys=True).encode()).hexdigest()


def json_schema() -> dict:
    schema = Requirements.model_json_schema()
    schema["title"] = "CHIC optimiser requirements"
    return schema


def parse_requirements(data, path="<requirements>") -> Requirements:
    """Validate parsed YAML ``data``; raises :class:`RequirementsError` with a one-line message."""
    path = Path(path)
    if not isinstance(data, dict):
        raise RequirementsError(f"{path}: the requirements must be a YAML mapping, got {type(data).__name__}")
    try:
        return Requirements.model_validate(data)
    except ValidationError as exc:
        raise RequirementsError(format_validation_error(path, exc.errors()[0], Requirements,
                                                        "see the requirements schema")) from None


def load_requirements(path) -> Requirements:
    """Read and validate a requirements file."""
    path = Path(path)
    try:
        data = load_yaml_file(path, "requirements file")  # the loader of specs and geometry files
    except InputFileError as exc:
        raise RequirementsError(str(exc)) from None
    return parse_requirements(data, path)


def baseline_path(req: Requirements, req_path) -> Path | None:
    """The baseline spec's path (relative to the requirements file), or None."""
    if req.search.baseline is None:
        return None
    p = Path(req.search.baseline)
    return p if p.is_absolute() else Path(req_path).parent / p
