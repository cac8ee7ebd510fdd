"""The blurred fit (chic_register.fit.blurred): the pose fitted to the pixels through the blurred model of all
sections, its precision and covariance.
"""

import math

import numpy as np
import pytest

from chic_register.detect.blobs import detect_blobs
from chic_register.fit.blurred import blurred_fit
from chic_register.model.pose import invert
from chic_register.model.tube_model import prepare_geometry
from chic_register.pipeline.register import register
from tests.helpers import blurred_slice, tre_and_rotation


def test_noise_free_fit_recovers_the_pose_and_the_blur(neuro_geometry):
    """From a start 0.5 deg and 0.3 mm off, the fit lands on the true pose and the blur that made the image."""
    model, _ = prepare_geometry(neuro_geometry)
    sl, T_true, sigma_px = blurred_slice(neuro_geometry, (25, 30, 40, 10), 2.0, None, 0)
    start = invert(T_true)
    c, s = math.cos(math.radians(0.5)), math.sin(math.radians(0.5))
    turn = np.array([[c, -s, 0, 0.3], [s, c, 0, -0.2], [0, 0, 1, 0.1], [0, 0, 0, 1.0]])
    b = detect_blobs(sl.pixels, sl.pixel_spacing_mm, model.diameter_mm)
    fit = blurred_fit(model, turn @ start, [sl], [sl.T_scanner_from_image()], [b], [np.full(9, -1)])
    tre, rot = tre_and_rotation(invert(fit.T_F_from_scanner), T_true, neuro_geometry.body.length)
    assert tre < 0.005 and rot < 0.01
    assert fit.psf_px == pytest.approx(sigma_px, rel=0.01)


@pytest.mark.slow
def test_the_fit_is_more_accurate_than_the_blob_centres_and_knows_its_precision(neuro_geometry):
    """Blobs twice as wide, SNR 20, 8 seeded draws: the blurred fit's position error is well below the centroid
    pose's (merged neighbours pull centroids), its rotation no worse, and each error within 3.5 of its own
    predicted worst-direction sigma (a 3-D error against a 1-D sigma)."""
    model, _ = prepare_geometry(neuro_geometry)
    L = neuro_geometry.body.length
    centroid, blurred = [], []
    for seed in range(8):
        sl, T_true, _ = blurred_slice(neuro_geometry, (18, 25, 200, -60), 2.0, 20.0, seed)
        reg = register([sl], neuro_geometry, verify=False, blurred_fit=False, section_fit=False)
        centroid.append(tre_and_rotation(reg.T_scanner_from_fiducial, T_true, L))
        b = detect_blobs(sl.pixels, sl.pixel_spacing_mm, model.diameter_mm)
        a = np.array([reg.slices[0].assignment.get(t, -1) for t in model.ids])
        fit = blurred_fit(model, invert(reg.T_scanner_from_fiducial), [sl], [sl.T_scanner_from_image()], [b], [a])
        tre, rot = tre_and_rotation(invert(fit.T_F_from_scanner), T_true, L)
        s_tre, s_rot = fit.precision(L)
        assert tre < 3.5 * s_tre and rot < 3.5 * s_rot
        blurred.append((tre, rot))
    rms = lambda e: np.sqrt(np.mean(np.square(e), axis=0))  # noqa: E731
    (tre_b, rot_b), (tre_c, rot_c) = rms(blurred), rms(centroid)
    assert tre_b < 0.7 * tre_c and rot_b < rot_c


def test_covariance_in_f_by_hand():
    """A turn of the scanner-frame twist about c = (0, 0, 40) is, in F (here = the scanner), the same turn about F's
    origin plus the shift -r x c: a variance of e^2 on rx gives e^2 on rx and (40 e)^2 on ty, fully correlated."""
    from chic_register.fit.blurred import BlurredFit

    e = 1e-3
    cov = np.zeros((6, 6))
    cov[0, 0] = e * e
    fit = BlurredFit(np.eye(4), 1.0, cov, np.array([0.0, 0.0, 40.0]), 1.0, 100)
    C = fit.covariance_F()
    d = math.degrees(e)
    assert C[0, 0] == pytest.approx(d * d, rel=1e-6)
    assert C[4, 4] == pytest.approx((40 * e) ** 2, rel=1e-6)
    assert C[0, 4] == pytest.approx(d * 40 * e, rel=1e-6)
    assert np.abs(C[[1, 2, 3, 5]][:, [1, 2, 3, 5]]).max() < 1e-12
