"""Simulate -> register -> the known pose: single slices of both CHIC designs, oblique placements, distractors,
missing tubes, slices leaving the body, no-lock cases and checked options.
"""

import math

import numpy as np
import pytest

from chic_register.errors import NoLock
from chic_register.imaging.simulate import simulate_slice
from chic_register.model.pose import rigid
from chic_register.pipeline.register import register
from tests.helpers import ACCURACY_TEST, check_round_trip

NEURO_POSES = [(25, 0, 0, 0), (10, 30, 45, 20), (40, 20, 200, -70), (25, 50, 120, 10), (30, 0, 0, 90)]


@pytest.mark.parametrize("pose", NEURO_POSES)
def test_simulate_then_register_neuro(neuro_geometry, pose):
    sim = simulate_slice(neuro_geometry, *pose, slice_thickness_mm=2.0, noise="uniform", noise_level=0.1, rng=7)
    reg = register([sim.slice], neuro_geometry, **ACCURACY_TEST)
    check_round_trip(reg, sim)
    assert reg.slices[0].n_tubes == 9
    assert set(reg.slices[0].residuals_mm) == set(neuro_geometry.ids)


@pytest.mark.parametrize("pose", [(20, 0, 0, 0), (12, 25, 60, 30), (28, 40, 300, -45)])
def test_simulate_then_register_needle_guide(needle_geometry, pose):
    sim = simulate_slice(needle_geometry, *pose, pixel_spacing_mm=(0.3, 0.3), slice_thickness_mm=1.5,
                         noise="rician", snr=25.0, rng=11)
    reg = register([sim.slice], needle_geometry, **ACCURACY_TEST)
    check_round_trip(reg, sim, depth_tol=0.15)


def test_oblique_scanner_placement_and_offset(neuro_geometry):
    c, s = math.cos(0.4), math.sin(0.4)
    T_si = rigid(np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]), (-40.0, 12.0, 7.0))
    sim = simulate_slice(neuro_geometry, 22, 15, 80, 5, T_scanner_from_image=T_si, center_offset_mm=(8, -5),
                         noise="uniform", rng=2)
    reg = register([sim.slice], neuro_geometry)
    check_round_trip(reg, sim)


def test_distractors_tool_and_a_missing_tube(neuro_geometry):
    sim = simulate_slice(neuro_geometry, 18, 20, 150, 30, noise="rician", snr=20, distractors=5, bore_signal=0.9,
                         missing_tubes=["D1"], rng=5)
    reg = register([sim.slice], neuro_geometry)
    check_round_trip(reg, sim)
    assert "D1" not in reg.slices[0].assignment and reg.slices[0].n_tubes == 8


def test_a_missing_orientation_marker_never_gives_a_wrong_pose(neuro_geometry):
    # without O0 the pattern is nearly symmetric: either the right pose or no lock, never a wrong "ok"
    sim = simulate_slice(neuro_geometry, 25, 0, 0, 0, noise="uniform", missing_tubes=["O0"], rng=1)
    try:
        reg = register([sim.slice], neuro_geometry)
    except NoLock as exc:
        assert "ambiguous" in exc.reason or "matched" in exc.reason or "precise" in exc.reason
    else:
        check_round_trip(reg, sim)


def test_a_slice_leaving_the_body_is_right_or_refused(neuro_geometry):
    sim = simulate_slice(neuro_geometry, 47, 45, 0, 0, noise="uniform", rng=3)  # a third of it above the top
    assert len(sim.truth.centres_px) < 9
    try:
        reg = register([sim.slice], neuro_geometry)
    except NoLock:
        return
    check_round_trip(reg, sim, depth_tol=0.3, angle_tol=1.5, point_tol=1.0)  # 7 tubes, 47 mm lever: less precise
    assert reg.slices[0].n_tubes == len(sim.truth.centres_px)


@pytest.mark.parametrize("kind", ["blank", "noise", "outside", "wrong_geometry"])
def test_no_lock_cases(neuro_geometry, needle_geometry, kind):
    if kind == "blank":
        sl = simulate_slice(neuro_geometry, 70, 0, 0, 0).slice  # beyond the body: nothing
        geom = neuro_geometry
    elif kind == "noise":
        sl = simulate_slice(neuro_geometry, 70, 0, 0, 0, noise="rician", snr=20, rng=3).slice
        geom = neuro_geometry
    elif kind == "outside":
        sl = simulate_slice(neuro_geometry, 53, 45, 0, 0, noise="uniform", rng=3).slice  # axis beyond the top
        geom = neuro_geometry
    else:
        sl = simulate_slice(neuro_geometry, 25, 10, 0, 0, noise="uniform", rng=3).slice
        geom = needle_geometry
    with pytest.raises(NoLock) as exc:
        register([sl], geom)
    assert exc.value.reason


def test_options_are_checked_and_used(neuro_geometry):
    sim = simulate_slice(neuro_geometry, 25, 20, 30, 0, noise="uniform", rng=0)
    with pytest.raises(TypeError):
        register([sim.slice], neuro_geometry, no_such_option=1)
    with pytest.raises(NoLock) as exc:  # demanding more tubes than the fiducial has
        register([sim.slice], neuro_geometry, min_tubes=10)
    assert "need at least 10" in exc.value.reason
