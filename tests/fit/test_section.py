"""The section fit (chic_register.fit.section) at the true pose: every crossing found, the joint pass's shared
pixels, the Rician mean model unbiased.
"""

from __future__ import annotations

import numpy as np
import pytest

from chic_register.fit.section import fit_sections
from chic_register.imaging.rician import rician_mean
from chic_register.imaging.simulate import simulate_slice
from chic_register.model.pose import invert
from chic_register.model.tube_model import plane_crossings, prepare_geometry


def test_section_fit_at_the_true_pose_finds_every_crossing(neuro_geometry):
    model, _ = prepare_geometry(neuro_geometry)
    sim = simulate_slice(neuro_geometry, 18.0, 30.0, 75.0, 20.0, slice_thickness_mm=2.0)
    T = invert(sim.truth.T_scanner_from_fiducial) @ sim.slice.T_scanner_from_image()
    q, _, _, found = plane_crossings(model, T, margin_mm=1e-9)
    fit, _ = fit_sections(model, T, np.where(found, 0, -1), np.asarray(sim.slice.pixels), (0.5, 0.5), 2.0, 0.05)
    assert fit.fitted.sum() >= 8
    k = np.flatnonzero(fit.fitted)
    # noise-free: each section found where its centreline crosses (curved helices, slab, tilt included)
    assert np.abs(fit.position_mm[k] - q[k]).max() < 0.004  # mm (0.008 px)
    assert np.allclose(fit.gain[k], 1.0, atol=0.02)
    assert np.all(np.linalg.eigvalsh(fit.info[k]) > 0)


def test_joint_pass_uses_the_pixels_neighbours_share(neuro_geometry):
    """Near an end (depth 5 mm, tilt 0) each helix runs 2-3 mm from its diametric tube: the separate fits leave
    the shared pixels out; the joint pass gives them back (neighbour subtracted), stays unbiased on a noise-free
    slice, and is more precise over noise draws (information larger)."""
    model, _ = prepare_geometry(neuro_geometry)
    sim = simulate_slice(neuro_geometry, 5.0, 0.0, 0.0, 0.0, slice_thickness_mm=2.0)
    T = invert(sim.truth.T_scanner_from_fiducial) @ sim.slice.T_scanner_from_image()
    q, _, _, found = plane_crossings(model, T, margin_mm=1e-9)
    args = (model, T, np.where(found, 0, -1), np.asarray(sim.slice.pixels), (0.5, 0.5), 2.0, 0.05)
    alone, _ = fit_sections(*args, joint=False)
    joint, _ = fit_sections(*args)
    k = np.flatnonzero(joint.fitted & alone.fitted)
    assert k.size >= 8
    assert (joint.n_pixels[k] >= alone.n_pixels[k]).all() and (joint.n_pixels[k] > alone.n_pixels[k]).sum() >= 2
    assert np.abs(joint.position_mm[k] - q[k]).max() < 0.004  # mm, noise-free: no bias from the subtraction
    gained = joint.n_pixels[k] > alone.n_pixels[k]
    assert (np.linalg.det(joint.info[k][gained]) > 1.02 * np.linalg.det(alone.info[k][gained])).all()


@pytest.mark.parametrize("pose", [(32.5, 0.0, 111.0, 24.0), (25.0, 45.0, 187.0, 0.0)])
def test_section_fit_of_the_rician_mean_image_is_unbiased(neuro_geometry, pose):
    """On the noise's mean image (what many draws average to) at the true pose, the Rician model puts every
    section where it is; the linear model reads the lifted faint edges as shifts of several thousandths of a
    pixel (the twist bias at SNR 50 was 0.6 of the bound from this)."""
    model, _ = prepare_geometry(neuro_geometry)
    sim = simulate_slice(neuro_geometry, *pose, slice_thickness_mm=2.0, supersample=16)
    T = invert(sim.truth.T_scanner_from_fiducial) @ sim.slice.T_scanner_from_image()
    q, _, _, found = plane_crossings(model, T, margin_mm=1e-9)
    assign = np.where(found, np.arange(found.size), -1)
    sigma = 0.1
    mean_img = sigma * rician_mean(sim.slice.pixels / sigma)[0]
    shifts = {}
    for rs in (0.0, sigma):
        sf, _ = fit_sections(model, T, assign, mean_img, (0.5, 0.5), 2.0, sigma, rician_sigma=rs)
        assert sf.fitted[found].all()
        shifts[rs] = np.linalg.norm(sf.position_mm - q, axis=1)[found] / 0.5  # pixels
    assert shifts[sigma].max() < 2e-3
    assert shifts[0.0].max() > 3e-3 and np.median(shifts[0.0]) > 1.5 * np.median(shifts[sigma])
