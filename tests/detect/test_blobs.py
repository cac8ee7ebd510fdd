"""Tube cross-section detection: sub-pixel centres, blank images, noise, distractors, touching tubes."""

import math

import numpy as np
import pytest
from scipy import ndimage as ndi

from chic_register.detect.blobs import Blobs, detect_blobs, otsu_threshold
from chic_register.detect.disc import disc_contrast
from chic_register.imaging.simulate import simulate_slice
from tests.helpers import rician_slice, zframe


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

    from chic_register.detect.filters import gaussian_smooth

    rng = np.random.default_rng(1)
    for shape in [(64, 48), (5, 3), (1, 7), (7, 1), (2, 2)]:
        img = rng.uniform(0, 1, shape)
        for sigma, n in [(0.5, 1), (0.9, 2), (1.3, 3)]:
            ref = img.copy()
            for _ in range(n):
                for axis in (0, 1):
                    ref = ndi.correlate1d(ref, [0.25, 0.5, 0.25], axis=axis, mode="nearest")
            out = gaussian_smooth(img, sigma)
            assert out.dtype == np.float32 and out.shape == shape
            assert np.allclose(out, ref, atol=1e-6)


def test_smoothing_scaled_at_the_end_is_the_same_to_the_bit():
    from chic_register.detect.filters import gaussian_smooth

    rng = np.random.default_rng(2)
    for lo, hi in [(1e-25, 1e-24), (0.5, 4095.0), (1.0, 1e25), (1e-20, 1e20)]:
        img = np.exp(rng.uniform(np.log(lo), np.log(hi), (61, 47)))
        for sigma in (0.5, 0.9, 1.3):
            assert np.array_equal(gaussian_smooth(img, sigma, scale_at_end=True), gaussian_smooth(img, sigma))


def test_maximum_filter_is_scipys():

    from chic_register.detect.filters import maximum_filter

    rng = np.random.default_rng(3)
    for _ in range(300):
        shape, size = tuple(rng.integers(1, 25, 2)), int(rng.choice([1, 3, 5, 7, 9, 13]))
        vals = rng.normal(size=shape).astype(np.float32)
        vals[rng.random(shape) < 0.3] = -np.inf
        ref = ndi.maximum_filter(vals, size=size, mode="constant", cval=-np.inf)
        assert np.array_equal(maximum_filter(vals, size), ref)


def test_footprints_areas_and_means_follow_the_per_blob_rules():
    """Blobs close enough that neighbours fall in each other's boxes and in the ring around them: every footprint is
    the blob dilated by one pixel less the neighbours' own dilations within its box, areas and means the blob's own."""
    import cc3d

    from chic_register.detect.filters import dilate, gaussian_smooth

    rng = np.random.default_rng(4)
    yy, xx = np.mgrid[:96, :96]
    for trial in range(6):
        img = rng.normal(10.0, 1.0, (96, 96))
        # rows and columns of discs 7-10 px apart: gaps of a pixel or two between many of them
        rows, cols = np.cumsum(rng.uniform(7.0, 10.0, 9)), np.cumsum(rng.uniform(7.0, 10.0, 9))
        for r in rows[rows < 90]:
            for c in cols[cols < 90]:
                img += 60.0 * (np.hypot(yy - r, xx - c) < rng.uniform(2.3, 3.2))
        b = detect_blobs(img, (0.5, 0.5), 3.0, smooth_sigma_px=0.9, split_touching=False, size_from_image=False)
        assert len(b) >= 30
        labels = cc3d.connected_components(gaussian_smooth(img, 0.9) > b.threshold, connectivity=4)
        for (r0, c0, foot), area, mean in zip(b.footprints, b.area_px, b.mean_intensity):
            lab = labels[r0:r0 + foot.shape[0], c0:c0 + foot.shape[1]]
            own = np.bincount(lab[foot & (lab > 0)]).argmax()
            blob = lab == own
            others = (lab != 0) & ~blob
            ref = dilate(blob) & ~dilate(others) if others.any() else dilate(blob)
            assert np.array_equal(foot, ref)
            assert area == np.count_nonzero(labels == own)  # the whole component lies in its box
            assert mean == img[r0:r0 + foot.shape[0], c0:c0 + foot.shape[1]][blob].sum() / area


