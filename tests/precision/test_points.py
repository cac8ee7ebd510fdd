"""A point's uncertainty under a pose covariance: its covariance, RMS and 95 % sphere radius."""

from __future__ import annotations

import numpy as np
import pytest

from chic_register.model.pose_params import tre_rms_mm
from chic_register.precision.points import PointUncertainty, point_covariance_F, sphere_radius_mm


@pytest.mark.parametrize("eigvals, radius", [((1.0, 1.0, 1.0), 2.795483), ((1.0, 0.0, 0.0), 1.959964),
                                             ((1.0, 1.0, 0.0), 2.447747), ((0.0, 0.0, 0.0), 0.0)])
def test_sphere_radius_of_the_chi_square_cases(eigvals, radius):
    assert sphere_radius_mm(np.diag(eigvals)) == pytest.approx(radius, abs=1e-6)
    assert sphere_radius_mm(4.0 * np.diag(eigvals)) == pytest.approx(2.0 * radius, abs=1e-6)  # scales with sigma


def test_sphere_radius_of_an_anisotropic_error_matches_sampling():
    cov = np.diag([4e-4, 1e-4, 1e-6])
    rng = np.random.default_rng(0)
    sampled = np.quantile(np.linalg.norm(rng.normal(size=(400_000, 3)) * np.sqrt(np.diag(cov)), axis=1), 0.95)
    assert sphere_radius_mm(cov) == pytest.approx(sampled, rel=3e-3)


def test_point_covariance_is_the_tre_propagation():
    rng = np.random.default_rng(2)
    A = rng.normal(size=(6, 6))
    cov = A @ A.T * 1e-2
    p = (5.0, -12.0, 30.0)
    u = PointUncertainty(point_covariance_F(cov, p))
    assert u.rms_mm == pytest.approx(tre_rms_mm(cov, p), rel=1e-12)
    assert np.allclose(u.sigma_mm ** 2, np.diag(u.covariance_mm2))
    assert set(u.to_dict()) == {"sigma_mm", "rms_mm", "radius95_mm", "covariance_mm2"}
