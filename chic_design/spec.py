"""The design spec: a YAML file with the paper's parameters, validated before any CAD work.

All lengths are millimetres, angles degrees. Unknown keys, wrong types,
out-of-range and contradictory values are rejected by :func:`load_spec` with a
one-line :class:`~chic_design.errors.SpecError` naming the file, the key path
and what is allowed. ``chic-design schema`` prints :func:`json_schema`.

pydantic does the type and range checking (and produces the JSON Schema);
the cross-field rules live in ``model_validator`` methods below.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from chic_register.errors import InputFileError
from chic_register.util.safeload import MAX_YAML_BYTES, load_yaml_file, read_regular_file

from .errors import SpecError

#: Physical ranges (mm, deg) of the spec's values; documented in the JSON Schema.
MAX_LENGTH_MM = 200.0  # body length: an MRI head/knee coil is ~250 mm; check time grows with it
MAX_DIAMETER_MM = 150.0
MAX_CHANNEL_MM = 20.0
MAX_CAP_MM = 20.0
MAX_PITCH_DEG_PER_MM = 90.0
MAX_HELIX_TURN_DEG = 360.0  # |pitch| * length: more is outside its quadrant anyway
MAX_NAME_CHARS = 64

#: A finite number (no .inf/.nan), never a bool or a string: YAML ``yes`` or ``"5"`` is a type error.
Number = Annotated[float, Field(strict=True, allow_inf_nan=False)]
PositiveMM = Annotated[Number, Field(gt=0)]
Angle360 = Annotated[Number, Field(ge=0, lt=360)]
SignedAngle = Annotated[Number, Field(gt=-360, lt=360)]
Quadrant = Annotated[int, Field(strict=True, ge=0, le=3)]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class BodySpec(_Strict):
    """The annular body that mounts coaxially on the tool."""

    length: PositiveMM = Field(ge=2, le=MAX_LENGTH_MM, description="Body length along the axis (mm).")
    outer_diameter: PositiveMM = Field(ge=2, le=MAX_DIAMETER_MM, description="Outer diameter (mm).")
    inner_diameter: PositiveMM = Field(ge=0.5, le=MAX_DIAMETER_MM,
                                       description="Diameter of the central bore for the tool (mm).")

    @model_validator(mode="after")
    def _wall(self):
        if self.inner_diameter >= self.outer_diameter:
            raise ValueError(
                f"inner_diameter ({self.inner_diameter:g}) must be smaller than "
                f"outer_diameter ({self.outer_diameter:g})"
            )
        return self

    @property
    def wall(self) -> float:
        return (self.outer_diameter - self.inner_diameter) / 2


class ChannelSpec(_Strict):
    """The fluid channels (tubes) in the wall."""

    diameter: PositiveMM = Field(ge=0.2, le=MAX_CHANNEL_MM, description="Channel diameter (mm).")
    circle_diameter: Annotated[PositiveMM, Field(le=MAX_DIAMETER_MM)] | None = Field(
        None,
        description="Diameter of the circle the channel centrelines lie on (mm); "
        "default: the middle of the wall.",
    )


class HelixSpec(_Strict):
    """The three depth-encoding helices (the paper's omega and angular offset phi)."""

    offset_deg: Number = Field(
        10.0, ge=0, lt=45, description="Angular offset of each helix from its quadrant's "
        "diametric tube at the bottom end (deg)."
    )
    offset_top_deg: Number | None = Field(
        None, ge=0, lt=45, description="Angular offset at the top end (deg); default: offset_deg. "
        "Ignored when pitch_deg_per_mm is given (then the pitch fixes the top angle)."
    )
    pitch_deg_per_mm: Number | None = Field(
        None, ge=-MAX_PITCH_DEG_PER_MM, le=MAX_PITCH_DEG_PER_MM, description="Helix pitch d(theta)/dz (deg/mm), sign = direction; default: each "
        "helix runs from offset_deg at the bottom to (quadrant - offset_top_deg) at the top."
    )

    @model_validator(mode="after")
    def _pitch(self):
        if self.pitch_deg_per_mm is not None:
            if self.pitch_deg_per_mm == 0:
                raise ValueError("pitch_deg_per_mm must not be 0 (a helix must turn)")
            if self.offset_top_deg is not None:
                raise ValueError(
                    "give either pitch_deg_per_mm or offset_top_deg, not both: the pitch fixes "
                    "the top offset"
                )
        return self


class MarkerSpec(_Strict):
    """Marker layout (paper Fig. 1): four diametric tubes, three helices, orientation tubes."""

    diametric_deg: tuple[Angle360, Angle360, Angle360, Angle360] = Field(
        (0.0, 90.0, 180.0, 270.0),
        description="Angles of the four straight diametric tubes D0..D3 (deg, increasing, "
        "D0 at 0: it defines +x of the fiducial frame).",
    )
    helix_quadrants: tuple[Quadrant, Quadrant, Quadrant] = Field(
        (0, 1, 2), description="Quadrants that hold helices H0..H2; quadrant q lies between "
        "diametric tubes Dq and D(q+1)."
    )
    orientation_deg: tuple[SignedAngle, ...] = Field(
        (290.0, 330.0), min_length=1, max_length=3,
        description="Angles of the straight orientation tubes O0.. (deg); they must lie in "
        "the quadrant without a helix, placed asymmetrically so the pattern fixes twist.",
    )

    @model_validator(mode="after")
    def _layout(self):
        d = self.diametric_deg
        if d[0] != 0:
            raise ValueError("diametric_deg[0] must be 0: D0 defines the +x axis of frame F")
        if not all(0 <= a < 360 for a in d) or not all(a < b for a, b in zip(d, d[1:])):
            raise ValueError(f"diametric_deg must increase within [0, 360), got {list(d)}")
        q = self.helix_quadrants
        if len(set(q)) != 3 or not all(0 <= i <= 3 for i in q):
            raise ValueError(f"helix_quadrants must be 3 different quadrants from 0..3, got {list(q)}")
        free = ({0, 1, 2, 3} - set(q)).pop()
        lo, hi = quadrant_bounds_deg(d, free)
        for a in self.orientation_deg:
            a_un = a if a >= lo else a + 360
            if not lo < a_un < hi:
                raise ValueError(
                    f"orientation tube at {a:g} deg is outside the free quadrant {free} "
                    f"({lo:g}..{hi:g} deg); allowed: strictly between its diametric tubes"
                )
        return self

    @property
    def free_quadrant(self) -> int:
        return ({0, 1, 2, 3} - set(self.helix_quadrants)).pop()


class CapSpec(_Strict):
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


class PrintSpec(_Strict):
    """Printer limits the design is checked against."""

    min_wall: PositiveMM = Field(0.8, ge=0.1, le=10.0,
                                 description="Thinnest wall the printer makes watertight (mm).")
    max_overhang_deg: Number = Field(
        45.0, gt=0, lt=90, description="Steepest overhang from the build direction (the axis) (deg)."
    )


class ImagingSpec(_Strict):
    """The imaging protocol the feasibility checks assume."""

    pixel_size: Number = Field(0.5, ge=0, le=10.0, description="In-plane pixel size (mm); 0 = ideal.")
    slice_thickness: Number = Field(2.0, ge=0, le=20.0, description="Slice thickness (mm); 0 = ideal.")


class ToolSpec(_Strict):
    """Where the tool tip is, relative to the fiducial frame F (optional; give one of the two keys)."""

    tip_offset_mm: float | None = Field(
        None, description="Tip on the axis at this z of F (mm; negative: below the bottom end face); "
        "tool axes = F's axes.")
    T_fiducial_from_tool: list[list[float]] | None = Field(
        None, description="Full rigid transform from the tool frame (origin = tip) to F, 4x4 row-major (mm).")

    @model_validator(mode="after")
    def _one(self):
        import math

        import numpy as np

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


class Spec(_Strict):
    """A CHIC fiducial design."""

    family: Literal["chic"] = Field("chic", description="Fiducial family: chic (default) or zframe "
                                    "(see chic_design.zframe_spec).")
    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]*$", max_length=MAX_NAME_CHARS, strict=True,
                      description="Design name: the export folder (letters, digits, _ . -; at most "
                      f"{MAX_NAME_CHARS} characters, so that every file name under it fits the file system).")
    description: str = Field("", max_length=2000, strict=True)
    body: BodySpec
    channels: ChannelSpec
    helix: HelixSpec = Field(default_factory=HelixSpec)
    markers: MarkerSpec = Field(default_factory=MarkerSpec)
    caps: CapSpec = Field(default_factory=CapSpec)
    print: PrintSpec = Field(default_factory=PrintSpec)
    imaging: ImagingSpec = Field(default_factory=ImagingSpec)
    tool: ToolSpec | None = Field(None, description="Optional tool frame: the tip a robot needs.")

    @model_validator(mode="after")
    def _fits(self):
        pitch = self.helix.pitch_deg_per_mm
        if pitch is not None and abs(pitch) * self.body.length > MAX_HELIX_TURN_DEG:
            raise ValueError(
                f"helix.pitch_deg_per_mm ({pitch:g}) turns the helix {abs(pitch) * self.body.length:g} deg "
                f"over body.length ({self.body.length:g}); allowed: at most {MAX_HELIX_TURN_DEG:g} deg"
            )
        r_in, r_out = self.body.inner_diameter / 2, self.body.outer_diameter / 2
        rc = self.channel_radius
        a = self.channels.diameter / 2
        if not r_in < rc - a or not rc + a < r_out:
            raise ValueError(
                f"channels of diameter {self.channels.diameter:g} on a circle of diameter "
                f"{2 * rc:g} do not fit in the wall ({2 * r_in:g}..{2 * r_out:g}); "
                "allowed: circle_diameter - diameter > inner_diameter and "
                "circle_diameter + diameter < outer_diameter"
            )
        if self.caps.fill_port_diameter >= self.channels.diameter:
            raise ValueError(
                f"caps.fill_port_diameter ({self.caps.fill_port_diameter:g}) must be smaller "
                f"than channels.diameter ({self.channels.diameter:g})"
            )
        return self

    @property
    def channel_radius(self) -> float:
        """Radius of the circle the channel centrelines lie on (mm)."""
        if self.channels.circle_diameter is not None:
            return self.channels.circle_diameter / 2
        return (self.body.inner_diameter + self.body.outer_diameter) / 4


