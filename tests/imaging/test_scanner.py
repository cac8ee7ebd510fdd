"""Scanner effects drawn into simulated slices, and the pose their images show."""

import dataclasses

import numpy as np
import pytest

from chic_register.imaging.scanner import ScannerEffects, apply_scanner_effects, body_footprint
from chic_register.imaging.simulate import simulate_slice
from chic_register.pipeline.register import register
from chic_register.studies.damage import pose_error
from chic_register.studies.distortion import apparent_pose


@pytest.fixture(scope="module")
def sim(neuro_geometry):
    return simulate_slice(neuro_geometry, 25, 30, 40, 10, noise="rician", snr=30, rng=1,
                          image_position=(-64.0, -64.0, 0.0))


def test_no_effect_leaves_the_pixels_as_they_are(sim):
    np.testing.assert_allclose(apply_scanner_effects(sim.slice, ScannerEffects(), 0), sim.slice.pixels, atol=1e-9)


def test_the_displacement_is_the_scale_about_the_isocentre_and_the_cubic_non_linearity():
    e = ScannerEffects((0.01, -0.02), 3.0)
    u, v = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    d = e.displacement_mm(np.array([[100.0, 0, 0], [0, 50.0, 0]]), u, v)
    np.testing.assert_allclose(d[0], [1.0 + 3.0, 0, 0])  # 1 % of 100 mm, and 3 mm at 100 mm
    np.testing.assert_allclose(d[1], [0, -1.0 + 3.0 * 0.5 * 0.25, 0])


def test_a_scaled_image_shows_another_pose_and_the_solver_finds_that_one(sim, neuro_geometry):
    """0.5 % along the rows: the image shows the fiducial 0.3-0.4 deg turned (the scale read as a tilt); the solve
    lands on the pose the image shows, not on the truth it cannot see."""
    e = ScannerEffects((0.0, 0.005))
    sl = dataclasses.replace(sim.slice, pixels=apply_scanner_effects(sim.slice, e, 0))
    shown = apparent_pose(neuro_geometry, sim.truth.T_scanner_from_fiducial, sim.slice, e)
    L = neuro_geometry.body.length
    assert pose_error(shown, sim.truth.T_scanner_from_fiducial, L)[1] > 0.2
    reg = register([sl], neuro_geometry)
    tre, rot = pose_error(reg.T_scanner_from_fiducial, shown, L)
    assert tre < 0.1 and rot < 0.15


def test_shading_and_tissue(sim):
    shaded = apply_scanner_effects(sim.slice, ScannerEffects(shading=0.6), 2)
    assert abs(shaded.mean() / sim.slice.pixels.mean() - 1.0) < 0.1 and not np.allclose(shaded, sim.slice.pixels)
    tissue = apply_scanner_effects(sim.slice, ScannerEffects(anatomy=5), 2)
    assert (tissue - sim.slice.pixels).max() > 0.2


def test_tissue_stays_out_of_the_fiducials_body(sim, neuro_geometry):
    """Tissue lies beside the fiducial, never inside its plastic, channels or bore: none is drawn on its footprint,
    which holds every tube's crossing."""
    T = sim.truth.T_scanner_from_fiducial
    body = body_footprint(sim.slice, T, 0.5 * neuro_geometry.body.outer_diameter, neuro_geometry.body.length)
    for r, c in sim.truth.centres_px.values():
        assert body[round(r), round(c)]
    assert 0 < body.mean() < 0.5
    tissue = apply_scanner_effects(sim.slice, ScannerEffects(anatomy=40), 3, no_tissue=body) - sim.slice.pixels
    assert np.abs(tissue[body]).max() < 1e-12 and tissue[~body].max() > 0.2
