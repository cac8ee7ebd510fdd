"""The CHIC family (``family: chic``, the default): the paper's cylinder of diametric, helical and orientation tubes.

Modules: :mod:`.spec` (the spec model), :mod:`.layout` (its tubes in F),
:mod:`.cad` (annular body and round caps), :mod:`.check` (its unambiguity
rule), :mod:`.report` (its part of report.md).
"""

from __future__ import annotations

from chic_design.families.base import Family, ReportHead
from chic_design.families.chic.check import symmetric_pattern_findings
from chic_design.families.chic.layout import chic_body, chic_tubes
from chic_design.families.chic.report import chic_report_head
from chic_design.families.chic.spec import ChicSpec
from chic_design.feasibility.records import Unambiguity


class ChicFamily(Family):
    """CHIC: an annular body with straight and helical channels; one slice fixes the whole pose."""

    name = "chic"
    title = "CHIC fiducial"
    spec_model = ChicSpec
    length_key = "body.length"
    preset = {"name": "chic-prototype", "description": "The paper's prototype (Ma et al., Fig. 1-2)",
              "body": {"length": 50.0, "outer_diameter": 30.0, "inner_diameter": 20.0}, "channels": {"diameter": 3.0}}

    def body(self, spec):
        return chic_body(spec)

    def tubes(self, spec):
        return chic_tubes(spec)

    def parts(self, spec, geometry):
        from chic_design.families.chic.cad import chic_parts  # the CAD kernel: check and schema start without it

        return chic_parts(spec, geometry)

    def unambiguity(self, geometry, *, usable_ranges_mm, tolerance_mm, symmetries, min_mismatch_mm, helix_crossings):
        """Every symmetry of the tilt-0 pattern is a violation (:mod:`.check`)."""
        unamb = Unambiguity(tolerance_mm, min_mismatch_mm, symmetries, helix_crossings)
        return unamb, symmetric_pattern_findings(symmetries, tolerance_mm), []

    def report_head(self, spec, geometry, cap_dims) -> ReportHead:
        return chic_report_head(spec, geometry, cap_dims)
