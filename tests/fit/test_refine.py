"""Refinement (chic_register.fit.refine): convergence on exact crossings, blob assignment, the Gauss-Newton rows'
scalar path, the steps' solver.
"""

from __future__ import annotations

import numpy as np
import pytest

from chic_register.fit.refine import assign_blobs, refine, residuals_jacobian
from chic_register.model.pose import slice_frame
from chic_register.model.tube_model import (
    TubeModel,
    crossing_jacobian,
    crossings_memo,
    exp_se3,
    plane_crossings,
    prepare_geometry,
)


def test_assignment_fast_path_agrees_with_the_hungarian_matching():
    from scipy.optimize import linear_sum_assignment

    rng = np.random.default_rng(5)
    for _ in range(300):
        K, N = int(rng.integers(1, 10)), int(rng.integers(1, 14))
        pred, blobs = rng.uniform(0, 20, (K, 2)), rng.uniform(0, 20, (N, 2))
        ok = rng.random(K) > 0.2
        gate = float(rng.uniform(0.5, 6.0))
        dist = np.linalg.norm(pred[:, None] - blobs[None], axis=2)
        cost = np.where((dist < gate) & ok[:, None], dist**2, 1e6)
        r, c = linear_sum_assignment(cost)
        ref = np.full(K, -1)
        ref[r[cost[r, c] < 1e6]] = c[cost[r, c] < 1e6]
        got = assign_blobs(pred, ok, blobs, gate)
        # same number of matches and the same total cost (the optimum; ties may pick other pairs)
        assert (got >= 0).sum() == (ref >= 0).sum()
        k = np.flatnonzero(got >= 0)
        assert cost[k, got[k]].sum() == pytest.approx(cost[r, c][cost[r, c] < 1e6].sum(), rel=1e-9, abs=1e-12)
        assert np.all(dist[k, got[k]] < gate) and len(set(got[k].tolist())) == k.size


POSES = [(25, 0, 0, 0), (12, 35, 60, -20), (38, 55, 200, 75), (2, 70, 10, 5), (49, 20, 300, 40)]


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


def test_gauss_newton_solve_without_numpys_private_gufunc_gives_the_same_steps(monkeypatch):
    """refine's Gauss-Newton steps (lapack.solve_vector) call numpy's private LAPACK gufunc; on a numpy without it,
    the public wrapper gives the same step, and NaNs (not an exception) for a singular matrix, as the gufunc does."""
    import numpy as np

    from chic_register.fit import refine
    from chic_register.util import lapack

    assert refine.solve_vector is lapack.solve_vector
    rng = np.random.default_rng(5)
    A = rng.normal(size=(6, 6))
    H, g = A @ A.T + np.eye(6), rng.normal(size=6)
    fast = lapack.solve_vector(H, g)
    monkeypatch.setattr(lapack, "GUFUNC_SOLVE1", None)
    assert lapack.solve_vector(H, g) == fast
    assert all(v != v for v in lapack.solve_vector(np.zeros((6, 6)), g))  # NaNs


@pytest.mark.parametrize("pose", [(25.0, 20.0, 40.0, 10.0), (15.0, 35.0, 200.0, -30.0), (35.0, 0.0, 0.0, 60.0)])
def test_refine_converges_from_a_perturbed_pose_on_exact_crossings(neuro_geometry, pose):
    """Blobs at the exact crossings of a known plane (scanner frame = image frame), shuffled; the start turned about
    1.3 deg and moved about 1.1 mm off: the fit lands on the pose to rounding, every tube matched to its own blob,
    residuals zero."""
    model, _ = prepare_geometry(neuro_geometry)
    T = slice_frame(*pose)
    q, _, _, inside = plane_crossings(model, T)
    assert inside.all()
    order = np.random.default_rng(1).permutation(9)
    blobs = q[order]
    start = T @ exp_se3(np.array([0.01, -0.015, 0.02, 0.8, -0.6, 0.5]))
    fit = refine(model, [blobs], [np.eye(4)], start)
    np.testing.assert_allclose(fit.T_F_from_scanner, T, atol=1e-9)
    assert fit.n_matched == 9 and fit.rms_mm < 1e-9
    assert np.array_equal(order[fit.assignments[0]], np.arange(9))  # tube k matched to the blob at its crossing


def test_refine_leaves_a_tube_without_its_blob_unmatched(neuro_geometry):
    """One crossing's blob missing (O0's) and an unrelated blob 8 mm from every crossing: eight tubes matched, O0
    and the stray left out, the pose still exact."""
    model, _ = prepare_geometry(neuro_geometry)
    T = slice_frame(25.0, 20.0, 40.0, 10.0)
    q = plane_crossings(model, T)[0]
    o0 = model.ids.index("O0")
    blobs = np.vstack([np.delete(q, o0, axis=0), q.mean(axis=0)])
    assert np.linalg.norm(q - blobs[-1], axis=1).min() > 8.0
    fit = refine(model, [blobs], [np.eye(4)], T @ exp_se3(np.array([0.005, 0.0, -0.005, 0.3, 0.2, -0.3])))
    np.testing.assert_allclose(fit.T_F_from_scanner, T, atol=1e-9)
    a = fit.assignments[0]
    assert fit.n_matched == 8 and a[o0] == -1 and len(blobs) - 1 not in a
