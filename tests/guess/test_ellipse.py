"""The robust ellipse fit of the first guess (chic_register.guess.ellipse)."""

import math

import numpy as np
import pytest

from chic_register.guess.ellipse import Ellipse, fit_ellipse_robust


def test_robust_ellipse_fit_recovers_axes_and_rejects_outliers():
    truth = Ellipse(np.array([40.0, 60.0]), 12.5 / math.cos(math.radians(35)), 12.5, math.radians(20))
    pts = truth.points(10)[:-1]
    outliers = np.array([[40.0, 60.0], [70.0, 20.0], [52.0, 60.0]])
    ell, inl = fit_ellipse_robust(np.vstack([pts, outliers]), 12.5, tol_mm=0.5)
    assert inl.tolist() == [True] * 9 + [False] * 3
    assert ell.a == pytest.approx(truth.a, abs=1e-6) and ell.b == pytest.approx(12.5, abs=1e-6)
    assert np.allclose(ell.centre, truth.centre, atol=1e-6)
    assert math.isclose(math.cos(2 * (ell.phi - truth.phi)), 1.0, abs_tol=1e-9)  # axis angle mod 180 deg
