"""The Tube protocol: both kinds implement it, and its methods agree with the tubes' own geometry."""

import math

import numpy as np
import pytest

from chic_register.model.tubes import (
    HelixTube,
    LineTube,
    Tube,
    sample_centreline,
    slab_reach_mm,
)

LINE = LineTube("D0", "diametric", (12.5, 0.0, 0.0), (12.5, 0.0, 50.0), 3.0)
SLANT = LineTube("Z1", "diagonal", (30.0, 30.0, 0.0), (30.0, -30.0, 60.0), 3.0)
HELIX = HelixTube("H0", "helix", radius=12.5, theta0_deg=10, pitch_deg_per_mm=1.4, z0=0, z1=50, diameter=3)


def test_both_kinds_are_tubes_and_the_protocol_is_abstract():
    assert isinstance(LINE, Tube) and isinstance(HELIX, Tube)
    assert not LINE.curved and HELIX.curved
    with pytest.raises(TypeError):
        Tube()


@pytest.mark.parametrize("tube", [LINE, SLANT, HELIX], ids=lambda t: t.id)
def test_bracket_params_span_the_tube_and_bracket_every_crossing(tube):
    t = tube.bracket_params()
    assert t[0] < 0 < 1 < t[-1] and np.all(np.diff(t) > 0)
    pts = tube.points(t)
    assert np.all(np.linalg.norm(np.diff(pts, axis=0), axis=1) <= 2.0 + 1e-9) or not tube.curved


@pytest.mark.parametrize("tube", [LINE, SLANT, HELIX], ids=lambda t: t.id)
def test_section_params_are_the_plane_crossings(tube):
    normal = np.array([math.sin(0.3), 0.0, math.cos(0.3)])
    origin = np.array([0.0, 0.0, 25.0])
    u = tube.section_params(origin, normal, margin_mm=6.0)
    assert len(u) >= 1
    assert (tube.points(u) - origin) @ normal == pytest.approx(np.zeros(len(u)), abs=1e-9)
    # a plane far beyond the tube: nothing to draw
    assert len(tube.section_params(np.array([0.0, 0.0, 500.0]), np.array([0.0, 0.0, 1.0]), 6.0)) == 0


@pytest.mark.parametrize("tube", [LINE, SLANT, HELIX], ids=lambda t: t.id)
def test_fluid_volume_is_pi_a_squared_times_the_length(tube):
    lo, hi = tube.z_range
    assert tube.fluid_volume_mm3(lo, hi) == pytest.approx(math.pi * (tube.diameter / 2) ** 2 * tube.length_mm)


def test_sample_and_slab_reach():
    pts = sample_centreline(HELIX, 0.5)
    assert np.array_equal(pts, HELIX.sample(0.5))
    assert np.max(np.linalg.norm(np.diff(pts, axis=0), axis=1)) <= 0.5
    # (radius + slice / 2) / cos(beta), floored at cos 1e-3, times the safety factor
    assert LINE.slab_reach_mm(0.5, 2.0) == pytest.approx(5.0)
    assert slab_reach_mm(1.5, np.array([1.0, 0.0]), 2.0, scale=2.0) == pytest.approx([5.0, 5000.0])


def test_sweep_path_asks_the_builder_for_its_kind():
    calls = []

    class Builder:
        @staticmethod
        def line(p0, p1):
            calls.append(("line", p0, p1))

        @staticmethod
        def helix(**kw):
            calls.append(("helix", kw))

    LINE.sweep_path(Builder)
    HELIX.sweep_path(Builder)
    assert calls[0] == ("line", (12.5, 0.0, 0.0), (12.5, 0.0, 50.0))
    assert calls[1][1] == dict(pitch=360.0 / 1.4, height=50, radius=12.5, lefthand=False, theta0_deg=10, z0=0)


def test_describe_is_the_report_row():
    assert LINE.describe() == ("line", "0.0", "-")
    assert HELIX.describe() == ("helix", "10.0 -> 80.0", "+1.4")


def test_helix_plane_crossings_are_roots_to_machine_precision():
    h = HelixTube("H0", "helix", 12.5, 10.0, 1.4, 0.0, 50.0, 3.0)
    rng = np.random.default_rng(1)
    for _ in range(20):
        n = np.array([*rng.uniform(-0.6, 0.6, 2), 1.0])  # up to 40 deg tilt: the plane meets the helix
        n /= np.linalg.norm(n)
        o = np.array([0.0, 0.0, rng.uniform(5, 45)])
        pts = h.intersect_plane(o, n)
        assert len(pts) >= 1
        assert np.all(np.abs((pts - o) @ n) < 1e-9)
        assert np.allclose(np.hypot(pts[:, 0], pts[:, 1]), 12.5)
