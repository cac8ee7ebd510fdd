"""Refinement: Gauss-Newton on the six DOF of a pose, with the blob-to-tube assignment re-solved on the way.

:func:`refine` turns a guess of ``T_F_from_scanner`` into a :class:`Fit`
(pose, assignments, residuals) from the detected centres of one or more
slices; :func:`reject_outliers` drops tubes that spoil a fit;
:func:`rank_fits` orders fits best first. The model and its derivatives are
:mod:`chic_register.model.tube_model`'s.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from chic_register.model.pose import invert
from chic_register.model.tube_model import (
    TubeModel,
    adjoint,
    crossing_jacobian,
    crossings_memo,
    exp_se3,
    inside_list,
)
from chic_register.options import SolveOptions
from chic_register.util.lapack import solve_vector
from chic_register.util.matching import matched_pairs


@dataclass(frozen=True, eq=False)
class Fit:
    """One refined joint hypothesis."""

    T_F_from_scanner: np.ndarray
    assignments: list  # per slice: (K,) int blob index or -1
    residuals: list  # per slice: (K,) mm, NaN where unassigned
    inside: list  # per slice: (K,) bool
    n_matched: int
    rms_mm: float
    # what the last fit was made of, when not the blob centroids: per slice (measured xy (N, 2) mm, square-root
    # information L (K, 2, 2) it was weighted by, the noise sigma L assumed) (see chic_register.precision.uncertainty)
    measurements: list | None = None


def whitened_residuals(measurement, q: np.ndarray, a: np.ndarray, k: np.ndarray) -> np.ndarray:
    """(len(k), 2): tubes ``k``'s ``L (predicted - measured)`` in one slice's ``measurement`` (an entry of
    ``Fit.measurements``), ``q`` (K, 2) the predicted crossings and ``a`` (K,) the blob index per tube."""
    xy, L, _ = measurement
    return np.einsum("kij,kj->ki", L[k], q[k] - xy[a[k]])


def assign_blobs(pred: np.ndarray, ok: np.ndarray, blobs_xy: np.ndarray, gate_mm: float) -> np.ndarray:
    """Blob index per tube (K,), -1 for none: minimum-cost matching within ``gate_mm``."""
    K, N = pred.shape[0], blobs_xy.shape[0]
    if N == 0:
        return np.full(K, -1)
    diff = pred[:, None, :] - blobs_xy[None, :, :]
    d2 = np.einsum("ijk,ijk->ij", diff, diff)  # squared distances (K, N)
    r, c = ((d2 < gate_mm * gate_mm) & ok[:, None]).nonzero()
    rl, cl = r.tolist(), c.tolist()
    if len(set(rl)) != len(rl) or len(set(cl)) != len(cl):
        rl, cl = matched_pairs(K, N, rl, cl, d2[r, c].tolist())
    # else every gated pair is alone in its row and column: they are the (unique) optimal matching
    out = [-1] * K
    for i, j in zip(rl, cl):
        out[i] = j
    return np.array(out)


def _image_adjoint(S: np.ndarray) -> np.ndarray:
    """``adjoint(invert(S))`` of a slice's ``T_scanner_from_image`` (read-only; memoised: every refinement of
    a slice needs it)."""
    S = np.asarray(S)
    if S.shape != (4, 4) or S.dtype != np.float64:
        return adjoint(invert(S))
    return _adjoint_of_inverse(S.tobytes())


def scanner_crossing_jacobian(q: np.ndarray, tan_I: np.ndarray, S: np.ndarray) -> np.ndarray:
    """(M, 2, 6) d(crossing xy)/d(xi) of crossings ``q`` (M, 2) with image-frame tangents ``tan_I`` (M, 3) for a
    twist xi of ``T_F_from_scanner`` in the scanner frame, on the slice ``S`` (its ``T_scanner_from_image``)."""
    return crossing_jacobian(q, tan_I) @ _image_adjoint(S)


def match_gate_mm(model: TubeModel, pixel_mm: float) -> float:
    """The widest blob-tube assignment gate of a refinement (mm): the widest tube, or two pixels if larger."""
    return max(float(model.diameter_mm.max()), 2 * pixel_mm)


@functools.lru_cache(maxsize=64)
def _adjoint_of_inverse(S_bytes: bytes) -> np.ndarray:
    A = adjoint(invert(np.frombuffer(S_bytes).reshape(4, 4)))
    A.flags.writeable = False
    return A


def refine(model: TubeModel, blobs_xy: list[np.ndarray], T_scanner_from_image: list[np.ndarray],
           T_F_from_scanner: np.ndarray, *, gates_mm=(3.0, 1.5, 1.0, 1.0), iters_per_gate: int = 3,
           final_iters: int = 4, damping: float = 1e-6, exclude: list | None = None,
           assign0: list | None = None, offsets_mm: list | None = None, strict_ends: bool = True,
           weights: list | None = None, tol: float = 1e-6) -> Fit:
    """Gauss-Newton on all six DOF of ``T_F_from_scanner`` with re-assignment.

    ``blobs_xy``: per slice, detected centres in image mm (N_j, 2). Each gate
    in ``gates_mm`` re-solves the blob-tube assignment, then iterates; the
    final iterations keep the last assignment (``assign0``, per slice (K,)
    blob indices, when there are no gates). ``exclude``: per slice, a (K,)
    bool mask of tubes left unassigned (rejected outliers). ``offsets_mm``:
    per slice (K, 2), added to the predicted crossings (the centroid model:
    the centroid of a tube's image section minus its centreline crossing).
    ``strict_ends``: leave out crossings whose section a tube end cuts
    (their blob centre is biased) unless the offsets model that cut.
    ``weights``: per slice (K, 2, 2) or None, each tube's square-root
    information ``L`` (``L^T L`` = the inverse covariance of its measured
    position, mm^-2): the fit then minimises the sum of ``|L (predicted -
    measured)|^2`` (the maximum-likelihood pose for Gaussian position errors).
    ``tol``: the final iterations stop once a step is below it (rad and mm).
    """
    end_margin = 0.0 if strict_ends else 1e-9
    X = T_F_from_scanner.copy()
    ads = [_image_adjoint(S) for S in T_scanner_from_image]
    assign = list(assign0) if assign0 is not None else [None] * len(blobs_xy)
    offs = offsets_mm if offsets_mm is not None else [None] * len(blobs_xy)
    schedule = [(g, iters_per_gate) for g in gates_mm] + [(None, final_iters)]
    xy_lists = [xy.tolist() for xy in blobs_xy]
    offs_lists = [o.tolist() if o is not None else None for o in offs]
    a_lists = [None] * len(blobs_xy)  # assign[j] as a list
    step = 1.0
    for gate, iters in schedule:
        changed = False
        margin = 5.0 if gate is not None else end_margin
        for it in range(iters):
            if it == 1 and not changed and step < 1e-5:
                break  # converged and the assignment did not change
            Js, rs = [], []
            for j, (xy, S) in enumerate(zip(blobs_xy, T_scanner_from_image)):
                hit = crossings_memo(model, X @ S)  # plane_crossings' numbers, less its copies (read-only here)
                inside = inside_list(model, hit, margin)
                if gate is not None and it == 0:
                    q = hit[0][:, :2]
                    qm = q + offs[j] if offs[j] is not None else q  # what the detector measures
                    ins = np.array(inside, dtype=bool)
                    new = assign_blobs(qm, ins & ~exclude[j] if exclude else ins, xy, gate)
                    changed = changed or assign[j] is None or not np.array_equal(new, assign[j])
                    assign[j] = new
                    a_lists[j] = None
                if a_lists[j] is None:
                    a_lists[j] = assign[j].tolist()
                a = a_lists[j]
                k = [i for i, (ai, ok) in enumerate(zip(a, inside)) if ai >= 0 and ok]
                if not k:
                    continue
                res, Jl = residuals_jacobian(hit[5].tolist(), k, a, xy_lists[j], offs_lists[j])
                M = len(k)
                # (M, 2, 6) @ (6, 6) as one (2M, 6) product: the same numbers, one BLAS call instead of M
                Jk = np.fromiter(Jl, float, 12 * M).reshape(2 * M, 6) @ ads[j]
                res = np.fromiter(res, float, 2 * M)
                if weights is not None and weights[j] is not None:
                    L = weights[j][k]
                    res = np.einsum("kij,kj->ki", L, res.reshape(M, 2)).ravel()
                    Jk = np.einsum("kij,kjl->kil", L, Jk.reshape(M, 2, 6)).reshape(-1, 6)
                rs.append(res)
                Js.append(Jk)
            if not rs:
                break
            J = Js[0] if len(Js) == 1 else np.concatenate(Js)
            r = rs[0] if len(rs) == 1 else np.concatenate(rs)
            H = J.T @ J
            diag = H.reshape(-1)[::7]  # a view of the diagonal
            diag *= 1 + damping
            diag += 1e-9
            xi = solve_vector(H, J.T @ r)
            step = max(map(abs, xi))
            if not math.isfinite(sum(xi)):
                break  # H singular (np.linalg.solve would raise)
            xi = [-v for v in xi]
            X = X @ exp_se3(xi)
            # rad and mm: under a gate, close enough to re-assign; at the end, far below any error that matters
            if step < (1e-3 if gate is not None else tol):
                break
        if step > 1e-2:  # still wandering after a whole gate: a hopeless guess, give up
            break
    # final bookkeeping (scalar code over the tubes, as in the iterations: numpy's numbers, fewer calls)
    residuals, insides, total, sq = [], [], 0, 0.0
    for j, (xy, S) in enumerate(zip(blobs_xy, T_scanner_from_image)):
        hit = crossings_memo(model, X @ S)
        inside = inside_list(model, hit, end_margin)
        a_j = assign[j] if assign[j] is not None else np.full(model.is_helix.size, -1)
        a = [ai if ok else -1 for ai, ok in zip(a_j.tolist(), inside)]
        qt, xyl, offl = hit[5].tolist(), xy_lists[j], offs_lists[j]
        res, dist = [math.nan] * len(a), []
        for i, ai in enumerate(a):
            if ai >= 0:
                (x, y, _), _ = qt[i]
                bx, by = xyl[ai]
                if offl is not None:
                    x, y = x + offl[i][0], y + offl[i][1]
                dx, dy = x - bx, y - by
                res[i] = math.sqrt(dx * dx + dy * dy)
                dist.append(res[i])
        assign[j] = np.array(a, dtype=a_j.dtype)
        residuals.append(np.array(res))
        insides.append(np.array(inside, dtype=bool))
        total += len(dist)
        if dist:
            sq += float(np.add.reduce(np.array(dist) ** 2))  # numpy's sum (pairwise: not Python's)
    rms = math.sqrt(sq / total) if total else float("inf")
    return Fit(X, assign, residuals, insides, total, rms)


def residuals_jacobian(qt: list, k: list, a: list, xy: list, offs: list | None):
    """The Gauss-Newton rows of the tubes ``k`` (a list): residuals ``[x, y, ...]`` (predicted + offset - blob
    ``a[i]``) and the crossings' Jacobian :func:`~chic_register.model.tube_model.crossing_jacobian` flattened
    (``12 * len(k)``), from :func:`~chic_register.model.tube_model._crossings`' ``qt`` as a list.

    Scalar code (the same arithmetic as the array versions, to the bit): on nine tubes a dozen numpy calls cost
    more than the loop.
    """
    res, J = [], []
    for i in k:
        (x, y, _), (tx, ty, tz) = qt[i]
        bx, by = xy[a[i]]
        if offs is None:
            res += (x - bx, y - by)
        else:
            dx, dy = offs[i]
            res += (x + dx - bx, y + dy - by)
        if -1e-6 < tz < 1e-6:
            tz = 1e-6
        ta, tb = tx / tz, ty / tz
        J += (ta * y, -ta * x, y, -1.0, 0.0, ta, tb * y, -tb * x, -x, 0.0, -1.0, tb)
    return res, J


def reject_outliers(model: TubeModel, xys, Ss, fit: Fit, px_mm: list[float], opts: SolveOptions) -> Fit:
    """Drop the worst-fitting tube while that makes the fit markedly better, and refit.

    Tried while the worst residual exceeds ``max_rms_px`` pixels (two
    touching tubes, a bubble, a blob merged with anatomy); a drop is kept
    when the RMS falls by at least a third. Never below ``min_tubes`` /
    ``min_depth_tubes``.
    """
    K = len(model.ids)
    excl = [np.zeros(K, bool) for _ in xys]
    gate = match_gate_mm(model, max(px_mm))
    for _ in range(max(0, fit.n_matched - opts.min_tubes)):
        res = [np.where(np.isfinite(r), r / px, -1.0) for r, px in zip(fit.residuals, px_mm)]
        worst = [float(r.max()) for r in res]
        j = worst.index(max(worst))  # the first of the largest, as np.argmax (no NaN here)
        k = int(res[j].argmax())
        if res[j][k] <= opts.max_rms_px:
            break
        n_depth = sum(int(np.sum((a >= 0) & model.depth_coding)) for a in fit.assignments)
        if model.depth_coding[k] and n_depth <= opts.min_depth_tubes:
            break
        trial_excl = [e.copy() for e in excl]
        trial_excl[j][k] = True
        trial = refine(model, xys, Ss, fit.T_F_from_scanner, gates_mm=(0.6 * gate,), iters_per_gate=4,
                       final_iters=2, exclude=trial_excl)
        if trial.n_matched < fit.n_matched - 1 or trial.rms_mm > fit.rms_mm / 1.5:
            break
        fit, excl = trial, trial_excl
    return fit


def rank_fits(fits: list[Fit], rms_limit_mm: float = math.inf) -> list[Fit]:
    """Best first: fits within the RMS limit, then the most tubes, then the lowest RMS."""
    return sorted(fits, key=lambda f: (f.rms_mm > rms_limit_mm, -f.n_matched, f.rms_mm))


def unexplained_tubes(fit: Fit) -> int:
    """Tubes a fit puts wholly inside the slice (every slice) that no blob is assigned to."""
    return sum(int(np.sum(ins & (a < 0))) for ins, a in zip(fit.inside, fit.assignments))
