"""Choosing from the Pareto set, and comparing two designs objective by objective."""

from __future__ import annotations

import numpy as np

from chic_design.optimize.score import DIRECTIONS, OBJECTIVES

LABELS = {"outer_diameter_mm": ("outer diameter", "mm"),
          "usable_region_deg_mm": ("usable tilt x depth region", "deg mm"),
          "tre_mm": ("predicted TRE at target (worst required pose)", "mm")}


def ideal_distances(front: list[dict]) -> np.ndarray:
    """Distance of each design to the ideal point, each objective scaled to [0, 1] (0 = best) over the set."""
    if not front:
        return np.empty(0)
    V = np.array([[r["objectives"][k] for k in OBJECTIVES] for r in front], dtype=float)
    V = V * np.array([1.0 if d == "minimize" else -1.0 for d in DIRECTIONS])
    span = V.max(axis=0) - V.min(axis=0)
    N = (V - V.min(axis=0)) / np.where(span > 0, span, 1.0)
    return np.sqrt((N ** 2).sum(axis=1))


def knee_order(front: list[dict]) -> list[int]:
    """Pareto designs ordered by :func:`ideal_distances`; the first is chosen (the best compromise)."""
    dist = ideal_distances(front)
    return [int(i) for i in np.lexsort((np.arange(len(front)), dist))]


def compare(a: dict, b: dict) -> list[dict]:
    """Per objective: a's and b's values, the difference a - b, and whether a is better, equal or worse."""
    out = []
    for k, d in zip(OBJECTIVES, DIRECTIONS):
        va, vb = a["objectives"][k], b["objectives"][k]
        better = va < vb if d == "minimize" else va > vb
        same = abs(va - vb) <= 1e-9 * max(1.0, abs(vb))
        rel = (va - vb) / abs(vb) if vb else float("nan")
        out.append({"objective": k, "label": LABELS[k][0], "unit": LABELS[k][1], "a": va, "b": vb,
                    "diff": va - vb, "rel": rel, "verdict": "equal" if same else ("better" if better else "worse")})
    return out


def weakly_dominating(front: list[dict], ref: dict) -> list[dict]:
    """Pareto designs at least as good as ``ref`` on every objective."""
    return [r for r in front if all(c["verdict"] != "worse" for c in compare(r, ref))]
