"""The CHIC family's unambiguity rule: a tilt-0 marker pattern that maps onto itself is a violation.

A CHIC fiducial fixes twist and depth from one slice only if no rotation
about the axis or reflection maps its markers onto themselves; the
orientation tubes are there to break every such symmetry.
"""

from __future__ import annotations

from chic_design.feasibility.records import Finding, Symmetry


def symmetric_pattern_findings(symmetries: tuple[Symmetry, ...], tolerance_mm: float) -> list[Finding]:
    """One ``symmetric_pattern`` violation per depth range where the pattern maps onto itself."""
    out = []
    for sym in symmetries:
        a, b = sym.depth_range_mm
        out.append(Finding("symmetric_pattern", f"the tilt-0 marker pattern maps onto itself under a "
                           f"{sym.describe()} (worst marker off by {sym.mismatch_mm:.2f} mm at z = "
                           f"{sym.at_depth_mm:.2f} mm; tolerance {tolerance_mm:.2f} mm): twist/depth are "
                           "ambiguous; move the orientation tubes so that no tube is equally far "
                           "from its two neighbours", f"z {a:.2f}-{b:.2f} mm"))
    return out
