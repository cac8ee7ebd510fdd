"""First guesses of the pose from one slice's blob centres, before any refinement.

Two stages, both returning ``T_F_from_I`` (4x4) guesses that
:func:`chic_register.refine.refine` then fits on all six degrees of freedom:

- the **closed form** of the paper (:func:`initial_hypotheses`): a robust
  ellipse through the blob centres (:mod:`chic_register.ellipse`) gives the tilt and azimuth, axial tubes the
  twist, helices the depth. It holds only when every tube lies on one cylinder
  about the axis (:func:`ellipse_layout`, the CHIC family) and is the fast path;
- the **generic** stage (:func:`family_hypotheses`), for any set of ``line``
  and ``helix`` tubes with a family of three or more parallel straight tubes
  (CHIC's axial tubes, a Z-frame's rods): every minimal set of three
  blob-to-tube correspondences in that family fixes the 2-D affine map from the
  image to the family's cross-section, hence the plane's orientation up to a
  two-fold sign (its larger singular value must be 1: a consensus check);
  the remaining translation along the family's direction comes from a vote of
  every other tube (any shape: sampled centrelines), so diagonals and helices
  alike give the depth. Nothing in it assumes a cylinder or a role.
"""

from __future__ import annotations

import functools
import itertools
import math
import weakref
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .detect import median
from .ellipse import Ellipse, fit_ellipse_robust  # noqa: F401  (fit_ellipse_robust: part of this stage's API)
from .geometry import sample_centreline
from .pose import rigid

if TYPE_CHECKING:
    from .tube_model import TubeModel

# --------------------------------------------------------------------------- closed form (ellipse)


@functools.lru_cache(maxsize=8)
def ellipse_layout(model: "TubeModel", rel_tol: float = 0.1) -> bool:
    """True when the paper's closed form applies: axial lines and z-axis helices on one cylinder.

    Every tube must be a line parallel to the axis or a helix about it, at
    radii within ``rel_tol`` of their median, with at least one axial line
    (it fixes the twist). A Z-frame's diagonals, or tubes at different radii,
    rule it out: its ellipse would be a false one. Memoised per model.
    """
    if not model.axial.any() or not np.all(model.axial | model.is_helix):
        return False
    r = model.axis_radius_mm
    med = median(r)
    return med > 0 and bool(np.all(np.abs(r - med) <= rel_tol * med))



# --------------------------------------------------------------------------- hypotheses


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def initial_hypotheses(model: TubeModel, xy_mm: np.ndarray, ell: Ellipse, *,
                       angle_tol_deg: float = 6.0, max_hypotheses: int = 6) -> list[np.ndarray]:
    """Closed-form pose guesses ``T_F_from_I`` (4x4) from an ellipse and unrolled blob angles.

    For each of the four sign choices (up end of the major axis ``s``,
    handedness ``h``) every pairing of a blob with an axial line tube gives
    a rotation ``beta`` about the axis; the rotations that line up the most
    axial tubes (all of those seen, when there are three or more) are kept,
    then the helices give the depth by consensus.
    Returns up to ``max_hypotheses`` guesses, best first.
    """
    line_ang, ang_diff = _line_angles(model)
    if line_ang.size == 0 or xy_mm.shape[0] == 0:
        return []
    cos_t = min(1.0, ell.b / ell.a)
    sin_t = math.sqrt(max(0.0, 1 - cos_t * cos_t))
    c, s_ = math.cos(ell.phi), math.sin(ell.phi)
    rel = xy_mm - ell.centre
    u = rel @ np.array([c, s_])
    w = rel @ np.array([-s_, c])
    Kl = line_ang.size
    hel = model.helix_idx
    tol = math.radians(angle_tol_deg)
    signs = [(1.0, 1.0), (1.0, -1.0), (-1.0, 1.0), (-1.0, -1.0)] if sin_t > 0.02 else [(1.0, 1.0), (1.0, -1.0)]
    per_h = {}
    for h in sorted({h for _, h in signs}, reverse=True):  # the line match does not depend on s
        th = np.arctan2(h * w, u * cos_t)  # (N,)
        beta = (line_ang[None, :] - th[:, None]).ravel()  # (B,)
        rows_b, cols_l = np.arange(beta.size)[:, None], np.arange(Kl)[None, :]
        # th[n] - th[i] + ang[l] - ang[m], each difference wrapped first: one add and two compares to wrap;
        # laid out (B, Kl, N) so that the search over blobs runs along the last (contiguous) axis
        e = (_wrap(th[None, :] - th[:, None])[:, None, None, :] + ang_diff).reshape(beta.size, Kl, th.size)
        np.subtract(e, 2 * np.pi, out=e, where=e >= np.pi)  # (never both: e >= pi leaves e - 2 pi >= -pi)
        np.add(e, 2 * np.pi, out=e, where=e < -np.pi)
        jmin = np.abs(e).argmin(axis=2)  # (B,Kl) (the methods here and below: np.argmin's numbers, less its wrapper)
        emin = e[rows_b, cols_l, jmin]  # np.take_along_axis, less its wrapper
        hit = np.abs(emin) < tol
        n_lines = np.add.reduce(hit, axis=1)
        b = beta - np.add.reduce(np.where(hit, emin, 0), axis=1) / np.maximum(n_lines, 1)
        per_h[h] = (th, n_lines, b)
    top = max(int(n_lines.max()) for _, n_lines, _ in per_h.values())
    floor = top if top >= 3 else max(top - 1, 1)
    kept = {}  # per h: the rotations kept, their line counts and each distinct rounded rotation's first index
    for h, (th, n_lines, b) in per_h.items():
        keep = n_lines >= floor
        b, nl = b[keep], n_lines[keep]
        key = np.degrees(_wrap(b)).round().astype(int)
        first = {}  # each key's first index, keys ascending: np.unique(key, return_index=True)[1] without its sorts
        for i, v in enumerate(key.tolist()):
            first.setdefault(v, i)
        kept[h] = (b, nl, [k for _, k in sorted(first.items())])
    rows = []  # (score, n_hel, s, h, beta, depth)
    cands = {}  # (h, k) -> the helix crossings of that rotation (they do not depend on s)
    for s, h in signs:
        th = per_h[h][0]
        zr = s * u * sin_t
        b, nl, ks = kept[h]
        for k in ks:
            cand = cands.get((h, k))
            if cand is None:
                cand = cands[h, k] = _helix_candidates(model, hel, th + b[k], tol)
            for depth, n_hel in _depths_from(model, cand, zr):
                rows.append((int(nl[k]) + n_hel, n_hel, s, h, float(b[k]), depth))
    rows.sort(key=lambda t: (-t[0], -t[1]))
    out, seen = [], []
    for score, n_hel, s, h, b, depth in rows:
        if any(k[0] == s and k[1] == h and abs(_wrap(k[2] - b)) < 0.05 and abs(k[3] - depth) < 2.0 for k in seen):
            continue
        seen.append((s, h, b, depth))
        out.append(_pose_from_hypothesis(ell, cos_t, sin_t, s, h, b, depth))
        if len(out) >= max_hypotheses:
            break
    return out


