"""Signed images (chic_register.detect.magnitude): background blocks of both signs, and magnitude images with an
offset or shading that have none.
"""

from __future__ import annotations

import numpy as np


def test_a_magnitude_image_with_an_offset_or_shading_is_not_signed():
    """An offset subtracted from a magnitude image's noise moves every background block alike, shading scales them:
    neither gives blocks of both signs, nor do the constant blocks of a masked field (no noise samples); the same
    background under a cosine that turns negative does."""
    from chic_register.detect.magnitude import MIN_SIGNED_BLOCKS, signed_blocks

    rng = np.random.default_rng(5)
    noise = np.hypot(rng.standard_normal((128, 128)), rng.standard_normal((128, 128)))  # Rayleigh, sigma 1
    xx = np.mgrid[0:128, 0:128][1] / 128.0
    masked = np.where(np.hypot(*(np.mgrid[0:128, 0:128] - 64.0)) < 50, noise, 0.0)  # zero outside the field
    for img in (noise, noise - 1.2, noise - 3.0, noise * (0.3 + 1.5 * xx), masked - 0.5):
        assert min(signed_blocks(img, (), noise_sigma=1.0)) < MIN_SIGNED_BLOCKS
    assert min(signed_blocks(masked - 0.5, ())) >= MIN_SIGNED_BLOCKS  # its constant blocks, if counted
    negative, positive = signed_blocks(noise * np.cos(2 * np.pi * 0.8 * xx + 0.3), ())
    assert min(negative, positive) >= MIN_SIGNED_BLOCKS
