"""The CHIC spec (``family: chic``, the default): the paper's parameters, validated before any CAD work.

Body, channels, helices and marker layout; the shared sections (caps,
printer, imaging, tool) come from :mod:`chic_design.families.sections`. The
cross-field rules live in ``model_validator`` methods.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from chic_design.families.sections import (
    MAX_CHANNEL_MM,
    MAX_DIAMETER_MM,
    MAX_HELIX_TURN_DEG,
    MAX_LENGTH_MM,
    MAX_NAME_CHARS,
    MAX_PITCH_DEG_PER_MM,
    NAME_PATTERN,
    Angle360,
    CapSpec,
    ImagingSpec,
    Number,
    PositiveMM,
    PrintSpec,
    Quadrant,
    SignedAngle,
    Strict,
    ToolSpec,
)


class BodySpec(Strict):
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


class ChannelSpec(Strict):
    """The fluid channels (tubes) in the wall."""

    diameter: PositiveMM = Field(ge=0.2, le=MAX_CHANNEL_MM, description="Channel diameter (mm).")
    circle_diameter: Annotated[PositiveMM, Field(le=MAX_DIAMETER_MM)] | None = Field(
        None,
        description="Diameter of the circle the channel centrelines lie on (mm); "
        "default: the middle of the wall.",
    )


class HelixSpec(Strict):
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


class MarkerSpec(Strict):
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


class ChicSpec(Strict):
    """A CHIC fiducial design."""

    family: Literal["chic"] = Field("chic", description="Fiducial family: chic (the default); "
                                    "`chic-design schema --family NAME` gives the others' specs.")
    name: str = Field(pattern=NAME_PATTERN, max_length=MAX_NAME_CHARS, strict=True,
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
