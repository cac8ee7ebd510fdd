"""chic_register.util.quantiles: np.percentile's values, bit for bit, from a partition of the values near them."""

import warnings

import numpy as np
import pytest

from chic_register.util.quantiles import order_statistics, percentiles


def _arrays(rng):
    yield rng.normal(size=60000)
    yield np.abs(rng.normal(size=65536) + 1j * rng.normal(size=65536))  # a magnitude image's background
    yield rng.integers(0, 4, 20000).astype(float)  # ties across the brackets
    yield np.sort(rng.exponential(size=30000))  # sorted: the strided sample is still fair
    yield np.concatenate([rng.normal(size=9000), rng.normal(40.0, 1.0, 3000)])
    yield rng.normal(size=17)  # below the bracketing size: partitioned whole


@pytest.mark.parametrize("q", [[25, 50, 75], [0, 100], [1, 99], [33.3, 50, 66.7]])
def test_percentiles_are_numpys_bits(q):
    rng = np.random.default_rng(3)
    for x in _arrays(rng):
        assert np.array_equal(percentiles(x, q), np.percentile(x, q))


def test_nan_gives_nan_as_numpy():
    x = np.random.default_rng(1).normal(size=10000)
    x[77] = np.nan
    assert np.isnan(percentiles(x, [25, 50, 75])).all()


def test_unrepresentative_sample_falls_back_to_the_whole_array():
    # every 16th value (the bracketing sample) far above the rest: the brackets miss, the answer is still exact
    x = np.random.default_rng(2).normal(size=32000)
    x[::16] += 1000.0
    ranks = np.array([100, 8000, 8001, 31000])
    assert np.array_equal(order_statistics(x, ranks), np.sort(x)[ranks])
    assert np.array_equal(percentiles(x, [25, 50, 75]), np.percentile(x, [25, 50, 75]))


def test_sorted_span_is_the_sorted_values_or_a_miss():
    from chic_register.util.quantiles import sorted_span

    rng = np.random.default_rng(4)
    hits = 0
    for x in list(_arrays(rng)) + [rng.normal(size=4096).astype(np.float32), np.full(5000, 2.5)]:
        ref = np.sort(x)
        for k0 in (0, x.size // 4, x.size // 2 - 1, x.size - 2):
            for k1 in (k0, k0 + 1):
                got = sorted_span(x, k0, k1)
                if got is not None:
                    hits += 1
                    assert got.dtype == x.dtype and np.array_equal(got, ref[k0:k1 + 1])
    assert hits >= 20  # the bracket does its work (middle ranks of the larger arrays)
    skewed = rng.normal(size=32000)
    skewed[::16] += 1000.0  # the sample far above the rest: a miss, never a wrong value
    assert sorted_span(skewed, 16000, 16001) is None


def test_nan_median_rows_is_numpys_nanmedian_bit_for_bit():
    from chic_register.util.quantiles import nan_median_rows

    rng = np.random.default_rng(1)
    for t in range(500):
        r, c = int(rng.integers(1, 40)), int(rng.integers(1, 12))
        a = rng.normal(size=(r, c)) * 10 ** rng.uniform(-3, 3)
        a[rng.random((r, c)) < rng.uniform(0, 1)] = np.nan
        if t % 5 == 0:
            a = np.round(a)  # ties
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # (numpy warns of a row of NaNs)
            want = np.nanmedian(a, axis=1)
        np.testing.assert_array_equal(nan_median_rows(a), want)
