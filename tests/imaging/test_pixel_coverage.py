"""Pixel-coverage formulas (chic_register.imaging.pixel_coverage): a pixel's share inside a straight edge, a chord's
second moment.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from chic_register.imaging.pixel_coverage import blurred_box_edge, box_edge, chord_m2


def test_box_edge_is_the_pixel_share_inside_a_straight_edge():
    rng = np.random.default_rng(0)
    u = (np.arange(400) + 0.5) / 400 - 0.5  # 400 x 400 samples of a 0.5 x 0.4 mm pixel
    X, Y = np.meshgrid(u * 0.5, u * 0.4)
    for _ in range(40):
        phi = rng.uniform(0, 2 * np.pi)
        n = np.array([math.cos(phi), math.sin(phi)])
        d = rng.uniform(-0.4, 0.4)
        share = float(np.mean(X * n[0] + Y * n[1] <= d))
        got, slope = box_edge(np.array([d]), np.array([0.5 * abs(n[0])]), np.array([0.4 * abs(n[1])]))
        assert got[0] == pytest.approx(share, abs=3e-3)
        up, _ = box_edge(np.array([d + 1e-4]), np.array([0.5 * abs(n[0])]), np.array([0.4 * abs(n[1])]))
        assert slope[0] == pytest.approx((up[0] - got[0]) / 1e-4, rel=1e-2, abs=1e-2)


def test_chord_second_moment_matches_the_chord():
    rng = np.random.default_rng(1)
    for _ in range(40):
        phi = rng.uniform(0, 2 * np.pi)
        nx, ny = math.cos(phi), math.sin(phi)
        d = rng.uniform(-0.3, 0.3)
        tau = np.linspace(-2, 2, 400001)
        x, y = d * nx - tau * ny, d * ny + tau * nx
        on = tau[(np.abs(x) <= 0.25) & (np.abs(y) <= 0.2)]
        if on.size < 10:
            continue
        got = chord_m2(np.array([d]), np.array([nx]), np.array([ny]), 0.5, 0.4)[0]
        assert got == pytest.approx(float(np.mean(on**2)), rel=2e-3, abs=1e-6)


@pytest.mark.parametrize("sigma", [0.08, 0.3])
def test_a_blurred_edge_is_the_box_edge_convolved_with_the_point_spread(sigma):
    """The closed form against a numerical convolution of :func:`box_edge` with the Gaussian, its slope and its
    derivative in the variance against finite differences (to the erf approximation's 1e-7 over their steps); no
    blur is the box edge itself, and a pixel far from the edge is wholly in or out."""
    delta = np.linspace(-1.5, 1.5, 31)
    A, B = np.full(31, 0.5), np.full(31, 0.3)
    z = np.linspace(-7 * sigma, 7 * sigma, 6001)
    w = np.exp(-0.5 * (z / sigma) ** 2)
    w /= w.sum()
    numeric = np.array([np.sum(w * box_edge(d + z, np.full(z.size, 0.5), np.full(z.size, 0.3))[0]) for d in delta])
    share, slope, spread = blurred_box_edge(delta, A, B, sigma, spread=True)
    np.testing.assert_allclose(share, numeric, atol=2e-6)
    h = 1e-5
    np.testing.assert_allclose(slope, (blurred_box_edge(delta + h, A, B, sigma)[0]
                                       - blurred_box_edge(delta - h, A, B, sigma)[0]) / (2 * h), atol=1e-4)
    v, dv = sigma * sigma, 1e-7
    np.testing.assert_allclose(spread, (blurred_box_edge(delta, A, B, math.sqrt(v + dv))[0]
                                        - blurred_box_edge(delta, A, B, math.sqrt(v - dv))[0]) / (2 * dv), atol=2e-4)
    for got, want in zip(blurred_box_edge(delta, A, B, 0.0), box_edge(delta, A, B)):
        np.testing.assert_array_equal(got, want)
    assert blurred_box_edge(np.array([1e9, -1e9]), A[:2], B[:2], sigma)[0].tolist() == pytest.approx([1.0, 0.0])