def test_otsu_is_the_histogram_rule():
    """The threshold equals the textbook computation (every value in one of ``bins`` equal bins, the top value in
    the last) on images whose maximum sits exactly at the top edge."""

    def reference(image, bins=256):
        lo, hi = float(image.min()), float(image.max())
        q = np.minimum(((image.ravel() - lo) * (bins / (hi - lo))).astype(np.intp), bins - 1)
        hist = np.bincount(q, minlength=bins).astype(float)
        centres = lo + (np.arange(bins) + 0.5) * (hi - lo) / bins
        w0 = np.cumsum(hist)
        w1 = w0[-1] - w0
        m0 = np.cumsum(hist * centres)
        mu0 = m0 / np.maximum(w0, 1e-12)
        mu1 = (m0[-1] - m0) / np.maximum(w1, 1e-12)
        k = int(np.argmax((w0 * w1 * (mu0 - mu1) ** 2)[:-1]))
        return float(lo + (k + 1) * (hi - lo) / bins)

    rng = np.random.default_rng(6)
    for dtype in (np.float32, np.float64):
        for _ in range(50):
            img = np.concatenate([rng.normal(0, 1, 3000), rng.normal(rng.uniform(3, 30), 1, 400)]).astype(dtype)
            img[rng.integers(img.size, size=rng.integers(1, 5))] = img.max()  # ties at the top edge
            assert otsu_threshold(img.reshape(68, 50)) == reference(img.reshape(68, 50))


def test_median_is_numpys_on_both_sides_of_the_bracketed_size():
    from chic_register.detect.blobs import MEDIAN_SPAN_MIN, median

    rng = np.random.default_rng(5)
    for n in (1, 2, 9, MEDIAN_SPAN_MIN - 1, MEDIAN_SPAN_MIN, 4096, 4097, 16384):
        for x in (rng.normal(size=n), rng.normal(size=n).astype(np.float32), rng.integers(0, 5, n),
                  np.abs(rng.normal(size=n) + 1j * rng.normal(size=n))):
            assert median(x) == float(np.median(np.asarray(x, float)))  # (float32: the middle pair's mean in float64)
    img = rng.normal(size=(256, 256)).astype(np.float32)
    assert median(img[::4, ::4]) == float(np.median(img[::4, ::4].astype(float)))  # a strided view, as detect's


def test_wide_z_frame_blob_is_never_split(z001):
    """Channels rendered 2.5 times as wide as the file says: one candidate per rod, its width measured."""
    sl, _ = rician_slice(z001, (30, 5, 20, 0), render_geom=zframe(7.5), seed=4)
    b = detect_blobs(sl.pixels, sl.pixel_spacing_mm, [t.diameter for t in z001.tubes])
    assert len(b) == 7 and 6.0 < b.width_mm < 8.5
    thin, _ = rician_slice(z001, (30, 5, 20, 0), render_geom=zframe(2.1), seed=4)
    assert len(detect_blobs(thin.pixels, thin.pixel_spacing_mm, 3.0)) == 7


def test_a_disc_contrast_is_the_mean_above_the_background_in_noise_sigmas():
    """A flat disc 4 units above a background of 10 with noise sigma 2 reads 2 sigmas at its centre, the plain
    background 0, and no noise gives NaN."""
    img = np.full((40, 40), 10.0)
    rr, cc = np.mgrid[:40, :40]
    img[(rr - 20) ** 2 + (cc - 20) ** 2 <= 36] = 14.0
    assert disc_contrast(img, 10.0, 2.0, (20, 20), 5.0) == pytest.approx(2.0)
    assert disc_contrast(img, 10.0, 2.0, (5, 5), 3.0) == pytest.approx(0.0)
    assert math.isnan(disc_contrast(img, 10.0, 0.0, (20, 20), 5.0))
