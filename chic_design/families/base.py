"""What a fiducial family provides: the :class:`Family` interface, and the steps every family shares.

A family is one kind of fiducial (the CHIC cylinder, the seven-rod Z-frame).
It owns its spec model and everything that depends on its shape; the generic
code (spec loading, the feasibility engine, the CAD sweeping, the build, the
report) asks the family through this interface and never tests which family
it has.

To add a family, make a folder ``chic_design/families/<name>/`` with a
subclass of :class:`Family` that sets the class attributes and
implements the abstract methods, and add one line to
:data:`chic_design.families.FAMILIES`. (The solver also checks the
``family`` key of a geometry file against its own list,
``chic_register.model.geometry.FAMILIES``.)
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, replace
from typing import ClassVar

from pydantic import BaseModel

from chic_design.families.sections import DesignSpec
from chic_design.feasibility.engine import check_geometry
from chic_design.feasibility.printability import build_violations
from chic_design.feasibility.records import FeasibilityReport, Finding, Symmetry, Unambiguity
from chic_design.printing.limits import print_violations
from chic_design.printing.settings import print_settings
from chic_register.model.body import Body, FrameCoordinates, ToolFrame
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.tubes import Tube
from chic_register.version import __version__


@dataclass(frozen=True)
class ReportHead:
    """A family's part of ``report.md``: its title, frame F in words and the rows of the dimension table."""

    title: str
    frame_text: str
    dimension_rows: tuple[str, ...]


def tool_frame(spec: DesignSpec) -> ToolFrame | None:
    """The tool frame of a spec's optional ``tool`` section, or None."""
    if spec.tool is None:
        return None
    if spec.tool.tip_offset_mm is not None:
        return ToolFrame.tip_offset(spec.tool.tip_offset_mm)
    return ToolFrame(spec.tool.T_fiducial_from_tool)