@functools.lru_cache(maxsize=8)
def _line_angles(model: TubeModel) -> tuple[np.ndarray, np.ndarray]:
    """The axial line tubes' angles (Kl,) and their wrapped differences ``ang[l] - ang[m]`` shaped (1, Kl, Kl, 1)
    for :func:`initial_hypotheses` (memoised per model; read-only)."""
    line_ang = model.angle_rad[model.axial]
    diff = _wrap(line_ang[:, None] - line_ang[None, :])[None, :, :, None]
    line_ang.flags.writeable = diff.flags.writeable = False
    return line_ang, diff


def _helix_candidates(model: TubeModel, hel: np.ndarray, theta_F: np.ndarray, tol: float):
    """Candidate depths of the ellipse centre, first part: from blob angles in F ``theta_F`` (N,), every (blob,
    helix) pair's height ``z`` of the helix at the blob's angle, within the helix's extent: ``(z (M,), blob (M,),
    helix (M,), depth tolerance (1, M), helix one-hot (M, H))``, or None for no helices or no pair. (It does not
    depend on the blobs' heights: :func:`initial_hypotheses` shares it between the two ends of the major axis.)"""
    if hel.size == 0:
        return None
    th0, om, z0, period, zmid, z_above, z_below, dtol, ids = _helix_terms(model, hel, tol)
    # z = z0 + (theta - th0 + 2 pi m) / om, pick m nearest to the middle of the tube
    raw = (theta_F[:, None] - th0) / om  # (N,H)
    m = ((zmid - raw) / period).round()
    z = z0 + raw + m * period
    inside = (z > z_above) & (z < z_below)
    bv, hv = np.nonzero(inside)  # the blob and helix of each (in the mask's order)
    if hv.size == 0:
        return None
    return z[inside], bv, hv, dtol[hv][None, :], hv[:, None] == ids


def _depths_from(model: TubeModel, cand, zr: np.ndarray, n_best: int = 2):
    """Candidate depths of the ellipse centre from :func:`_helix_candidates`' pairs and the blobs' heights
    relative to it ``zr`` (N,).

    Every (blob, helix) pair implies a depth; depths agreed on by the most
    helices win (ties broken by spread). Returns up to ``n_best`` distinct
    ``(depth_mm, n_helices_agreeing)``, clamped to the body.
    """
    if cand is None:
        return [(model.length_mm / 2, 0)]
    zv, bv, _, dtol, onehot = cand
    dv = zv - zr[bv]  # each pair's depth
    diff = np.abs(dv[:, None] - dv[None, :])
    close = diff < dtol
    # (np.add.reduce: the sums' numbers, less ndarray.sum's wrapper)
    n = np.add.reduce(close @ onehot, axis=1)  # helices agreeing with each depth (a boolean product: any)
    n_close = np.add.reduce(close, axis=1)
    spread = np.add.reduce(np.where(close, diff, 0), axis=1) / np.maximum(n_close, 1)
    means = (close @ dv) / n_close  # each row holds its own depth: never empty
    L = model.length_mm
    out = []
    means_l, n_l = means.tolist(), n.tolist()
    for i in np.lexsort((spread, -n)).tolist():
        depth = means_l[i]
        if any(abs(depth - o[0]) < 1.0 for o in out):
            continue
        out.append((min(max(depth, 0.0), L), n_l[i]))
        if len(out) >= n_best:
            break
    return out


