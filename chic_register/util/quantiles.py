"""Exact order statistics of a large array from a partition of the values near them only.

``np.percentile`` partitions the whole array about every rank it needs; the
background of a 256 x 256 slice (~60 000 values) costs about a millisecond
that way, on every pose's uncertainty. The quartiles lie in the middle half
of the values: a strided sample brackets them, one pass counts what lies
below the bracket, and only the values inside it are partitioned. The
results are those of ``np.percentile`` (linear interpolation), bit for bit;
when the sample's bracket misses (or the array holds NaN) the whole array is
partitioned as ``np.percentile`` does.
"""

from __future__ import annotations

import math

import numpy as np

#: Arrays smaller than this are partitioned whole (the bracket would not pay).
MIN_BRACKETED = 4096
#: One value in this many is sampled to bracket the ranks.
SAMPLE_STRIDE = 16
#: :func:`sorted_span`: one value in this many is sampled, and the bracket spans this many standard deviations of a
#: sampled rank each side (a miss only costs the whole partition).
SPAN_STRIDE = 16
SPAN_SIGMAS = 3.0


def unique_ints(values) -> np.ndarray:
    """The distinct integers of ``values``, sorted (``np.unique`` imports ``numpy.ma``: ~40 ms of a one-shot
    solve's start-up)."""
    return np.array(sorted(set(np.ravel(values).tolist())), dtype=np.intp)


def sorted_span(x: np.ndarray, k0: int, k1: int):
    """The values of ``x`` (1-D) at 0-based sorted positions ``k0`` to ``k1`` (a few, ``k0 <= k1``), ascending, as
    ``np.sort(x)[k0:k1 + 1]``; None when the sample's bracket misses (the caller then partitions the whole array).

    A sorted strided sample brackets the ranks, one pass counts the values
    below the bracket, and only those inside it are sorted (small arrays
    sort fast, while a partition of a few thousand values costs a branch
    misprediction per comparison). NaNs fall outside every bracket: a rank
    among them is a miss.
    """
    n = x.size
    sample = np.sort(x[::SPAN_STRIDE])
    m = sample.size
    margin = int(SPAN_SIGMAS * 0.5 * math.sqrt(m)) + 2  # a sampled quantile's rank has sd <= sqrt(m) / 2
    j0, j1 = int(k0 * m / n) - margin, int(k1 * m / n) + margin
    if j0 < 0 or j1 >= m:
        return None
    lo_v, hi_v = sample[j0], sample[j1]
    below = int(np.count_nonzero(x < lo_v))
    inside = x.take(((x >= lo_v) & (x <= hi_v)).nonzero()[0])  # (x[mask], without a branch per value)
    r0, r1 = k0 - below, k1 - below
    if r0 < 0 or r1 >= inside.size:
        return None
    inside.sort()
    return inside[r0:r1 + 1]


def order_statistics(values: np.ndarray, ranks: np.ndarray) -> np.ndarray:
    """The values of ``values`` (1-D) at 0-based sorted positions ``ranks`` (increasing ints); shape of ``ranks``.

    Ranks close together (within a sample's uncertainty) share one bracket;
    each bracket's values are gathered and partitioned on their own.
    """
    x = np.asarray(values).ravel()
    ranks = np.asarray(ranks, dtype=np.intp)
    n = x.size
    out = np.empty(ranks.size, dtype=x.dtype)
    if n >= MIN_BRACKETED and ranks.size:
        sample = x[::SAMPLE_STRIDE]
        m = sample.size
        margin = int(3.0 * math.sqrt(m)) + 2  # ~7 standard deviations of a sampled quantile's rank
        groups = np.split(np.arange(ranks.size), np.flatnonzero(np.diff(ranks) > 2 * margin * n / m) + 1)
        edges = [(int(ranks[g[0]] * m / n) - margin, int(ranks[g[-1]] * m / n) + margin) for g in groups]
        if edges[0][0] >= 0 and edges[-1][1] < m:
            part = np.partition(sample, unique_ints(edges))
            for g, (s_lo, s_hi) in zip(groups, edges):
                lo_v, hi_v = part[s_lo], part[s_hi]
                below = int(np.count_nonzero(x < lo_v))
                mid = x[(x >= lo_v) & (x <= hi_v)]
                r = ranks[g] - below
                if r[0] < 0 or r[-1] >= mid.size:
                    break  # the sample missed: the whole array
                out[g] = np.partition(mid, unique_ints(r))[r]
            else:
                return out
    return np.partition(x, unique_ints(ranks))[ranks]


def percentiles(values: np.ndarray, q) -> np.ndarray:
    """``np.percentile(values, q)`` (linear interpolation, values flattened), the same bits, from
    :func:`order_statistics`; NaN when ``values`` holds NaN, as ``np.percentile``."""
    x = np.asarray(values, dtype=float).ravel()
    n = x.size
    if n == 0:
        raise IndexError("percentiles of an empty array")
    quant = np.true_divide(np.asarray(q, dtype=float), 100)
    virtual = (n - 1) * quant
    prev = np.floor(virtual).astype(np.intp)
    nxt = np.minimum(prev + 1, n - 1)
    prev = np.clip(prev, 0, n - 1)
    ranks = unique_ints(np.concatenate([prev, nxt]))
    at = order_statistics(x, ranks)
    a, b = at[np.searchsorted(ranks, prev)], at[np.searchsorted(ranks, nxt)]
    gamma = virtual - np.floor(virtual)
    # numpy's _lerp: a + (b - a) t, or b - (b - a) (1 - t) from t = 0.5 (monotone, exact at both ends)
    diff = np.subtract(b, a)
    out = np.add(a, diff * gamma)
    np.subtract(b, diff * (1 - gamma), out=out, where=gamma >= 0.5)
    if np.isnan(x).any():
        out[:] = np.nan
    return out


def nan_median_rows(values: np.ndarray) -> np.ndarray:
    """``np.nanmedian(values, axis=1)`` of a 2-D float array, the same numbers, from one sort: NaN for a row of NaNs
    only (without numpy's warning). ``np.nanmedian`` of small rows goes through ``numpy.ma``, whose import costs a
    one-shot solve 15 ms."""
    a = np.sort(np.asarray(values, dtype=float), axis=1)  # (NaN sorts last)
    n = np.count_nonzero(~np.isnan(a), axis=1)
    rows = np.arange(a.shape[0])
    lo, hi = a[rows, np.maximum((n - 1) // 2, 0)], a[rows, np.maximum(n // 2, 0)]
    with np.errstate(over="ignore", invalid="ignore"):  # (two values near the float limit: inf, as numpy's mean)
        out = np.where(n % 2 == 1, lo, (lo + hi) / 2.0)
    out[n == 0] = np.nan
    return out
