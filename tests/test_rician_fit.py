"""The Rician mean in the section fit, the bound's counted tubes, and the efficiency benchmark's intervals."""

from __future__ import annotations

import numpy as np
import pytest

from chic_register.fit.section import fit_sections
from chic_register.imaging.rician import rayleigh_sigma, rician_mean, rician_signal
from chic_register.imaging.simulate import add_rician_noise, simulate_slice
from chic_register.model.pose import invert, slice_frame
from chic_register.model.tube_model import plane_crossings, prepare_geometry
from chic_register.precision.crlb import Protocol, counted_tubes, pose_crlb
from chic_register.studies.efficiency import pose_efficiency, ratio_interval


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


def test_the_bound_counts_the_tubes_the_plane_crosses(neuro_geometry):
    # 40 mm, 45 deg: two tubes cross the plane just beyond their ends, and the slab grazes them
    pose = (40.0, 45.0, 343.0, 32.0)
    T = slice_frame(*pose)
    assert len(counted_tubes(neuro_geometry, T)) == len(neuro_geometry.tubes) - 2
    assert len(counted_tubes(neuro_geometry, T, "all")) == len(neuro_geometry.tubes)
    p = Protocol(0.5, 2.0, 50.0)
    crossing = pose_crlb(neuro_geometry, *pose, p, quality="fast")
    every = pose_crlb(neuro_geometry, *pose, p, quality="fast", sections="all")
    assert every.sd_depth_mm < 0.75 * crossing.sd_depth_mm
    mid = (25.0, 45.0, 187.0, 0.0)  # every tube crosses: the same bound
    a = pose_crlb(neuro_geometry, *mid, p, quality="fast")
    b = pose_crlb(neuro_geometry, *mid, p, quality="fast", sections="all")
    assert a.sd_depth_mm == pytest.approx(b.sd_depth_mm, rel=1e-12)
    with pytest.raises(ValueError):
        counted_tubes(neuro_geometry, T, "some")


def test_ratio_interval_covers_the_truth_and_narrows_with_draws():
    rng = np.random.default_rng(2)
    crlb = np.array([1.0, 2.0, 0.5, 3.0])
    covered = 0
    for _ in range(40):
        e = rng.normal(size=(100, 4)) * crlb
        ci = ratio_interval(e, crlb, seed=1)
        covered += int(np.sum((ci[:, 0] <= 1.0) & (ci[:, 1] >= 1.0)))
    assert covered >= 0.88 * 160
    wide = np.diff(ratio_interval(rng.normal(size=(50, 4)) * crlb, crlb), axis=1)
    narrow = np.diff(ratio_interval(rng.normal(size=(800, 4)) * crlb, crlb), axis=1)
    assert np.all(narrow < 0.5 * wide)
    assert np.isnan(ratio_interval(np.zeros((1, 4)), crlb)).all()


def test_adaptive_draws_run_whole_batches_and_keep_every_draw(neuro_geometry):
    r = pose_efficiency(neuro_geometry, 25.0, 20.0, 30.0, 0.0, snr=20.0, draws=4, draws_max=12, seed=5,
                        crlb_quality="fast")
    assert r.draws in (4, 8, 12)
    assert r.errors.shape == (r.draws - r.no_lock, 4)
    assert np.allclose(r.rms, np.sqrt(np.mean(r.errors**2, axis=0)))
    assert r.ratio_ci.shape == (4, 2) and np.all(r.ratio_ci[:, 0] <= r.ratio) and np.all(r.ratio <= r.ratio_ci[:, 1])
    if r.draws < 12:  # stopped early: no interval contains the target
        assert not np.any((r.ratio_ci[:, 0] <= 1.15) & (r.ratio_ci[:, 1] >= 1.15))
