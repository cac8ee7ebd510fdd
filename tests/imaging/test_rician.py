"""The Rician mean (chic_register.imaging.rician): against Monte Carlo and its closed form, and the Rayleigh
background's noise scale.
"""

from __future__ import annotations

import numpy as np
import pytest

from chic_register.imaging.rician import rayleigh_sigma, rician_mean, rician_signal
from chic_register.imaging.simulate import add_rician_noise


def test_rician_mean_matches_magnitudes_of_noisy_signals():
    rng = np.random.default_rng(0)
    noise = rng.normal(size=(2, 400_000))
    for u in (0.0, 0.5, 1.5, 3.0, 8.0, 11.9, 12.1, 25.0):
        mc = float(np.mean(np.hypot(u + noise[0], noise[1])))
        g, slope = rician_mean(np.array([u]))
        assert g[0] == pytest.approx(mc, abs=4e-3)
        if u > 0:
            (up, down), _ = rician_mean(np.array([u + 1e-3, u - 1e-3]))
            assert slope[0] == pytest.approx((up - down) / 2e-3, abs=1e-3)
        else:
            assert slope[0] == pytest.approx(0.0, abs=1e-3)
    u = np.linspace(0.3, 30.0, 300)
    assert np.allclose(rician_signal(rician_mean(u)[0]), u, atol=1e-3)


def test_rician_mean_table_is_the_closed_form():
    """g(u) = sqrt(pi / 2) ((1 + 2x) I0e(x) + 2x I1e(x)), x = u^2 / 4: the table's quadrature to machine precision."""
    from scipy.special import i0e, i1e

    u = np.linspace(0.0, 12.0, 997)
    x = 0.25 * u * u
    exact = np.sqrt(np.pi / 2) * ((1 + 2 * x) * i0e(x) + 2 * x * i1e(x))
    g, d = rician_mean(u)
    assert np.abs(g - exact).max() < 2e-4  # the linear interpolation between the table's 0.02 steps
    assert rician_mean(np.array([0.0]))[0][0] == pytest.approx(np.sqrt(np.pi / 2), abs=1e-14)  # Rayleigh mean
    from chic_register.imaging.rician import rician_table

    u_tab, g_tab, _ = rician_table()
    x = 0.25 * u_tab * u_tab
    assert np.abs(g_tab - np.sqrt(np.pi / 2) * ((1 + 2 * x) * i0e(x) + 2 * x * i1e(x))).max() < 1e-13


def test_rayleigh_background_gives_the_noise_scale_and_other_noise_none():
    rng = np.random.default_rng(1)
    bg = add_rician_noise(np.zeros(20_000), 25.0, rng)  # sigma 0.04
    assert rayleigh_sigma(float(bg.mean()), float(bg.std())) == pytest.approx(0.04, rel=0.03)
    uniform = rng.uniform(-0.1, 0.1, 20_000)
    assert rayleigh_sigma(float(uniform.mean()), float(uniform.std())) == 0.0
    gauss = 0.3 + rng.normal(0, 0.04, 20_000)  # tissue: an offset background
    assert rayleigh_sigma(float(gauss.mean()), float(gauss.std())) == 0.0