def _helix_terms(model: TubeModel, hel: np.ndarray, tol: float) -> tuple:
    """:func:`_helix_candidates`' per-geometry terms, each (1, H) (memoised per model, helices and tolerance):
    ``(theta0, omega, z0, period, middle - z0, z_lo - 3, z_hi + 3, depth tolerance, helix numbers)``."""
    memo = _HELIX_TERMS.get(model)
    if memo is None:
        memo = _HELIX_TERMS[model] = {}
    key = (hel.tobytes(), tol)
    terms = memo.get(key)
    if terms is None:
        th0, om, z0 = model.theta0_rad[hel], model.omega_rad_per_mm[hel], model.z0[hel]
        zlo, zhi = model.z_lo[hel], model.z_hi[hel]
        period = 2 * np.pi / np.abs(om)
        zmid = (zlo + zhi) / 2 - z0
        dtol = tol / np.abs(om)  # depth tolerance of the angle tolerance
        terms = (th0[None, :], om[None, :], z0[None, :], period[None, :], zmid[None, :], (zlo - 3)[None, :],
                 (zhi + 3)[None, :], dtol, np.arange(hel.size)[None, :])
        for a in terms:
            a.flags.writeable = False
        if len(memo) >= 16:
            memo.clear()
        memo[key] = terms
    return terms


_HELIX_TERMS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _pose_from_hypothesis(ell: Ellipse, cos_t, sin_t, s, h, beta, depth) -> np.ndarray:
    """``T_F_from_I`` placing the ellipse centre on the axis at ``depth`` (see module docstring)."""
    # columns of F's frame: m = cos_t e1 + s sin_t z, mn = h e2, m x mn; of the image: u_maj, u_min, z
    c, s_ = math.cos(ell.phi), math.sin(ell.phi)
    cb, sb = math.cos(beta), math.sin(beta)
    m = (cos_t * cb, cos_t * sb, s * sin_t)
    mn = (-h * sb, h * cb, 0.0)
    m3 = (m[1] * mn[2] - m[2] * mn[1], m[2] * mn[0] - m[0] * mn[2], m[0] * mn[1] - m[1] * mn[0])
    # R = F @ I^T with I = [[c, -s_, 0], [s_, c, 0], [0, 0, 1]]; in floats, one array at the end (rigid's numbers)
    R = [[m[i] * c - mn[i] * s_, m[i] * s_ + mn[i] * c, m3[i]] for i in range(3)]
    cx, cy = float(ell.centre[0]), float(ell.centre[1])
    o = (-(R[0][0] * cx + R[0][1] * cy), -(R[1][0] * cx + R[1][1] * cy), depth - (R[2][0] * cx + R[2][1] * cy))
    return np.array([R[0] + [o[0]], R[1] + [o[1]], R[2] + [o[2]], [0.0, 0.0, 0.0, 1.0]])



# --------------------------------------------------------------------------- generic: parallel family + depth vote

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


def _affine_candidates(fam: ParallelFamily, xy: np.ndarray, gate_mm: float, cos_max: float, max_pairs: int,
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
    blob_t, ti = _affine_candidates(fam, xy, gate_mm, cos_max, max_pairs, rng)
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
    dist = _nearest_blob_mm(pred, xy)  # (n, F)
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
        rots = _rotations_from_affine(Ao, fam, cos_max)
        for (R, _), votes in zip(rots, _depth_votes(fam, xy[free], Ao, bo, [w for _, w in rots], gate_mm)):
            for lam, n_depth in votes:
                rows.append((n_fam + n_depth, n_depth, R, fam.E @ bo + lam * fam.u))
    rows.sort(key=lambda r: (-r[0], -r[1]))
    return [rigid(R, t) for _, _, R, t in rows[:max_hypotheses]]


#: Points x blobs per chunk of the nearest-blob search (~50 MB of float64 differences at a time: an image strewn
#: with hundreds of bright pixels must not make it allocate gigabytes).
NEAREST_CHUNK = 3_000_000


def _nearest_blob_mm(pred: np.ndarray, xy: np.ndarray) -> np.ndarray:
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


def _rotations_from_affine(A: np.ndarray, fam: ParallelFamily, cos_max: float):
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