def quadrant_bounds_deg(diametric_deg, q: int) -> tuple[float, float]:
    """Angular bounds (lo, hi) of quadrant ``q``; hi may exceed 360 for the last one."""
    lo = diametric_deg[q]
    hi = diametric_deg[(q + 1) % 4] + (360 if q == 3 else 0)
    return float(lo), float(hi)


def json_schema(family: str = "chic") -> dict:
    """JSON Schema of the spec of ``family`` (for editors)."""
    schema = spec_model(family).model_json_schema()
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = "CHIC fiducial design spec" if family == "chic" else f"{family} fiducial design spec"
    return schema


def format_validation_error(path: Path, err: dict, root=None, schema_hint: str = "see `chic-design schema`") -> str:
    """One line for a pydantic error in a YAML file: the file, the key path, what is wrong and what was given."""
    loc = ".".join(str(p) for p in err["loc"]) or "(top level)"
    msg = err["msg"].removeprefix("Value error, ")
    kind = err["type"]
    if kind == "extra_forbidden":
        parent = err["loc"][:-1]
        model = Spec if root is None else root
        for part in parent:
            field = model.model_fields.get(str(part))
            model = field.annotation if field is not None else None
            if not isinstance(model, type) or not issubclass(model, BaseModel):
                model = None
                break
        allowed = ", ".join(model.model_fields) if model is not None else schema_hint
        return f"{path}: unknown key '{loc}'; allowed keys here: {allowed}"
    if kind == "missing":
        return f"{path}: missing key '{loc}'"
    shown = err.get("input")
    if isinstance(shown, (dict, list)) or kind.startswith("value_error"):
        return f"{path}: {loc}: {msg}"
    shown = repr(shown)
    return f"{path}: {loc}: {msg} (got {shown if len(shown) <= 60 else shown[:57] + '...'})"


