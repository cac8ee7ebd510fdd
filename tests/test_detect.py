"""Tube cross-section detection: sub-pixel centres, blank images, noise, distractors, touching tubes."""

import numpy as np
import pytest

from chic_register.detect import Blobs, detect_blobs, otsu_threshold
from chic_register.simulate import simulate_slice


def _nearest(blobs: Blobs, centres: dict) -> dict:
    """Distance (px) from each true centre to the nearest detected centre."""
    out = {}
    for tid, rc in centres.items():
        out[tid] = float(np.min(np.hypot(*(blobs.centres_rc - np.asarray(rc)).T)))
    return out


def test_centroid_of_a_hand_worked_blob():
    img = np.zeros((64, 64))
    img[10:17, 20:27] = 1.0
    img[10:17, 27] = 0.5  # a half-filled column on the right
    b = detect_blobs(img, (0.5, 0.5), 3.0)
    assert len(b) == 1
    # rows 10..16 -> 13; cols: (7 * (20 + ... + 26) + 3.5 * 27) / 52.5
    assert b.centres_rc[0, 0] == pytest.approx(13.0, abs=1e-9)
    assert b.centres_rc[0, 1] == pytest.approx((7 * sum(range(20, 27)) + 3.5 * 27) / 52.5, abs=1e-9)
    assert b.centres_rc.shape == (1, 2) and b.area_px.shape == b.axis_ratio.shape == (1,)


def test_blank_and_constant_images_give_no_blobs():
    assert len(detect_blobs(np.zeros((128, 128)), (0.5, 0.5), 3.0)) == 0
    assert len(detect_blobs(np.full((128, 128), 7.0), (0.5, 0.5), 3.0)) == 0
    assert len(detect_blobs(np.full((128, 128), np.nan), (0.5, 0.5), 3.0)) == 0


def test_otsu_splits_two_levels():
    img = np.concatenate([np.zeros(1000), np.ones(200)])
    t = otsu_threshold(img)
    assert 0.0 < t <= 1.0


@pytest.mark.parametrize("tilt,azimuth", [(0.0, 0.0), (30.0, 40.0)])
def test_noise_free_centres_are_sub_pixel(neuro_geometry, tilt, azimuth):
    sim = simulate_slice(neuro_geometry, 25.0, tilt, azimuth, 10.0, slice_thickness_mm=0.0)
    b = detect_blobs(sim.slice.pixels, sim.slice.pixel_spacing_mm, 3.0)
    err = _nearest(b, sim.truth.centres_px)
    assert len(err) == 9
    assert max(err.values()) < 0.02, err


def test_noisy_image_with_distractors_and_a_tool_keeps_every_tube(neuro_geometry):
    sim = simulate_slice(neuro_geometry, 20.0, 20.0, 70.0, 0.0, noise="rician", snr=15.0, distractors=4,
                         bore_signal=0.8, rng=3)
    b = detect_blobs(sim.slice.pixels, sim.slice.pixel_spacing_mm, 3.0)
    assert len(b) > 9  # the distractors are candidates too: the solver chooses
    err = _nearest(b, sim.truth.centres_px)
    assert max(err.values()) < 0.25, err


def test_touching_tubes_are_split(neuro_geometry):
    # at 5 mm depth each helix nearly touches a diametric tube: 17 deg apart
    sim = simulate_slice(neuro_geometry, 5.0, 0.0, 0.0, 0.0, slice_thickness_mm=0.0)
    b = detect_blobs(sim.slice.pixels, sim.slice.pixel_spacing_mm, 3.0)
    err = _nearest(b, sim.truth.centres_px)
    assert max(err.values()) < 0.15, err
    without = detect_blobs(sim.slice.pixels, sim.slice.pixel_spacing_mm, 3.0, split_touching=False)
    assert max(_nearest(without, sim.truth.centres_px).values()) > 0.5


def test_pure_noise_has_no_strong_candidates():
    rng = np.random.default_rng(0)
    b = detect_blobs(rng.uniform(0, 1, (256, 256)), (0.5, 0.5), 3.0)
    assert len(b) <= 3


def test_smoothing_is_repeated_binomial_passes_with_replicated_edges():
    from scipy import ndimage as ndi

    from chic_register.detect import _smooth

    rng = np.random.default_rng(1)
    for shape in [(64, 48), (5, 3), (1, 7), (7, 1), (2, 2)]:
        img = rng.uniform(0, 1, shape)
        for sigma, n in [(0.5, 1), (0.9, 2), (1.3, 3)]:
            ref = img.copy()
            for _ in range(n):
                for axis in (0, 1):
                    ref = ndi.correlate1d(ref, [0.25, 0.5, 0.25], axis=axis, mode="nearest")
            out = _smooth(img, sigma)
            assert out.dtype == np.float32 and out.shape == shape
            assert np.allclose(out, ref, atol=1e-6)
