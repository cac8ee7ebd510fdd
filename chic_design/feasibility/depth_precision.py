"""Depth sensitivity: mm of depth per degree of helix angle, and the depth precision it gives.

Item 6 of :mod:`chic_design.feasibility.engine` (a centroid quantisation bound at the
protocol's pixel size). ``check`` reports it; :mod:`chic_design.feasibility.printability`
refuses a design whose helices turn too little to give a useful depth.
"""

from __future__ import annotations

import math

from chic_design.feasibility.records import DepthSensitivity
from chic_register.model.geometry import FiducialGeometry


def depth_sensitivity(geom: FiducialGeometry, pixel_size_mm: float) -> DepthSensitivity:
    """mm of depth per degree of helix angle and expected depth precision (:mod:`chic_design.feasibility.engine`, item 6)."""
    sigma_xy = pixel_size_mm / math.sqrt(12.0)
    per, sig = [], []
    for h in (t for t in geom.tubes if t.role == "helix" and hasattr(t, "pitch_deg_per_mm")):
        w = abs(h.pitch_deg_per_mm)
        per.append((h.id, 1.0 / w))
        sig.append((h.id, math.degrees(sigma_xy / h.radius) / w))
    combined = None
    if sig:
        inv = sum(1.0 / v**2 for _, v in sig if v > 0)
        combined = 0.0 if inv == 0 else 1.0 / math.sqrt(inv)
    return DepthSensitivity(tuple(per), sigma_xy, tuple(sig), combined)
