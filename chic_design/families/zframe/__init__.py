"""The Z-frame family (``family: zframe``): the classic seven-rod frame of 3D Slicer's ZFrameRegistration.

Modules: :mod:`.spec` (the spec model), :mod:`.layout` (its rods in F, as
z001), :mod:`.cad` (square frame and square caps), :mod:`.check` and
:mod:`.twins` (its unambiguity rule: symmetries are warnings),
:mod:`.report` (its part of report.md).
"""

from __future__ import annotations

from chic_design.families.base import Family, ReportHead
from chic_design.families.zframe.check import zframe_unambiguity
from chic_design.families.zframe.layout import zframe_body, zframe_tubes
from chic_design.families.zframe.report import zframe_report_head
from chic_design.families.zframe.spec import ZFrameSpec


class ZFrameFamily(Family):
    """Z-frame: four axial and up to four diagonal rods in a square frame; symmetric frames need a prior."""

    name = "zframe"
    title = "Z-frame fiducial"
    spec_model = ZFrameSpec
    length_key = "frame.height"
    preset = {"family": "zframe", "name": "zframe-z001", "description": "Slicer's z001: seven rods on a 60 mm cube"}

    def body(self, spec):
        return zframe_body(spec)

    def tubes(self, spec):
        return zframe_tubes(spec)

    def parts(self, spec, geometry):
        from chic_design.families.zframe.cad import zframe_parts  # the CAD kernel: check and schema start without it

        return zframe_parts(spec, geometry)

    def unambiguity(self, geometry, *, usable_ranges_mm, tolerance_mm, symmetries, min_mismatch_mm, helix_crossings):
        """Frame symmetries and slices with a twin pose are warnings (:mod:`.check`)."""
        unamb, warnings = zframe_unambiguity(geometry, usable_ranges_mm, min_mismatch_mm, helix_crossings,
                                             tolerance_mm)
        return unamb, [], warnings

    def usable_note(self, geometry) -> str:
        return (f"usable = all {len(geometry.tubes)} rods visible and separate (one blob each, at least one "
                "pixel apart), for every azimuth:")

    def report_head(self, spec, geometry, cap_dims) -> ReportHead:
        return zframe_report_head(spec, geometry, cap_dims)
