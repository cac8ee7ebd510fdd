"""Blobs drawn wider than their channels, as real images show them."""


import numpy as np
import pytest
from scipy import ndimage

from chic_design.families import family_of
from chic_design.spec import load_spec
from chic_register.imaging.blob_width import BlobWidth, render_tubes_widened
from chic_register.imaging.simulate import simulate_slice
from chic_register.model.pose import slice_frame
from tests.conftest import ZFRAME


@pytest.mark.parametrize("factor", [1.5, 2.0, 2.5])
def test_blob_width_factor_gives_that_full_width_at_half_maximum(factor):
    spec = load_spec(ZFRAME)
    tube = family_of(spec).geometry(spec).tube("A0")
    bw = BlobWidth.for_tube(tube.diameter, factor)
    # an axial rod in a thin axial slice, 0.05 mm pixels: measure the profile through its centre
    T = slice_frame(30.0, 0.0, 0.0, 0.0)
    T[:3, 3] = (30.0, -30.0, 30.0)  # the slice frame's origin on the rod
    img = render_tubes_widened([tube], T, (301, 301), (0.05, 0.05), 0.0, supersample=2, blob_width=factor)
    row = img[150]
    assert row.max() == pytest.approx(1.0, abs=0.01)  # peak kept at the fluid signal
    above = np.flatnonzero(row >= 0.5 * row.max())
    fwhm = (above[-1] - above[0] + 1) * 0.05
    assert fwhm == pytest.approx(factor * tube.diameter, abs=0.1)
    assert bw.sigma_mm > 0 and bw.gain > 1


def test_narrow_blobs_and_centroids_at_any_width(zframe_geometry):
    areas = {}
    for factor in (0.7, 1.0, 2.0):
        sim = simulate_slice(zframe_geometry, 25.0, 12.0, 30.0, 10.0, shape=(220, 220), slice_thickness_mm=1.0,
                             blob_width=factor, supersample=3)
        img = sim.slice.pixels
        labels, n = ndimage.label(img > 0.05)
        assert n == 7, factor
        cents = ndimage.center_of_mass(img, labels, range(1, n + 1))
        for tid, (r, c) in sim.truth.centres_px.items():
            d = min(np.hypot(r - a, c - b) for a, b in cents)
            assert d < 0.05, (factor, tid, d)  # symmetric widening: centroids stay put (pixels)
        areas[factor] = img.sum()
        assert sim.truth.settings["blob_width"] == factor
    assert areas[0.7] / areas[1.0] == pytest.approx(0.49, rel=0.05)  # a 0.7x narrower lumen
    assert areas[2.0] > 3 * areas[1.0]
    with pytest.raises(ValueError, match="blob width factor must be 0.2..5, got 9"):
        BlobWidth.for_tube(3.0, 9.0)
