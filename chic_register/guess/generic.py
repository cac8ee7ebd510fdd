"""The generic first guess: a pose from any tube set with a family of three or more parallel straight tubes.

The second stage of :mod:`chic_register.guess.hypotheses` (see its docstring): every
minimal set of three blob-to-tube correspondences in the parallel family
(CHIC's axial tubes, a Z-frame's rods) fixes the 2-D affine map from the
image to the family's cross-section, hence the plane's orientation up to a
two-fold sign; the translation along the family's direction comes from a
vote of every other tube (sampled centrelines), so diagonals and helices
alike give the depth. Nothing in it assumes a cylinder or a role.
"""

from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from chic_register.detect.blobs import median
from chic_register.model.pose import rigid
from chic_register.model.tubes import sample_centreline

if TYPE_CHECKING:
    from chic_register.model.tube_model import TubeModel

_PARALLEL_COS = math.cos(math.radians(1.0))


@dataclass(frozen=True, eq=False)
class ParallelFamily:
    """Straight tubes of one direction ``u`` (F) and what the generic stage needs of the others.

    ``idx``: the family's tube indices; ``E`` (3, 2): a basis of the plane
    normal to ``u`` (``E, u`` right-handed); ``c`` (n, 2): the tubes' points in
    that cross-section; ``triples`` (T, 3): ordered member triples with a
    non-degenerate cross-section triangle (indices into ``idx``) and
    ``side_min_mm`` (T,) their shortest side; ``depth_idx``: the tubes not
    parallel to ``u`` (they fix the plane's position along ``u``) with their
    centreline samples, all tubes' concatenated: cross-section coordinates
    ``sample_q`` (M, 2), heights along ``u`` ``sample_h`` (M,), each tube's
    ``(start, stop)`` in them and its depth tolerance factor ``sample_rise``
    (height per mm of cross-section travel: 1 for a 45-degree diagonal, more
    for a shallow helix).
    """

    idx: np.ndarray
    u: np.ndarray
    E: np.ndarray
    c: np.ndarray
    triples: np.ndarray
    side_min_mm: np.ndarray
    depth_idx: np.ndarray
    sample_q: np.ndarray
    sample_h: np.ndarray
    sample_slices: tuple
    sample_rise: tuple


def _basis_normal_to(u: np.ndarray) -> np.ndarray:
    """(3, 2) orthonormal basis [e1, e2] of the plane normal to ``u`` with (e1, e2, u) right-handed; e1 = x when u = z."""
    a = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = a - (a @ u) * u
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(u, e1)], axis=1)


@functools.lru_cache(maxsize=8)
def parallel_family(model: "TubeModel", sample_step_mm: float = 0.5) -> ParallelFamily | None:
    """The largest family of >= 3 parallel straight tubes not all in one plane, or None (memoised per model)."""
    li = model.line_idx
    if li.size < 3:
        return None
    dirs = model.line_dunit
    best = None
    for a in range(li.size):
        members = np.flatnonzero(np.abs(dirs @ dirs[a]) > _PARALLEL_COS)
        if members.size >= 3 and (best is None or members.size > best.size):
            best = members
    if best is None:
        return None
    u = dirs[best[0]].copy()
    E = _basis_normal_to(u)
    idx = li[best]
    c = model.p0[idx] @ E
    triples, sides = [], []
    for t in itertools.permutations(range(idx.size), 3):
        p = c[list(t)]
        area = 0.5 * abs((p[1, 0] - p[0, 0]) * (p[2, 1] - p[0, 1]) - (p[1, 1] - p[0, 1]) * (p[2, 0] - p[0, 0]))
        side = min(np.linalg.norm(p[0] - p[1]), np.linalg.norm(p[0] - p[2]), np.linalg.norm(p[1] - p[2]))
        if side > 0 and area > 0.05 * side * side:
            triples.append(t)
            sides.append(side)
    if not triples:
        return None  # the family lies in one plane: its cross-section cannot fix a 2-D affine map
    parallel = np.zeros(len(model.ids), bool)
    parallel[idx] = True
    for k in li:
        parallel[k] |= abs(model.d[k] @ u) / np.linalg.norm(model.d[k]) > _PARALLEL_COS
    depth_idx = np.flatnonzero(~parallel)
    qs, hs, spans, rises = [], [], [], []
    start = 0
    for k in depth_idx:
        S = sample_centreline(model.tubes[k], sample_step_mm)
        Q, h = S @ E, S @ u
        travel = float(np.sum(np.linalg.norm(np.diff(Q, axis=0), axis=1)))
        rise = float(abs(h[-1] - h[0])) if h.size > 1 else 0.0
        qs.append(Q)
        hs.append(h)
        spans.append((start, start + h.size))
        rises.append(rise / travel if travel > 1e-9 else math.inf)
        start += h.size
    return ParallelFamily(idx, u, E, c, np.array(triples, int), np.array(sides), depth_idx,
                          np.concatenate(qs) if qs else np.zeros((0, 2)), np.concatenate(hs) if hs else np.zeros(0),
                          tuple(spans), tuple(rises))


