"""The N-localizer family (``family: nlocalizer``): Brown-Roberts-Wells "N" plates of a stereotactic head frame.

Modules: :mod:`.spec` (the spec model), :mod:`.layout` (its rods in F, its body
and its stereotactic coordinates), :mod:`.cad` (rectangular ring and caps, for
printed frames), :mod:`.check` (its unambiguity rule: symmetries are warnings),
:mod:`.report` (its part of report.md).
"""

from __future__ import annotations

from chic_design.families.base import Family, ReportHead
from chic_design.families.nlocalizer.check import dot_tubes, nlocalizer_unambiguity
from chic_design.families.nlocalizer.layout import nlocalizer_body, nlocalizer_frame_coordinates, nlocalizer_tubes
from chic_design.families.nlocalizer.report import nlocalizer_report_head
from chic_design.families.nlocalizer.spec import NLocalizerSpec

#: The Leksell G CT indicator box (designs/leksell-g-ct.yaml): two lateral N-plates, commercial hardware.
LEKSELL_G_CT = {
    "family": "nlocalizer", "name": "leksell-g-ct", "hardware": "commercial",
    "description": "Leksell G CT indicator box: two lateral N-plates, 190 x 120 x 120 mm",
    "plates": [
        {"name": "right", "azimuth_deg": 180, "distance": 95, "width": 120, "diagonal_from": "right"},
        {"name": "left", "azimuth_deg": 0, "distance": 95, "width": 120, "diagonal_from": "left"},
    ],
    "frame": {"height": 120, "wall": 8}, "rods": {"diameter": 2},
    "coordinates": {"system": "leksell"},
    "imaging": {"pixel_size": 0.6, "slice_thickness": 1.0},
}


class NLocalizerFamily(Family):
    """N-localizer: N-plates of two vertical rods and a diagonal; symmetric frames need a prior."""

    name = "nlocalizer"
    title = "N-localizer"
    spec_model = NLocalizerSpec
    length_key = "frame.height"
    preset = LEKSELL_G_CT

    def body(self, spec):
        return nlocalizer_body(spec)

    def tubes(self, spec):
        return nlocalizer_tubes(spec)

    def frame_coordinates(self, spec):
        return nlocalizer_frame_coordinates(spec)

    def printed(self, spec) -> bool:
        return spec.printed

    def required_tubes(self, geometry):
        """The vertical rods and diagonals: edge rods lie in axial planes and never show as dots."""
        return dot_tubes(geometry)

    def parts(self, spec, geometry):
        from chic_design.families.nlocalizer.cad import nlocalizer_parts  # CAD kernel: not needed by check

        return nlocalizer_parts(spec, geometry)

    def unambiguity(self, geometry, *, usable_ranges_mm, tolerance_mm, symmetries, min_mismatch_mm, helix_crossings):
        """Frame symmetries and slices with a twin are warnings (:mod:`.check`)."""
        unamb, warnings = nlocalizer_unambiguity(geometry, usable_ranges_mm, min_mismatch_mm, helix_crossings,
                                                 tolerance_mm)
        return unamb, [], warnings

    def usable_note(self, geometry) -> str:
        dots = dot_tubes(geometry)
        edges = len(geometry.tubes) - len(dots)
        return (f"usable = all {len(dots)} vertical and diagonal rods visible and separate (one blob each, at "
                "least one pixel apart), for every azimuth"
                + (f" ({edges} edge rods lie in axial planes and are not required)" if edges else "") + ":")

    def report_head(self, spec, geometry, cap_dims) -> ReportHead:
        return nlocalizer_report_head(spec, geometry, cap_dims)
