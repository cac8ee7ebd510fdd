"""Assignment solvers (chic_register.util.matching): optimal against brute force, gated pairs first, list and array
forms alike.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from chic_register.util.matching import gated_matching, hungarian, matched_pairs


def test_hungarian_is_optimal_against_brute_force():
    rng = np.random.default_rng(2)
    for _ in range(150):
        n, m = int(rng.integers(1, 6)), int(rng.integers(1, 6))
        cost = rng.uniform(0, 10, (n, m)).round(1)  # ties included
        pairs = hungarian(cost.tolist())
        assert len(pairs) == min(n, m)
        assert len({r for r, _ in pairs}) == len(pairs) == len({c for _, c in pairs})
        if n <= m:
            best = min(sum(cost[i, p[i]] for i in range(n)) for p in itertools.permutations(range(m), n))
        else:
            best = min(sum(cost[p[j], j] for j in range(m)) for p in itertools.permutations(range(n), m))
        assert sum(cost[r, c] for r, c in pairs) == pytest.approx(best)


def test_gated_matching_maximises_allowed_pairs_first():
    # tube 0 could take blob 0 (cheap) or blob 1; tube 1 only blob 0: both must be matched
    cost = np.array([[0.1, 5.0], [1.0, 9.0]])
    allowed = np.array([[True, True], [True, False]])
    r, c = gated_matching(cost, allowed)
    assert dict(zip(r.tolist(), c.tolist())) == {0: 1, 1: 0}
    r, c = gated_matching(cost, np.zeros((2, 2), bool))
    assert r.size == c.size == 0


def test_matched_pairs_is_gated_matching_on_lists():
    rng = np.random.default_rng(0)
    for _ in range(300):
        K, N = int(rng.integers(1, 8)), int(rng.integers(1, 9))
        cost = rng.random((K, N))
        allowed = rng.random((K, N)) < 0.4
        r, c = gated_matching(cost, allowed)
        ri, ci = np.nonzero(allowed)
        r2, c2 = matched_pairs(K, N, ri.tolist(), ci.tolist(), cost[ri, ci].tolist())
        assert sorted(zip(r.tolist(), c.tolist())) == sorted(zip(r2, c2))
        # the most pairs, then the least cost: against the dense Hungarian method with a big cost for gated pairs
        dense = np.where(allowed, cost, 1e6).tolist()
        best = [(i, j) for i, j in hungarian(dense) if allowed[i, j]]
        assert len(r) == len(best)
        assert math.isclose(sum(cost[i, j] for i, j in zip(r, c)), sum(cost[i, j] for i, j in best), abs_tol=1e-12)
