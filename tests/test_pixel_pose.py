"""The optional pose refinement on the pixels (chic_register.pixel_pose): recovery, no bias, safeguards, precision."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from chic_register.crlb import Protocol, pose_crlb
from chic_register.efficiency import pose_errors
from chic_register.pixel_pose import pixel_pose_refine
from chic_register.pose import invert
from chic_register.section import section_windows
from chic_register.simulate import add_rician_noise, simulate_slice
from chic_register.solve import plane_crossings, prepare_geometry, register
from chic_register.tube_model import _exp_se3

TARGET = (0.0, 0.0, 25.0)


def _windows(model, T_F_from_scanner, sl):
    """The section fit's windows at a pose, every tube the slice shows assigned."""
    T = T_F_from_scanner @ sl.T_scanner_from_image()
    q, tan, _, found = plane_crossings(model, T, margin_mm=1e-9)
    todo = np.flatnonzero(found)
    win = section_windows(model, q, tan, found, todo, sl.pixels.shape, sl.pixel_spacing_mm, sl.slice_thickness_mm)
    return win, np.where(found, 0, -1)


def _errors(X, sim):
    return pose_errors(invert(X), sim.truth.T_scanner_from_fiducial, sim.slice.T_scanner_from_image(), TARGET)


@pytest.mark.parametrize("pose", [(30.0, 3.0, 40.0, 10.0), (18.0, 30.0, 75.0, 20.0)])
def test_refinement_recovers_a_perturbed_pose_on_a_noise_free_slice(neuro_geometry, pose):
    """Started 0.3 deg and 0.1 mm off, Gauss-Newton on the pixels returns to the truth (no bias, right Jacobian)."""
    model, _ = prepare_geometry(neuro_geometry)
    sim = simulate_slice(neuro_geometry, *pose, slice_thickness_mm=2.0)
    X_true = invert(sim.truth.T_scanner_from_fiducial)
    win, assign = _windows(model, X_true, sim.slice)
    X0 = X_true @ _exp_se3(np.array([math.radians(0.2), -math.radians(0.2), math.radians(0.1), 0.1, -0.05, 0.08]))
    before = _errors(X0, sim)
    out = pixel_pose_refine(model, X0, [sim.slice.T_scanner_from_image()], [sim.slice], [win], [assign], steps=4,
                            max_step_sigma=math.inf, noise_sigma=0.05)
    after = _errors(out.T_F_from_scanner, sim)
    assert out.moved and out.ssr_after < 0.01 * out.ssr_before
    assert before[0] > 0.2 and after[0] < 0.01  # deg, image normal
    assert abs(after[1]) < 0.01 and abs(after[2]) < 0.003 and after[3] < 0.003  # twist deg; depth, TRE mm


def test_a_step_longer_than_its_limit_is_rejected(neuro_geometry):
    model, _ = prepare_geometry(neuro_geometry)
    sim = simulate_slice(neuro_geometry, 30.0, 3.0, 40.0, 10.0, slice_thickness_mm=2.0)
    X_true = invert(sim.truth.T_scanner_from_fiducial)
    win, assign = _windows(model, X_true, sim.slice)
    X0 = X_true @ _exp_se3(np.array([0.004, 0.0, 0.0, 0.0, 0.1, 0.0]))
    out = pixel_pose_refine(model, X0, [sim.slice.T_scanner_from_image()], [sim.slice], [win], [assign], steps=2,
                            max_step_sigma=3.0, noise_sigma=0.05)
    assert not out.moved and np.array_equal(out.T_F_from_scanner, X0)
    assert len(out.step_sigma) == 1 and out.step_sigma[0] > 3.0  # 0.23 deg and 0.1 mm: many SDs at SNR 20
    # and through the solver on the noise-free slice (noise read as ~0, floored at 1 % of the fluid for the
    # weights): whether or not its step is kept, no bias
    reg = register([sim.slice], neuro_geometry, pixel_pose_steps=1)
    e = pose_errors(reg.T_scanner_from_fiducial, sim.truth.T_scanner_from_fiducial, sim.slice.T_scanner_from_image(),
                    TARGET)
    assert e[0] < 0.02 and abs(e[2]) < 0.005 and e[3] < 0.005


def test_refinement_over_noise_draws_at_a_near_normal_slice(neuro_geometry):
    """20 seeded Rician draws (SNR 20) of the normal slice at 40 mm: steps are taken, the refined pose is as precise
    as the section fit's (within 10 %) and within 1.25x the Cramér-Rao bound (normal angle, TRE)."""
    model, _ = prepare_geometry(neuro_geometry)
    snr = 20.0
    sim = simulate_slice(neuro_geometry, 40.0, 0.0, 0.0, 0.0, slice_thickness_mm=2.0)
    bound = pose_crlb(neuro_geometry, 40.0, 0.0, 0.0, 0.0, Protocol(snr=snr), TARGET, quality="fast")
    rng = np.random.default_rng(11)
    base, refined, moved = [], [], 0
    for _ in range(20):
        sl = dataclasses.replace(sim.slice, pixels=add_rician_noise(sim.slice.pixels, snr, rng))
        reg = register([sl], neuro_geometry, trust_rot_deg=math.inf, trust_tre_mm=math.inf)
        X = invert(reg.T_scanner_from_fiducial)
        win, assign = _windows(model, X, sl)
        out = pixel_pose_refine(model, X, [sl.T_scanner_from_image()], [sl], [win], [assign], steps=2,
                                noise_sigma=1.0 / snr)
        moved += out.moved
        base.append(_errors(X, sim))
        refined.append(_errors(out.T_F_from_scanner, sim))
    rms_base = np.sqrt(np.mean(np.square(base), axis=0))
    rms = np.sqrt(np.mean(np.square(refined), axis=0))
    assert moved >= 16
    assert rms[0] < 1.1 * rms_base[0] and rms[3] < 1.1 * rms_base[3]
    assert rms[0] < 1.25 * bound.sd_normal_deg and rms[3] < 1.25 * bound.tre_mm
