"""Where each tube's section lies in the image, by fitting a model of the section to the pixels.

A blob's intensity centroid is a biased and noisy estimate of where a tube
crosses the slice: it sums the noise of every pixel of the footprint, and a
curved (helix), clipped (tube end) or tilted section has its centroid off the
centreline crossing. The efficient estimate fits the expected image of the
section to the pixels. Here that image is a local analytic model, evaluated
only on a small window around each matched tube and vectorised across all
tubes at once (no renders):

- the tube near its crossing is a cylinder of radius ``diameter / 2`` about
  the centreline's second-order expansion (tangent and curvature: exact for a
  line, a helix bends by ``kappa s^2 / 2``), with its end faces;
- a pixel's value is the fluid fraction of the voxel: the mean over
  ``supersample``² points across the pixel and ``thickness_samples`` planes
  across the slice thickness of an anti-aliased inside test (a linear ramp
  across each sample's footprint, as the simulator renders).

For tube ``k`` the window's pixels ``y`` are fitted, to first order in a
small in-plane shift ``d`` of the section, by ``y = b + a (S(x - d))``
(``S``: the model at the current pose; offset ``b`` and gain ``a`` free), a
linear least-squares problem in ``(b, a, a d)``. The tube's measured position
is its crossing plus ``d``; its 2 x 2 information matrix (from the same
normal equations, scaled by ``(a / sigma)^2``) weights it in the pose fit
(elongated sections locate a tube poorly along their length). The caller
refits the pose on these positions and repeats at the new pose: at the true
pose the model matches the noise-free image, so the fixed point is unbiased.

Pixels a neighbouring tube's section or another blob reaches are left out of
a window, so each fit sees one tube.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class SectionFit:
    """Per tube (K,): ``position_mm`` (K, 2) image mm (NaN where not fitted), ``info`` (K, 2, 2) in mm^-2,
    ``gain`` (fitted fluid signal), ``n_pixels`` in the window, ``fitted`` (bool); ``predicted_mm`` (K, 2):
    the crossings of the pose the model was drawn at."""

    predicted_mm: np.ndarray
    position_mm: np.ndarray
    info: np.ndarray
    gain: np.ndarray
    n_pixels: np.ndarray
    fitted: np.ndarray


def tube_frames(model, T_F_from_I: np.ndarray, q: np.ndarray, tan_I: np.ndarray):
    """Local second-order geometry of every tube at its crossing, in the image frame.

    Returns ``(kappa_I (K, 3), s_lo (K,), s_hi (K,))``: the curvature vector
    of the centreline (zero for lines) and the arc length from the crossing
    back to the tube's start and on to its end (mm).
    """
    K = q.shape[0]
    R, o = T_F_from_I[:3, :3], T_F_from_I[:3, 3]
    X = np.column_stack([q, np.zeros(K)]) @ R.T + o  # crossings in F
    kappa_F = np.zeros((K, 3))
    s_lo, s_hi = np.zeros(K), np.zeros(K)
    li, hi = model.line_idx, model.helix_idx
    if li.size:
        d = model.d[li]
        t = np.einsum("ij,ij->i", X[li] - model.p0[li], d) / np.einsum("ij,ij->i", d, d)
        length = np.linalg.norm(d, axis=1)
        s_lo[li], s_hi[li] = t * length, (1 - t) * length
    if hi.size:
        r, om = model.radius[hi], model.omega_rad_per_mm[hi]
        g2 = 1 + (r * om) ** 2
        th = np.arctan2(X[hi, 1], X[hi, 0])
        kappa_F[hi, 0] = -r * om * om * np.cos(th) / g2
        kappa_F[hi, 1] = -r * om * om * np.sin(th) / g2
        g = np.sqrt(g2)
        s_lo[hi], s_hi[hi] = (X[hi, 2] - model.z_lo[hi]) * g, (model.z_hi[hi] - X[hi, 2]) * g
    return kappa_F @ R, s_lo, s_hi


def fit_sections(model, T_F_from_I: np.ndarray, assignment: np.ndarray, pixels: np.ndarray, pixel_spacing_mm,
                 slice_thickness_mm: float, noise_sigma: float, *, footprints=(), thickness_samples: int = 5,
                 margin_px: float = 1.5) -> SectionFit:
    """Fit each matched tube's section model to ``pixels`` (rows, cols) at the pose ``T_F_from_I`` (4x4).

    ``assignment`` (K,): blob index per tube, -1 for unmatched (not fitted);
    ``footprints``: the detector's ``(row0, col0, mask)`` per blob, whose
    pixels are left out of every other tube's window; ``noise_sigma`` scales
    the information matrices. See the module docstring.
    """
    from .solve import _section_extent, plane_crossings  # (solve imports this module lazily)

    rs, cs = (float(v) for v in pixel_spacing_mm)
    H, W = pixels.shape
    q, tan, _, found = plane_crossings(model, T_F_from_I, margin_mm=1e-9)
    K = q.shape[0]
    out_pos = np.full((K, 2), np.nan)
    out_info, out_gain = np.zeros((K, 2, 2)), np.zeros(K)
    n_pix, fitted = np.zeros(K, int), np.zeros(K, bool)
    todo = np.flatnonzero((assignment >= 0) & found)
    if todo.size == 0:
        return SectionFit(q, out_pos, out_info, out_gain, n_pix, fitted)
    half_len, _, u = _section_extent(model, tan, slice_thickness_mm)
    half_wid = 0.5 * model.diameter_mm  # across its length a section is the tube's width
    u = np.where((np.abs(u).sum(axis=1) > 0)[:, None], u, [1.0, 0.0])  # a round section: any direction
    kappa, s_lo, s_hi = tube_frames(model, T_F_from_I, q, tan)
    r_tube = 0.5 * model.diameter_mm
    # ---- windows: each matched tube's section box grown by the margin, in pixels
    m_mm = margin_px * max(rs, cs)
    ex = np.abs(u[:, 0]) * half_len + np.abs(u[:, 1]) * half_wid + m_mm
    ey = np.abs(u[:, 1]) * half_len + np.abs(u[:, 0]) * half_wid + m_mm
    rows, cols, owner = [], [], []
    for k in todo.tolist():
        i0, i1 = max(0, math.ceil((q[k, 1] - ey[k]) / rs)), min(H - 1, math.floor((q[k, 1] + ey[k]) / rs))
        j0, j1 = max(0, math.ceil((q[k, 0] - ex[k]) / cs)), min(W - 1, math.floor((q[k, 0] + ex[k]) / cs))
        if i1 < i0 or j1 < j0:
            continue
        ii, jj = np.mgrid[i0:i1 + 1, j0:j1 + 1]
        rows.append(ii.ravel())
        cols.append(jj.ravel())
        owner.append(np.full(ii.size, k))
    if not rows:
        return SectionFit(q, out_pos, out_info, out_gain, n_pix, fitted)
    rr, cc, own = np.concatenate(rows), np.concatenate(cols), np.concatenate(owner)
    px, py = cc * cs, rr * rs
    # ---- leave out what another tube's section (grown by half a pixel) or another blob reaches
    others = np.flatnonzero(found)
    dx = px[:, None] - q[others, 0][None]
    dy = py[:, None] - q[others, 1][None]
    along = np.abs(dx * u[others, 0] + dy * u[others, 1])
    across = np.abs(dx * u[others, 1] - dy * u[others, 0])
    grow = 0.5 * max(rs, cs) + 0.5 * max(rs, cs)
    hit = (along < half_len[others] + grow) & (across < half_wid[others] + grow) & (others[None] != own[:, None])
    keep = ~hit.any(axis=1)
    if footprints:
        keep &= ~_foreign_blob_pixels(rr, cc, own, assignment, footprints, H, W)
    rr, cc, own, px, py = rr[keep], cc[keep], own[keep], px[keep], py[keep]
    # ---- the model at every plane of every kept pixel: (P, M)
    nz = thickness_samples if slice_thickness_mm > 0 else 1
    sz = ((np.arange(nz) + 0.5) / nz - 0.5) * float(slice_thickness_mm)
    t = tan[own]
    kap = kappa[own]
    dxs = (px - q[own, 0])[:, None]
    dys = (py - q[own, 1])[:, None]
    dzs = sz[None]
    tx, ty, tz = t[:, 0:1], t[:, 1:2], t[:, 2:3]
    kx, ky, kz = kap[:, 0:1], kap[:, 1:2], kap[:, 2:3]
    s0 = dxs * tx + dys * ty + dzs * tz  # arc length along the tangent
    h = 0.5 * s0 * s0
    ex_, ey_, ez_ = dxs - s0 * tx - h * kx, dys - s0 * ty - h * ky, dzs - s0 * tz - h * kz  # from the curve point
    ux, uy, uz = tx + s0 * kx, ty + s0 * ky, tz + s0 * kz  # its tangent (unit to first order)
    al = ex_ * ux + ey_ * uy + ez_ * uz
    ex_ -= al * ux
    ey_ -= al * uy
    ez_ -= al * uz
    dist = np.sqrt(ex_ * ex_ + ey_ * ey_ + ez_ * ez_)
    pxy = np.maximum(np.sqrt(ex_ * ex_ + ey_ * ey_), 1e-12)
    nx, ny = ex_ / pxy, ey_ / pxy  # the section edge's in-plane outward normal
    # in-plane signed distance to the edge (inside > 0), then the pixel's exact coverage of a straight edge
    delta = (r_tube[own][:, None] - dist) * (dist / pxy)
    cov, dcov = _box_edge(delta, cs * np.abs(nx), rs * np.abs(ny))
    # the edge is curved (curvature of the section's outline at the pixel): the inside loses kappa tau^2 / 2
    # along the chord of the pixel at the edge, tau its coordinate along the edge from the foot point
    kap_edge = (pxy * pxy - (ex_ * ty - ey_ * tx) ** 2) / (pxy * pxy * pxy)
    cov = cov - dcov * _chord_m2(delta, nx, ny, cs, rs) * (0.5 * kap_edge)
    gx, gy = dcov * nx, dcov * ny  # moving the section by (dx, dy) raises delta by n . (dx, dy)
    # the tube's end faces: a ramp across the pixel along the centreline
    s_along = s0 + al
    inside = np.minimum(s_lo[own][:, None] + s_along, s_hi[own][:, None] - s_along)
    w_e = np.maximum(cs * np.abs(tx) + rs * np.abs(ty), 1e-12)
    end = np.clip(0.5 + inside / w_e, 0.0, 1.0)
    S = (cov * end).mean(axis=1)
    Sx = (gx * end).mean(axis=1)
    Sy = (gy * end).mean(axis=1)
    y = np.asarray(pixels, dtype=float)[rr, cc]
    # ---- per tube linear least squares y = b + a S + (a dx) Sx + (a dy) Sy, from segment sums
    feats = (np.ones_like(S), S, Sx, Sy)
    N = np.empty((K, 4, 4))
    rhs = np.empty((K, 4))
    for i in range(4):
        rhs[:, i] = np.bincount(own, feats[i] * y, minlength=K)
        for j in range(i, 4):
            N[:, i, j] = N[:, j, i] = np.bincount(own, feats[i] * feats[j], minlength=K)
    counts = np.bincount(own, minlength=K)
    sel = todo[counts[todo] >= 8]
    if sel.size == 0:
        return SectionFit(q, out_pos, out_info, out_gain, n_pix, fitted)
    Ns = N[sel]
    good = np.linalg.cond(Ns) < 1e12
    sel, Ns = sel[good], Ns[good]
    if sel.size == 0:
        return SectionFit(q, out_pos, out_info, out_gain, n_pix, fitted)
    Ninv = np.linalg.inv(Ns)
    theta = np.einsum("kij,kj->ki", Ninv, rhs[sel])
    a = theta[:, 1]
    ok = a > 0
    shift = np.zeros((sel.size, 2))
    shift[ok] = theta[ok, 2:4] / a[ok, None]  # (x, y) mm: the sample offsets were in mm
    # information of the shift: (a / sigma)^2 times the inverse of its block of N^-1
    blk = Ninv[:, 2:4, 2:4]
    info = np.linalg.inv(blk) * ((a / max(noise_sigma, 1e-12)) ** 2)[:, None, None]
    out_pos[sel] = q[sel] + shift
    out_info[sel] = info
    out_gain[sel] = a
    n_pix[: K] = counts[: K]
    fitted[sel] = ok
    out_pos[~fitted] = np.nan
    out_info[~fitted] = 0.0
    return SectionFit(q, out_pos, out_info, out_gain, n_pix, fitted)


def _box_edge(delta: np.ndarray, A: np.ndarray, B: np.ndarray):
    """Share of a pixel inside a straight edge at signed distance ``delta`` from its centre, and its derivative.

    ``A``, ``B``: the pixel's two sides projected on the edge normal. The
    share is the distribution function of ``n . p`` for ``p`` uniform over
    the pixel: the convolution of two boxes of widths ``A`` and ``B`` (a
    trapezoid), so linear in the middle and quadratic in the corners.
    """
    m = np.maximum(np.maximum(A, B), 1e-12)
    ab = np.maximum(A * B, 1e-12)
    lo, hi = 0.5 * np.abs(A - B), 0.5 * (A + B)
    ad = np.abs(delta)
    tail = hi - ad
    corner = ad > lo
    half = np.where(corner, 0.5 - 0.5 * tail * tail / ab, ad / m)  # the share beyond 1/2, from |delta|
    slope = np.where(corner, tail / ab, 1.0 / m)
    out = ad >= hi
    half = np.where(out, 0.5, half)
    slope = np.where(out, 0.0, slope)
    return 0.5 + np.copysign(half, delta), slope


def _chord_m2(delta, nx, ny, cs: float, rs: float):
    """Mean of tau^2 over the chord ``n . p = delta`` of the pixel ``|x| <= cs/2, |y| <= rs/2``; tau along the edge.

    On the chord ``p = delta n + tau (-ny, nx)``; each pair of pixel sides
    bounds tau to an interval, and over ``[t1, t2]`` the mean of tau^2 is
    ``(t1^2 + t1 t2 + t2^2) / 3``.
    """
    big = 1e6
    with np.errstate(divide="ignore", invalid="ignore"):
        # |delta nx - tau ny| <= cs / 2
        a1, a2 = (delta * nx - 0.5 * cs) / ny, (delta * nx + 0.5 * cs) / ny
        b1, b2 = (-0.5 * rs - delta * ny) / nx, (0.5 * rs - delta * ny) / nx
    ok_a, ok_b = np.abs(ny) > 1e-9, np.abs(nx) > 1e-9
    lo = np.maximum(np.where(ok_a, np.minimum(a1, a2), -big), np.where(ok_b, np.minimum(b1, b2), -big))
    hi = np.minimum(np.where(ok_a, np.maximum(a1, a2), big), np.where(ok_b, np.maximum(b1, b2), big))
    hi = np.maximum(hi, lo)
    return (lo * lo + lo * hi + hi * hi) / 3.0


def _foreign_blob_pixels(rr, cc, own, assignment, footprints, H, W) -> np.ndarray:
    """Window pixels (P,) inside the footprint of a blob that is not the tube's own (nor overlaps it)."""
    owner_map = np.full((H, W), -1, dtype=np.int32)
    assigned = {int(b) for b in assignment if b >= 0}
    for n, (r0, c0, m) in enumerate(footprints):
        if n in assigned:
            continue
        view = owner_map[r0:r0 + m.shape[0], c0:c0 + m.shape[1]]
        view[m] = n
    hit = owner_map[rr, cc] >= 0
    if not hit.any():
        return hit
    # a blob that overlaps the tube's own blob (a split half, or the whole of a split) is not foreign
    for k in np.unique(own[hit]).tolist():
        r0, c0, m = footprints[int(assignment[k])]
        mine = np.zeros((H, W), bool)
        mine[r0:r0 + m.shape[0], c0:c0 + m.shape[1]] = m
        sel = hit & (own == k)
        overl = {int(n) for n in np.unique(owner_map[rr[sel], cc[sel]])
                 if (owner_map[mine] == n).any()}
        if overl:
            hit[sel] &= ~np.isin(owner_map[rr[sel], cc[sel]], list(overl))
    return hit
