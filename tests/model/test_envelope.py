"""The design's plane checks on one plane (chic_register.model.envelope.plane_status)."""

from __future__ import annotations

from chic_register.model.envelope import plane_status


def test_plane_status_is_the_design_checks_on_one_plane(neuro_geometry):
    ok = plane_status(neuro_geometry, 25, 0, 0, 0.5, 2.0)
    assert ok.ok and ok.failure == "" and not ok.merged and not ok.outside
    # at depth 1 mm, tilt 0 each helix sits 11.4 deg from its diametric tube: 2.5 mm apart, 3 mm tubes overlap
    end = plane_status(neuro_geometry, 1, 0, 0, 0.5, 2.0)
    assert set(end.merged) == {("H0", "D0"), ("H1", "D1"), ("H2", "D2")}
    # a plane tilted through the top face misses tubes
    cut = plane_status(neuro_geometry, 48, 17, -122, 0.5, 1.0)
    assert not cut.ok and cut.failure == "tube_outside_body" and len(cut.outside) >= 1