class Family(ABC):
    """One kind of fiducial: its spec, geometry, parts, feasibility rules and report section."""

    #: The spec's (and geometry.yaml's) ``family`` value.
    name: ClassVar[str]
    #: What reports call it ("CHIC fiducial").
    title: ClassVar[str]
    #: Its spec model: a pydantic model with a ``family`` literal and the sections of
    #: :class:`~chic_design.families.sections.DesignSpec`.
    spec_model: ClassVar[type[BaseModel]]
    #: The spec key of the body's length along z, as messages name it ("body.length").
    length_key: ClassVar[str]
    #: A complete spec of this family (its reference design), as parsed YAML: every family's
    #: geometry, check and parts are tested on it.
    preset: ClassVar[dict]

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        missing = [a for a in ("name", "title", "spec_model", "length_key", "preset") if not hasattr(cls, a)]
        if missing:
            raise TypeError(f"family {cls.__name__} does not set {', '.join(missing)}")

    # ------------------------------------------------------------ geometry

    @abstractmethod
    def body(self, spec) -> Body:
        """The body the tubes run in, in frame F (its bottom face at z = 0)."""

    @abstractmethod
    def tubes(self, spec) -> tuple[Tube, ...]:
        """Every fluid channel's centreline in F, in the order geometry.yaml lists them."""

    def geometry(self, spec, source: dict | None = None) -> FiducialGeometry:
        """The geometry model of ``spec``: what geometry.yaml holds and what the CAD channels are swept along.

        ``source`` (the spec file and its hash) is recorded with this program's version.
        """
        if source is not None:
            source = {**source, "generator": f"chic-design {__version__}"}
        return FiducialGeometry(spec.name, self.body(spec), self.tubes(spec), source, tool=tool_frame(spec),
                                family=self.name, frame_coordinates=self.frame_coordinates(spec))

    def frame_coordinates(self, spec) -> FrameCoordinates | None:
        """The frame's own stereotactic coordinates for geometry.yaml (None: the file has none)."""
        return None

    def printed(self, spec) -> bool:
        """Whether ``build`` makes printed parts for ``spec`` (False: hardware described for the solver only,
        whose build writes geometry.yaml, pictures, check and report, and no part files)."""
        return True

    def required_tubes(self, geometry: FiducialGeometry) -> tuple[Tube, ...]:
        """The tubes an image must show as separate dots for a slice to be usable (default: all)."""
        return geometry.tubes

    # ------------------------------------------------------------ CAD

    @abstractmethod
    def parts(self, spec, geometry: FiducialGeometry):
        """The printed parts in F: :func:`chic_design.cad.parts.build_parts` of this family's body
        blank (the solid before the channels are cut) and its :class:`~chic_design.cad.parts.CapDims`.

        Returns :class:`~chic_design.cad.parts.FiducialParts`. Import the CAD kernel inside this
        method, so that ``check`` and ``schema`` start without it.
        """

    # ------------------------------------------------------------ feasibility

    @abstractmethod
    def unambiguity(self, geometry: FiducialGeometry, *, usable_ranges_mm, tolerance_mm: float,
                    symmetries: tuple[Symmetry, ...], min_mismatch_mm: float | None,
                    helix_crossings: tuple[Finding, ...]) -> tuple[Unambiguity, list[Finding], list[Finding]]:
        """Judge whether an image fixes the pose: ``(unambiguity, violations, warnings)``.

        ``symmetries`` are the rotations and reflections about the axis that map the
        tilt-0 marker pattern onto itself at depths in ``usable_ranges_mm`` (within
        ``tolerance_mm``; :func:`chic_design.feasibility.unambiguity.pattern_symmetries`),
        ``min_mismatch_mm`` how close any came; ``helix_crossings`` are already violations.
        """

    def usable_note(self, geometry: FiducialGeometry) -> str:
        """A line for ``check``'s summary saying what "usable" means for this family ("" for none)."""
        return ""

    def check(self, spec, pixel_size_mm: float | None = None,
              slice_thickness_mm: float | None = None) -> FeasibilityReport:
        """Feasibility of ``spec`` for its imaging protocol (pixel size and slice thickness overridable).

        Tilt limits and usable depth are judged on :meth:`required_tubes`. The generic checks of
        :func:`~chic_design.feasibility.engine.check_geometry` plus the rules ``build`` refuses even
        forced (:func:`~chic_design.feasibility.printability.build_violations`), so that a design ``check`` calls feasible always builds, and what the print check of the
        sliced plate will fail (:func:`~chic_design.printing.limits.print_violations`); for hardware
        that is not :meth:`printed`, none of the printability rules.
        """
        geom = self.geometry(spec)
        pixel = spec.imaging.pixel_size if pixel_size_mm is None else float(pixel_size_mm)
        thickness = spec.imaging.slice_thickness if slice_thickness_mm is None else float(slice_thickness_mm)
        required = self.required_tubes(geom)
        printed = self.printed(spec)
        report = check_geometry(geom, self, pixel_size_mm=pixel, slice_thickness_mm=thickness,
                                min_wall_mm=spec.print.min_wall, max_overhang_deg=spec.print.max_overhang_deg,
                                required_tubes=None if len(required) == len(geom.tubes) else required,
                                printed=printed)
        if not printed:  # nothing is printed: the rules of the build and the print plate do not apply
            return report
        extra = build_violations(spec, geom, pixel, self.length_key)
        port = spec.caps.fill_port_diameter
        extra += print_violations(print_settings(spec, geom), geom, report.overhangs, port)
        return replace(report, violations=report.violations + tuple(extra)) if extra else report

    # ------------------------------------------------------------ report

    @abstractmethod
    def report_head(self, spec, geometry: FiducialGeometry, cap_dims) -> ReportHead:
        """This family's title, frame F in words and dimension rows for ``report.md``.

        ``cap_dims`` are the :class:`~chic_design.cad.parts.CapDims` the parts were made with.
        """