def affine_candidates(fam: ParallelFamily, xy: np.ndarray, gate_mm: float, cos_max: float, max_pairs: int,
                       rng: np.random.Generator):
    """Every (blob triple, member triple) whose image distances a tilted cut can give; (blob idx (n, 3), triple (n,))."""
    N = xy.shape[0]
    dp = np.linalg.norm(xy[:, None] - xy[None], axis=-1)
    dc = np.linalg.norm(fam.c[:, None] - fam.c[None], axis=-1)
    # a cut stretches the cross-section by 1 .. 1/cos(tilt): image distances lie in [dc, dc / cos_max]
    ok = (dp[:, :, None, None] >= dc[None, None] - gate_mm) & (dp[:, :, None, None] * cos_max <= dc[None, None] + gate_mm)
    tri = fam.triples
    keep = max(1, max_pairs // max(tri.shape[0], 1))
    if math.comb(N, 3) <= keep:
        blob_t = np.array(list(itertools.combinations(range(N), 3)), int).reshape(-1, 3)
    else:  # too many blobs to try every triple (hundreds of bright specks): a random sample of distinct triples
        draw = np.sort(rng.integers(0, N, size=(2 * keep, 3)), axis=1)
        draw = draw[(draw[:, 0] < draw[:, 1]) & (draw[:, 1] < draw[:, 2])]
        blob_t = np.unique(draw, axis=0)[:keep]
    i, j, n = blob_t.T
    a, b, c = tri.T
    compat = (ok[i[:, None], j[:, None], a[None], b[None]] & ok[i[:, None], n[:, None], a[None], c[None]]
              & ok[j[:, None], n[:, None], b[None], c[None]])
    bi, ti = np.nonzero(compat)
    return blob_t[bi], ti


def family_hypotheses(model: "TubeModel", xy_mm: np.ndarray, *, gate_mm: float, max_tilt_deg: float = 75.0,
                      max_hypotheses: int = 8, max_affines: int = 96, max_pairs: int = 400_000,
                      rng_seed: int = 0) -> list[np.ndarray]:
    """Generic pose guesses ``T_F_from_I`` from blob centres (N, 2), best first (see the module docstring).

    ``gate_mm``: how far a blob may lie from a predicted crossing to count.
    Consensus at two levels: affine maps are ranked by how many of the
    family's tubes land on blobs (the best ``max_affines`` distinct ones are
    kept: a missing tube and a stray blob can reorder them), and depths by
    how many non-family tubes agree on them. Returns ``[]`` when the layout has no usable family, no tube
    outside it (the depth is then under-determined) or no consistent guess.
    """
    fam = parallel_family(model)
    xy = np.asarray(xy_mm, float)
    if fam is None or fam.depth_idx.size == 0 or xy.shape[0] < 3:
        return []
    cos_max = math.cos(math.radians(max_tilt_deg))
    rng = np.random.default_rng(rng_seed)
    blob_t, ti = affine_candidates(fam, xy, gate_mm, cos_max, max_pairs, rng)
    if blob_t.size == 0:
        return []
    P = xy[blob_t]  # (n, 3, 2)
    C = fam.c[fam.triples[ti]]  # (n, 3, 2)
    M = np.concatenate([P, np.ones(P.shape[:2] + (1,))], axis=2)  # rows [x, y, 1]
    det = np.linalg.det(M)
    good = np.abs(det) > 1e-3 * np.max(np.abs(det)) if det.size else det.astype(bool)
    M, C, side = M[good], C[good], fam.side_min_mm[ti[good]]
    if M.shape[0] == 0:
        return []
    X = np.linalg.solve(M, C)  # (n, 3, 2): c = A p + b with A = X[:2].T, b = X[2]
    A = np.transpose(X[:, :2, :], (0, 2, 1))
    b = X[:, 2, :]
    sv = np.linalg.svd(A, compute_uv=False)
    sig_tol = np.maximum(0.04, 0.5 * gate_mm / side)
    keep = (np.abs(sv[:, 0] - 1.0) < sig_tol) & (sv[:, 1] > cos_max - sig_tol)
    A, b = A[keep], b[keep]
    if A.shape[0] == 0:
        return []
    # every family tube predicted in the image: how many land on a blob
    Ainv = np.linalg.inv(A)
    pred = np.einsum("nij,nkj->nki", Ainv, fam.c[None] - b[:, None, :])  # (n, F, 2)
    dist = nearest_blob_mm(pred, xy)  # (n, F)
    hit = dist < gate_mm
    n_hit = hit.sum(axis=1)
    err = np.where(hit, dist, 0.0).sum(axis=1)
    order = np.lexsort((err, -n_hit))
    floor = max(3, int(n_hit.max()) - 1)
    seen, affines = [], []
    for o in order:
        if n_hit[o] < floor or len(affines) >= max_affines:
            break
        Ao, bo, used = _refit_affine(fam, xy, A[o], b[o], gate_mm)
        if any(np.abs(Ao - As).max() < 0.02 and np.abs(bo - bs).max() < 0.5 for As, bs in seen):
            continue
        seen.append((Ao, bo))
        affines.append((int(n_hit[o]), Ao, bo, used))
    rows = []
    for n_fam, Ao, bo, used in affines:
        free = np.ones(xy.shape[0], bool)
        free[used] = False  # blobs taken by the family vote for no depth (they sit where diagonals end)
        rots = rotations_from_affine(Ao, fam, cos_max)
        for (R, _), votes in zip(rots, _depth_votes(fam, xy[free], Ao, bo, [w for _, w in rots], gate_mm)):
            for lam, n_depth in votes:
                rows.append((n_fam + n_depth, n_depth, R, fam.E @ bo + lam * fam.u))
    rows.sort(key=lambda r: (-r[0], -r[1]))
    return [rigid(R, t) for _, _, R, t in rows[:max_hypotheses]]


#: Points x blobs per chunk of the nearest-blob search (~50 MB of float64 differences at a time: an image strewn
#: with hundreds of bright pixels must not make it allocate gigabytes).
NEAREST_CHUNK = 3_000_000


def nearest_blob_mm(pred: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Distance (mm) from each predicted point ``pred`` (n, F, 2) to its nearest blob of ``xy`` (N, 2): (n, F)."""
    flat = pred.reshape(-1, 2)
    out = np.empty(flat.shape[0])
    step = max(1, NEAREST_CHUNK // max(xy.shape[0], 1))
    for i in range(0, flat.shape[0], step):
        d = flat[i:i + step, None, :] - xy[None]
        out[i:i + step] = np.sqrt(np.min(np.einsum("pnk,pnk->pn", d, d), axis=1))
    return out.reshape(pred.shape[:2])


def _refit_affine(fam: ParallelFamily, xy: np.ndarray, A: np.ndarray, b: np.ndarray, gate_mm: float):
    """Least-squares image-to-section map over the family tubes landing on blobs (>= 3, else as given).

    Returns ``(A, b, indices of the blobs used)``.
    """
    pred = np.linalg.solve(A, (fam.c - b).T).T  # (F, 2)
    d = np.linalg.norm(pred[:, None] - xy[None], axis=-1)
    j = d.argmin(axis=1)
    ok = d[np.arange(d.shape[0]), j] < gate_mm
    if ok.sum() < 3 or len(set(j[ok].tolist())) < ok.sum():
        return A, b, j[ok]
    M = np.concatenate([xy[j[ok]], np.ones((int(ok.sum()), 1))], axis=1)
    X, *_ = np.linalg.lstsq(M, fam.c[ok], rcond=None)
    return X[:2].T, X[2], j[ok]


def rotations_from_affine(A: np.ndarray, fam: ParallelFamily, cos_max: float):
    """The rotations ``R_F_from_I`` whose cut maps the image onto the section by ``A``: ``[(R, w)]``, 1 or 2.

    ``E^T R[:, :2] = A`` once ``A``'s larger singular value is set to 1 (a
    plane cut never shrinks a direction); the part along ``u``,
    ``w = u^T R[:, :2]``, has ``w w^T = I - A^T A``: known up to its sign
    (which end of the cut's steepest line is up), so two rotations.
    """
    U, s, Vt = np.linalg.svd(A)
    s2 = min(max(float(s[1]), cos_max), 1.0)
    Ap = U @ np.diag([1.0, s2]) @ Vt
    w0 = math.sqrt(max(0.0, 1.0 - s2 * s2)) * Vt[1]
    out = []
    for sign in ((1.0, -1.0) if s2 < 0.9995 else (1.0,)):
        w = sign * w0
        R2 = fam.E @ Ap + np.outer(fam.u, w)
        R = np.column_stack([R2, np.cross(R2[:, 0], R2[:, 1])])
        out.append((R, w))
    return out


def _depth_votes(fam: ParallelFamily, xy: np.ndarray, A: np.ndarray, b: np.ndarray, ws: list, gate_mm: float,
                 n_best: int = 2) -> list:
    """Positions ``lam`` of the plane along ``u`` that the non-family tubes vote for, per ``w`` in ``ws``.

    A blob at image point p sits, for the plane at ``lam``, at section point
    ``A p + b`` and height ``w . p + lam``; each non-family tube passing
    within the gate of that section point votes for the ``lam`` putting the
    blob on it. Votes agreeing within each tube's depth tolerance are pooled.
    Returns, for each ``w``, up to ``n_best`` ``(lam, n_tubes)``, most tubes first.
    """
    if xy.shape[0] == 0:
        return [[] for _ in ws]
    c = xy @ A.T + b
    Q, h = fam.sample_q, fam.sample_h
    d2 = (Q * Q).sum(axis=1)[:, None] - 2.0 * (Q @ c.T) + (c * c).sum(axis=1)[None]  # (M, N)
    idx, blob, tube, tol = [], [], [], []
    for k, (lo, hi) in enumerate(fam.sample_slices):
        m = lo + d2[lo:hi].argmin(axis=0)
        near = np.flatnonzero(d2[m, np.arange(c.shape[0])] < gate_mm * gate_mm)
        idx.append(m[near])
        blob.append(near)
        tube.append(np.full(near.size, k))
        tol.append(np.full(near.size, max(0.5 * gate_mm * min(fam.sample_rise[k], 10.0), 0.5)))
    idx, blob, tube, tol = (np.concatenate(v) for v in (idx, blob, tube, tol))
    if idx.size == 0:
        return [[] for _ in ws]
    onehot = (tube[:, None] == np.arange(len(fam.sample_slices))[None]).astype(float)
    tol_pair = np.maximum(tol[:, None], tol[None])
    out = []
    for w in ws:
        lam = h[idx] - xy[blob] @ w
        close = np.abs(lam[:, None] - lam[None]) <= tol_pair
        n = ((close @ onehot) > 0).sum(axis=1)
        votes = []
        for i in np.argsort(-n, kind="stable"):
            value = median(lam[close[i]])
            if any(abs(value - v) < 2 * tol[i] for v, _ in votes):
                continue
            votes.append((value, int(n[i])))
            if len(votes) >= n_best:
                break
        out.append(votes)
    return out