def parse_spec(data, path="<spec>") -> Spec:
    """Validate parsed YAML ``data`` into a :class:`Spec`; raises :class:`SpecError`."""
    path = Path(path)
    if not isinstance(data, dict):
        raise SpecError(f"{path}: the spec must be a YAML mapping of keys, got {type(data).__name__}")
    family = data.get("family", "chic")
    model = spec_model(family)
    if model is None:
        raise SpecError(f"{path}: family: unknown family {family!r}; allowed: {', '.join(FAMILIES)}")
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise SpecError(format_validation_error(path, exc.errors()[0], model)) from None


#: Spec families: the ``family`` key of a spec picks its model (default ``chic``).
FAMILIES = ("chic", "zframe")


def spec_model(family):
    """The pydantic model of a spec family, or None for an unknown one."""
    if family == "chic":
        return Spec
    if family == "zframe":
        from .zframe_spec import ZFrameSpec

        return ZFrameSpec
    return None


def load_spec(path) -> Spec:
    """Read and validate a spec file; raises :class:`SpecError` with a one-line message."""
    path = Path(path)
    try:
        data = load_yaml_file(path, "spec file")
    except InputFileError as exc:
        raise SpecError(str(exc)) from None
    return parse_spec(data, path)


def spec_sha256(path) -> str:
    """SHA-256 of the spec file's bytes (recorded in the geometry file's ``source``)."""
    try:
        return hashlib.sha256(read_regular_file(path, "spec file", MAX_YAML_BYTES)).hexdigest()
    except InputFileError as exc:
        raise SpecError(str(exc)) from None


def spec_to_json(spec: Spec) -> str:
    return json.dumps(spec.model_dump(), indent=2)
