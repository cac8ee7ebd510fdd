"""The verification's windows (chic_register.verify.windows): a section's aspect error and its shift, against noisy
draws.
"""

from __future__ import annotations

import math

import numpy as np

import chic_register.verify.windows as vw


def test_aspect_standard_error_matches_the_scatter_of_noisy_sections():
    """A tilted section's spread aspect (column over row, :func:`window_spread`) measured in 2000 noisy draws scatters as
    :func:`aspect_error` predicts from the pixel noise (within 15 %), at a low and a moderate SNR."""
    from chic_register.verify.windows import aspect_error, window_spread

    r, c = np.mgrid[0:15, 0:19].astype(float)
    section = np.clip(1.0 - np.hypot((r - 7.0) / 3.0, (c - 9.0) / 4.5), 0.0, 0.3) / 0.3  # an ellipse, 3 x 4.5 px
    support = section > 0.0
    rng = np.random.default_rng(4)
    for sigma in (0.12, 0.04):
        aspects, predicted = [], []
        for _ in range(2000):
            w = (section + rng.normal(0.0, sigma, section.shape)) * support
            v = window_spread(w)
            aspects.append(math.sqrt(v[1] / v[0]))
            predicted.append(aspect_error(w, support, v, sigma))
        rel = np.std(aspects) / np.mean(aspects)
        assert abs(np.median(predicted) / rel - 1.0) < 0.15, (sigma, rel, np.median(predicted))


def test_a_shifted_section_is_measured():
    """section_shift reads a section rendered 1.5 px off its window's prediction as ~1.5 px, and an unshifted one as
    ~0, with a standard error that follows the noise."""
    from chic_register.imaging.psf import gaussian_blur

    yy, xx = np.mgrid[0:24, 0:24]

    def disc(r0, c0):
        return gaussian_blur((np.hypot(yy - r0, xx - c0) < 4.0).astype(float), 0.7)

    w = vw.TubeWindow(0, 0, 0, disc(12.0, 12.0), np.zeros((24, 24)))
    rng = np.random.default_rng(0)
    for true_shift in (0.0, 1.5):
        y = (0.1 + disc(12.0, 12.0 + true_shift) + rng.normal(0, 0.02, (24, 24))).ravel()
        coef, y, _ = vw.fit_window(y.reshape(24, 24), w)
        shift, se = vw.section_shift(w, y, coef, 0.02)
        assert abs(shift - true_shift) < 0.35 and 0 < se < 0.05
