"""An infeasible design's error lists one violation per line."""

from __future__ import annotations


def test_infeasible_build_lists_one_violation_per_line():
    from types import SimpleNamespace

    from chic_design.errors import InfeasibleDesign

    vs = [SimpleNamespace(code=f"c{i}", where=f"w{i}", message=f"m{i}") for i in range(18)]
    text = str(InfeasibleDesign("spec.yaml", vs))
    lines = text.splitlines()
    assert len(lines) == 19 and "18 violations" in lines[0] and lines[5] == "  - c4 (w4): m4"
    assert max(len(x) for x in lines) < 200
