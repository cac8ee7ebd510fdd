"""Lost pixels (scattered exact zeros, NaNs, extreme values) are found and filled from their neighbours amid signal,
and nothing else is touched (chic_register.detect.dropout).
"""

import numpy as np
import pytest

from chic_register.detect.dropout import fill_dropouts


def _disc_image(rng, size=64, level=10.0, sigma=1.0):
    """A bright disc (radius 12 px, ``level``) on a Rayleigh background of scale ``sigma``, (size, size)."""
    yy, xx = np.mgrid[:size, :size]
    disc = (yy - size / 2) ** 2 + (xx - size / 2) ** 2 < 12 ** 2
    re = level * disc + sigma * rng.standard_normal((size, size))
    im = sigma * rng.standard_normal((size, size))
    return np.hypot(re, im), disc


def test_zeros_inside_signal_are_filled_with_the_local_level():
    rng = np.random.default_rng(0)
    img, disc = _disc_image(rng)
    lost = rng.random(img.shape) < 0.3
    damaged = np.where(lost, 0.0, img)
    filled, n = fill_dropouts(damaged)
    inner = disc & lost & (np.abs(np.gradient(disc.astype(float))[0]) == 0)  # lost pixels in the disc, off its rim
    assert n >= inner.sum()
    assert np.median(filled[inner]) == pytest.approx(10.0, abs=1.0)
    assert np.all(filled[~lost] == damaged[~lost])  # valid pixels untouched


@pytest.mark.parametrize("kind", ["noise_free", "clipped_noise", "masked_half", "few_zeros"])
def test_images_without_dropouts_are_left_alone(kind):
    rng = np.random.default_rng(1)
    img, disc = _disc_image(rng)
    if kind == "noise_free":
        img = 10.0 * disc  # mostly zero: a render, not a noisy image with holes
    elif kind == "clipped_noise":  # a real-valued reconstruction with its negative noise clipped to zero
        img = np.clip(10.0 * disc + rng.uniform(-1, 1, img.shape), 0.0, None)
    elif kind == "masked_half":  # a volume masked outside the anatomy: a region of zeros
        img[:, :20] = 0.0
    elif kind == "few_zeros":  # an integer image rounding a handful of background pixels to 0
        img[rng.random(img.shape) < 0.001] = 0.0
    filled, n = fill_dropouts(img)
    assert n == 0 and filled is img


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.uint16, np.int32])
def test_integer_and_float_images_alike_with_and_without_zeros(dtype):
    """The image's range decides whether the zero test runs (no zero in a positive image): the same fills for every
    pixel type, and a positive image without dropouts comes back as it is."""
    rng = np.random.default_rng(2)
    img, disc = _disc_image(rng, level=400.0, sigma=40.0)
    img = np.maximum(np.round(img), 1.0).astype(dtype)  # positive: no zero anywhere
    filled, n = fill_dropouts(img)
    assert n == 0 and filled is img
    lost = rng.random(img.shape) < 0.2
    damaged = np.where(lost, 0, img).astype(dtype)
    filled, n = fill_dropouts(damaged)
    ref, n_ref = fill_dropouts(damaged.astype(np.float64))
    assert n == n_ref > 0 and np.array_equal(filled, ref)
    assert np.median(filled[disc & lost]) == pytest.approx(400.0, abs=40.0)


def test_every_zero_of_an_image_with_lost_samples_is_marked_lost():
    """The mask covers the filled zeros and the background's (not filled: a section fit's surroundings must leave
    them out too), and no valid pixel; an undamaged image has no mask."""
    from chic_register.detect.dropout import lost_pixels

    rng = np.random.default_rng(4)
    img = _disc_image(rng)[0]
    assert lost_pixels(img)[2] is None
    gone = rng.random(img.shape) < 0.3
    _, n, lost = lost_pixels(np.where(gone, 0.0, img))
    assert n > 0 and np.array_equal(lost, gone)


def test_a_callers_lost_mask_is_kept_beside_the_found_one():
    from chic_register.detect.dropout import fill_slice_dropouts
    from chic_register.model.slices import Slice

    rng = np.random.default_rng(6)
    img = _disc_image(rng)[0]
    gone = rng.random(img.shape) < 0.2
    given = np.zeros(img.shape, bool)
    given[5, :] = True  # a row the caller knows is bad
    (out,), filled = fill_slice_dropouts([Slice(np.where(gone, 0.0, img), (1.0, 1.0), lost=given)])
    assert np.array_equal(out.lost, gone | given) and filled
    (plain,), _ = fill_slice_dropouts([Slice(img, (1.0, 1.0), lost=given.astype(np.uint8))])
    assert plain.lost.dtype == bool and np.array_equal(plain.lost, given)
    with pytest.raises(ValueError, match="shape"):
        fill_slice_dropouts([Slice(img, (1.0, 1.0), lost=given[:10])])
