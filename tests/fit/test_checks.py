"""The fit's statistical checks (chic_register.fit.checks): the chi-square quantile without scipy."""

from __future__ import annotations

import pytest


def test_chi_square_quantile_without_scipy_matches_scipy():
    from scipy.special import gammainc, gammaincinv

    from chic_register.fit.checks import gamma_p, gamma_p_inverse

    for a in (1.5, 3.0, 4.5, 10.0, 27.0, 100.0):
        for p in (0.01, 0.1, 0.5, 0.9):
            assert gamma_p_inverse(a, p) == pytest.approx(float(gammaincinv(a, p)), rel=1e-9)
        for x in (0.2, 1.0, 5.0, 30.0, 150.0):
            assert gamma_p(a, x) == pytest.approx(float(gammainc(a, x)), abs=1e-12)
