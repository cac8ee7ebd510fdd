"""The small linear algebra (chic_register.util.lapack) gives numpy's answers bit for bit."""

from __future__ import annotations

import numpy as np


def test_window_least_squares_are_numpys():
    """The windows' least squares skip np.linalg.lstsq's wrapper: the same coefficients and rank, bit for bit, for
    full-rank, collinear and empty columns, and its answer where the call gives no finite one (NaN pixels)."""
    from chic_register.util.lapack import lstsq as _lstsq

    rng = np.random.default_rng(0)
    for i in range(300):
        m, n = int(rng.integers(1, 300)), int(rng.integers(1, 4))
        A, y = rng.normal(size=(m, n)), rng.normal(size=m)
        if i % 3 == 1 and n > 1:
            A[:, 1] = 2.0 * A[:, 0]
        if i % 5 == 2:
            A[:, -1] = 0.0
        coef, _, rank, _ = np.linalg.lstsq(A, y, rcond=None)
        got, got_rank = _lstsq(A, y)
        np.testing.assert_array_equal(got, coef)
        assert got_rank == rank
    y[0] = np.nan
    np.testing.assert_array_equal(_lstsq(A, y)[0], np.linalg.lstsq(A, y, rcond=None)[0])
