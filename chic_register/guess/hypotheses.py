"""First guesses of the pose from one slice's blob centres, before any refinement.

Two stages, both returning ``T_F_from_I`` (4x4) guesses that
:func:`chic_register.fit.refine.refine` then fits on all six degrees of freedom:

- the **closed form** of the paper (:func:`initial_hypotheses`): a robust
  ellipse through the blob centres (:mod:`chic_register.guess.ellipse`) gives the tilt and azimuth, axial tubes the
  twist, helices the depth. It holds only when every tube lies on one cylinder
  about the axis (:func:`ellipse_layout`, the CHIC family) and is the fast path;
- the **generic** stage (:func:`~chic_register.guess.generic.family_hypotheses`, in its own module and
  importable from here), for any set of ``line``
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
import math
from typing import TYPE_CHECKING

import numpy as np

from chic_register.detect.blobs import median
from chic_register.guess.ellipse import Ellipse

if TYPE_CHECKING:
    from chic_register.model.tube_model import TubeModel

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
                cand = cands[h, k] = _helix_candidates(model, th + b[k], tol)
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


def _helix_candidates(model: TubeModel, theta_F: np.ndarray, tol: float):
    """Candidate depths of the ellipse centre, first part: from blob angles in F ``theta_F`` (N,), every (blob,
    helix) pair's height ``z`` of the model's helices at the blob's angle, within the helix's extent: ``(z (M,),
    blob (M,), depth tolerance (1, M), helix one-hot (M, H))``, or None for no helices or no pair. (It does not
    depend on the blobs' heights: :func:`initial_hypotheses` shares it between the two ends of the major axis.)"""
    if model.helix_idx.size == 0:
        return None
    th0, om, z0, period, zmid, z_above, z_below, dtol, ids = _helix_terms(model, tol)
    # z = z0 + (theta - th0 + 2 pi m) / om, pick m nearest to the middle of the tube
    raw = (theta_F[:, None] - th0) / om  # (N,H)
    m = ((zmid - raw) / period).round()
    z = z0 + raw + m * period
    inside = (z > z_above) & (z < z_below)
    bv, hv = np.nonzero(inside)  # the blob and helix of each (in the mask's order)
    if hv.size == 0:
        return None
    return z[inside], bv, dtol[hv][None, :], hv[:, None] == ids


def _depths_from(model: TubeModel, cand, zr: np.ndarray, n_best: int = 2):
    """Candidate depths of the ellipse centre from :func:`_helix_candidates`' pairs and the blobs' heights
    relative to it ``zr`` (N,).

    Every (blob, helix) pair implies a depth; depths agreed on by the most
    helices win (ties broken by spread). Returns up to ``n_best`` distinct
    ``(depth_mm, n_helices_agreeing)``, clamped to the body.
    """
    if cand is None:
        return [(model.length_mm / 2, 0)]
    zv, bv, dtol, onehot = cand
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


@functools.lru_cache(maxsize=16)
def _helix_terms(model: TubeModel, tol: float) -> tuple:
    """:func:`_helix_candidates`' per-geometry terms for the model's helices, each (1, H) (memoised per model and
    tolerance): ``(theta0, omega, z0, period, middle - z0, z_lo - 3, z_hi + 3, depth tolerance, helix numbers)``."""
    hel = model.helix_idx
    th0, om, z0 = model.theta0_rad[hel], model.omega_rad_per_mm[hel], model.z0[hel]
    zlo, zhi = model.z_lo[hel], model.z_hi[hel]
    period = 2 * np.pi / np.abs(om)
    zmid = (zlo + zhi) / 2 - z0
    dtol = tol / np.abs(om)  # depth tolerance of the angle tolerance
    terms = (th0[None, :], om[None, :], z0[None, :], period[None, :], zmid[None, :], (zlo - 3)[None, :],
             (zhi + 3)[None, :], dtol, np.arange(hel.size)[None, :])
    for a in terms:
        a.flags.writeable = False
    return terms


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

