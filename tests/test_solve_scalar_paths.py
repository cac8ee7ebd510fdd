"""The solver's scalar fast paths give the array formulas' numbers bit for bit (refine, extent tests, matching)."""

import math

import numpy as np
import pytest

from chic_register.fit.refine import residuals_jacobian
from chic_register.model.pose import slice_frame
from chic_register.model.tube_model import (
    TubeModel,
    crossing_jacobian,
    crossings_memo,
    inside_mask,
    plane_crossings,
)
from chic_register.util.matching import gated_matching, hungarian, matched_pairs

POSES = [(25, 0, 0, 0), (12, 35, 60, -20), (38, 55, 200, 75), (2, 70, 10, 5), (49, 20, 300, 40)]


def _inside_arrays(model, T, margin_mm):
    """plane_crossings' extent test as array formulas (its earlier implementation)."""
    _, tan_I, zF, _ = plane_crossings(model, T, margin_mm=5.0)
    ok = np.array(crossings_memo(model, np.asarray(T, float))[3])
    if margin_mm > 0:
        return ok & (zF >= model.z_lo - margin_mm - 1e-6) & (zF <= model.z_hi + margin_mm + 1e-6)
    cos_a = np.maximum(np.abs(tan_I[:, 2]), 1e-6)
    tan_z = np.array(crossings_memo(model, np.asarray(T, float))[4])
    clear = 0.5 * model.diameter_mm * np.sqrt(np.maximum(1 - cos_a * cos_a, 0.0)) / cos_a * np.abs(tan_z)
    return ok & (zF >= model.z_lo + clear - 1e-6) & (zF <= model.z_hi - clear + 1e-6)


@pytest.mark.parametrize("pose", POSES)
@pytest.mark.parametrize("margin_mm", [0.0, 1e-9, 5.0])
def test_scalar_extent_test_equals_the_array_formula(neuro_geometry, pose, margin_mm):
    model = TubeModel.from_geometry(neuro_geometry)
    T = slice_frame(*pose)
    hit = crossings_memo(model, T)
    got = inside_mask(model, hit, margin_mm)
    assert got.dtype == bool
    assert np.array_equal(got, _inside_arrays(model, T, margin_mm))


@pytest.mark.parametrize("pose", POSES)
@pytest.mark.parametrize("with_offsets", [False, True])
def test_scalar_gauss_newton_rows_equal_the_array_versions(neuro_geometry, pose, with_offsets):
    model = TubeModel.from_geometry(neuro_geometry)
    rng = np.random.default_rng(3)
    T = slice_frame(*pose)
    q, tan, _, _ = plane_crossings(model, T, margin_mm=5.0)
    K = q.shape[0]
    blobs = q + rng.normal(0, 0.3, q.shape)
    a = rng.permutation(K)
    k = sorted(rng.choice(K, size=K - 2, replace=False).tolist())
    offs = rng.normal(0, 0.05, (K, 2)) if with_offsets else None
    res, J = residuals_jacobian(crossings_memo(model, T)[5].tolist(), k, a.tolist(), blobs.tolist(),
                                 offs.tolist() if with_offsets else None)
    qm = q + offs if with_offsets else q
    assert np.array_equal(np.array(res), (qm[k] - blobs[a[k]]).ravel())
    J_ref = crossing_jacobian(q[k], tan[k])
    J_got = np.array(J).reshape(len(k), 2, 6)
    assert np.array_equal(J_got, J_ref)
    assert np.array_equal(np.signbit(J_got), np.signbit(J_ref))


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
