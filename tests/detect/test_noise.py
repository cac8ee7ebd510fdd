"""Noise estimates (chic_register.detect.noise): neighbour differences beside bright regions, the noise correlation
of interpolated images and the blocks it is read from.
"""

from __future__ import annotations

import math

import numpy as np
import pytest


def test_difference_sigma_holds_beside_large_bright_regions():
    """Gaussian noise (sigma 2) over an image half of which is a bright slab: the neighbour-difference estimate is
    within 5 % of 2, where the pixels' own spread is twenty times that."""
    from chic_register.detect.noise import difference_sigma

    rng = np.random.default_rng(1)
    img = rng.normal(0.0, 2.0, (200, 200))
    img[:, 100:] += 80.0
    assert difference_sigma(img) == pytest.approx(2.0, rel=0.05)
    assert np.std(img) > 20.0


def test_noise_correlation_reads_an_interpolated_image_and_not_objects():
    """Neighbour correlation of the noise: ~0 for white Rician noise (with bright objects in part of the image), about
    0.7 once the image is zoomed 2x bilinearly (each new pixel half-shares its neighbour's noise)."""
    from scipy import ndimage as ndi

    from chic_register.detect.noise import (
        correlation_inflation,
        noise_correlation,
        noise_correlation_axes,
    )

    rng = np.random.default_rng(4)
    img = np.hypot(1.0 + rng.normal(0, 0.3, (160, 160)), rng.normal(0, 0.3, (160, 160)))
    img[20:60, 20:60] += 5.0 * np.hanning(40)[:, None] * np.hanning(40)[None]  # an object, not noise
    assert noise_correlation(img, ()) < 0.05
    zoomed = ndi.zoom(img, 2, order=1)
    assert 0.6 < noise_correlation(zoomed, ()) <= 0.8
    assert correlation_inflation(0.0) == correlation_inflation(0.3) == 1.0  # a reformat at its own pitch: 0.25-0.3
    assert correlation_inflation(0.7) == pytest.approx(1 / 0.3)

    def block_sum_factor(z):  # the spread of 16 x 16 sums against independent pixels'
        sums = z[:400, :400].reshape(25, 16, 25, 16).sum(axis=(1, 3))
        return math.sqrt(sums.var() / (256 * z[:400, :400].var()))

    white = rng.normal(0.0, 1.0, (400, 400))
    z = ndi.zoom(white[:200, :200], 2, order=1)
    assert correlation_inflation(noise_correlation_axes(z, ())) == pytest.approx(block_sum_factor(z), rel=0.15)
    # a motion blur shares the noise along one axis only: the mean of the two reads under the threshold, the axes do not
    blurred = ndi.convolve(white, np.ones((1, 5)) / 5)
    rows, cols = noise_correlation_axes(blurred, ())
    assert rows < 0.1 and 0.7 < cols and noise_correlation(blurred, ()) < 0.45
    assert correlation_inflation((rows, cols)) == pytest.approx(block_sum_factor(blurred), rel=0.15)


def test_clear_blocks_are_the_blocks_wholly_clear_of_blobs_and_finite():
    """The noise correlation's blocks, found from the footprints' boxes: the blocks whose every pixel is finite and
    outside every footprint's box grown by the guard (clear_of_blobs), footprints at the image's edges included."""
    from chic_register.detect.noise import clear_blocks, clear_of_blobs

    rng = np.random.default_rng(8)
    for shape in ((96, 96), (101, 77), (64, 130)):
        img = rng.normal(size=shape)
        img[rng.random(shape) < 0.002] = np.nan
        fps = [(int(rng.integers(-2, shape[0] - 3)), int(rng.integers(-2, shape[1] - 3)),
                rng.random((int(rng.integers(1, 14)), int(rng.integers(1, 14)))) < 0.7) for _ in range(12)]
        fps = [(max(r, 0), max(c, 0), m) for r, c, m in fps]
        for guard in (0, 3):
            keep = np.isfinite(img) & clear_of_blobs(shape, fps, guard)
            hb, wb = shape[0] // 8, shape[1] // 8
            want = keep[:hb * 8, :wb * 8].reshape(hb, 8, wb, 8).all(axis=(1, 3))
            np.testing.assert_array_equal(clear_blocks(img, fps, guard, 8), want)
            assert want.any() and not want.all()


def test_a_masked_background_is_read_where_it_is_not_masked():
    """A volume exported masked: 70 % of the slice set to exactly zero, Gaussian noise (sigma 4) on an offset of 50
    elsewhere. The noise is read from the unmasked pixels, not as zero."""
    from chic_register.detect.noise import background_noise

    rng = np.random.default_rng(0)
    img = 50.0 + rng.normal(0.0, 4.0, (128, 128))
    img[:, :90] = 0.0
    est = background_noise(img, [])
    assert est.sigma == pytest.approx(4.0, rel=0.1)
    clean = np.zeros((64, 64))  # a noise-free render: no noise to read, and none is made up
    assert background_noise(clean, []).sigma == 0.0
