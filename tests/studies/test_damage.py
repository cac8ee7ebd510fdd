"""The false-lock hunts' cases (chic_register.studies.damage): a short seeded hunt, and the print hunt's
other-design and water-bath cases.
"""

from __future__ import annotations

import pytest

from chic_register.studies.damage import make_case, other_design_geometries, run_case, run_print_case
from tests.helpers import hunt_geometries


def test_short_seeded_hunt_has_no_false_lock_and_no_crash():
    """~10 s: 40 random damaged slices of both designs (benchmarks/hunt.py, seed 12)."""
    geoms = hunt_geometries()
    results = [run_case(make_case(i, 12, geoms), geoms) for i in range(40)]
    bad = [r for r in results if r["outcome"] in ("false_lock", "crash", "setup_error")]
    assert not bad, bad
    assert sum(r["outcome"] == "ok" for r in results) >= 1  # not vacuous: some slices lock, checked against the truth


@pytest.mark.parametrize("kind, cases", [("other_design", 12), ("water_bath", 12)])
def test_print_hunt_short(kind, cases):
    """The print hunt's cases (seed 5, as benchmarks/hunt_print.py runs them): slices solved with the other design's
    geometry file never lock, and fiducials in a water bath lock without a false lock (the full runs are in
    docs/benchmarks.md)."""
    geoms = hunt_geometries()
    wrong = other_design_geometries(geoms) if kind == "other_design" else None
    out = [run_print_case(i, 5, kind, 0.0, geoms, wrong)["outcome"] for i in range(cases)]
    assert "crash" not in out and "false_lock" not in out, out
    if kind == "other_design":
        assert set(out) == {"no_lock"}
    else:
        assert "ok" in out
