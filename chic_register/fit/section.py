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
- a pixel's value is the fluid fraction of the voxel, averaged over
  ``thickness_samples`` planes across the slice thickness (as the simulator
  renders); in each plane, the exact share of the pixel inside the section's
  edge taken as straight (a trapezoid in the signed distance,
  :func:`box_edge`) less the edge's curvature times the second moment of
  the pixel's chord along it (:func:`chord_m2`); pixels no edge crosses are
  1 or 0 without that work.

For tube ``k`` the window's pixels ``y`` are fitted, to first order in a
small in-plane shift ``d`` of the section, by ``y = b + a (S(x - d))``
(``S``: the model at the current pose; offset ``b`` and gain ``a`` free), a
linear least-squares problem in ``(b, a, a d)`` (solved for all tubes at
once from per-window sums). The tube's measured position
is its crossing plus ``d``; its 2 x 2 information matrix (from the same
normal equations, scaled by ``(a / sigma)^2``) weights it in the pose fit
(elongated sections locate a tube poorly along their length). The caller
refits the pose on these positions and repeats at the new pose: at the true
pose the model matches the noise-free image, so the fixed point is unbiased.

Pixels a neighbouring tube's section or another blob reaches are left out of
a window, so each fit sees one tube; a joint pass then gives each tube back the
pixels it shares with a fitted neighbour, that neighbour's fitted section
subtracted (near the body's ends a helix runs close to its straight tube: the
fit was 1.2-1.6x the Cramér-Rao bound there without it).

In a magnitude image (Rician noise) a section's faint edge pixels read
brighter than ``b + a S``; the fit then takes the model's Rician mean instead
(:mod:`chic_register.imaging.rician`), or that lift moves the sections by a bias that
grows with the noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from chic_register.fit.windows import (
    Windows,
    joint_windows,
    joint_windows_from_reach,
    kept_pixels,
    section_windows,
    window_pixels,
)
from chic_register.imaging.pixel_coverage import blurred_box_edge, chord_m2
from chic_register.imaging.rician import inner_gain, rician_model
from chic_register.model.tube_model import plane_crossings

__all__ = ["SectionFit", "Windows", "fit_sections", "joint_windows", "section_model", "section_windows", "tube_frames"]


@dataclass(frozen=True, eq=False)
class SectionFit:
    """Per tube (K,): ``position_mm`` (K, 2) image mm (NaN where not fitted), ``info`` (K, 2, 2) in mm^-2,
    ``gain`` (fitted fluid signal), ``n_pixels`` in the window, ``fitted`` (bool); ``predicted_mm`` (K, 2):
    the crossings of the pose the model was drawn at. With the point spread measured (``fit_sections``'
    ``measure_blur``): ``blur_step_mm2``, the change of its variance the sections ask for, its information
    ``blur_info`` (mm^-4; 0: not measured) and ``blur_chi2``, the tubes' own steps' scatter about it over their
    noise (per degree of freedom: about 1 when one blur describes every section)."""

    predicted_mm: np.ndarray
    position_mm: np.ndarray
    info: np.ndarray
    gain: np.ndarray
    n_pixels: np.ndarray
    fitted: np.ndarray
    blur_step_mm2: float = 0.0
    blur_info: float = 0.0
    blur_chi2: float = 0.0


def tube_frames(model, T_F_from_I: np.ndarray, q: np.ndarray, tan_I: np.ndarray):
    """Local second-order geometry of every tube at its crossing, in the image frame.

    Returns ``(kappa_I (K, 3), s_lo (K,), s_hi (K,))``: the curvature vector
    of the centreline (zero for lines) and the arc length from the crossing
    back to the tube's start and on to its end (mm).
    """
    key = (id(model), T_F_from_I.tobytes(), q.tobytes())
    hit = _FRAMES.get(key)
    if hit is not None and hit[0] is model:
        return hit[1]  # (read-only arrays)
    K = q.shape[0]
    R, o = T_F_from_I[:3, :3], T_F_from_I[:3, 3]
    Xq = np.zeros((K, 3))
    Xq[:, :2] = q
    X = Xq @ R.T + o  # crossings in F
    x_F, y_F, z_F = X.T.copy()  # (rows: 1-d gathers, cheaper than 2-d fancy indexing)
    k_x, k_y = np.zeros(K), np.zeros(K)
    s_lo, s_hi = np.zeros(K), np.zeros(K)
    li, hi = model.line_idx, model.helix_idx
    if li.size:
        d, p0, dd, length = model.line_d, model.line_p0, model.line_dd, model.line_length_mm
        t = np.einsum("ij,ij->i", np.take(X, li, axis=0) - p0, d) / dd
        s_lo[li], s_hi[li] = t * length, (1 - t) * length
    if hi.size:
        r, om = model.radius[hi], model.omega_rad_per_mm[hi]
        g2 = 1 + (r * om) ** 2
        th = np.arctan2(y_F[hi], x_F[hi])
        c = -r * om * om
        k_x[hi] = c * np.cos(th) / g2
        k_y[hi] = c * np.sin(th) / g2
        g = np.sqrt(g2)
        z = z_F[hi]
        s_lo[hi], s_hi[hi] = (z - model.z_lo[hi]) * g, (model.z_hi[hi] - z) * g
    kappa_F = np.zeros((K, 3))
    kappa_F[:, 0], kappa_F[:, 1] = k_x, k_y
    out = (kappa_F @ R, s_lo, s_hi)
    for v in out:
        v.flags.writeable = False
    if len(_FRAMES) >= 4:
        _FRAMES.clear()
    _FRAMES[key] = (model, out)  # a fit draws the model at the same crossings several times
    return out


_FRAMES: dict = {}  # tube_frames' last few results: (model id, pose bytes, crossings bytes) -> (model, result)


#: Passes of the joint fit (each tube refitted on the pixels it shares with fitted neighbours, their sections
#: subtracted; a second pass, with the neighbours' refitted positions, changed no figure of the study poses) ...
JOINT_PASSES = 1
#: ... using a shared pixel only where the neighbour's model (fluid fraction) is at most this.
JOINT_NEIGHBOUR_LEVEL = 0.05
#: A pixel this many point-spread sigmas beyond a section's edge is drawn as having none of it.
PSF_REACH_SIGMAS = 5.0
#: The sections' own point-spread variances differ by about this much (px^2) with no noise at all, on slices
#: rendered from the printed body through k-space: the section model's own error, beside their noise in
#: :func:`blur_step`'s agreement test.
BLUR_FLOOR_PX2 = 0.008

# the products summed per window: (i, j) of [1, S, Sx, Sy] for i <= j, then each with the pixel value y
_PAIR_I = np.array([0, 0, 0, 0, 1, 1, 1, 2, 2, 3, 0, 1, 2, 3])
_PAIR_J = np.array([0, 1, 2, 3, 1, 2, 3, 2, 3, 3, 4, 4, 4, 4])
_SYM = np.array([[0, 1, 2, 3], [1, 4, 5, 6], [2, 5, 7, 8], [3, 6, 8, 9]])
# _linear_fit's rows of products: 1, S, Sx, Sy, y, then rows _PROD_I times rows _PROD_J; _PROD_ROW: the row of
# each (_PAIR_I, _PAIR_J) product
_PROD_I = np.array([1, 1, 1, 2, 2, 3, 1, 2, 3])
_PROD_J = np.array([1, 2, 3, 2, 3, 3, 4, 4, 4])
_PROD_ROW = np.array([0, 1, 2, 3, 5, 6, 7, 8, 9, 10, 4, 11, 12, 13])
_ADJUGATE_SIGN = np.array([[1.0, -1.0], [-1.0, 1.0]])


def section_model(model, T_F_from_I: np.ndarray, q: np.ndarray, tan: np.ndarray, win: Windows, pixel_spacing_mm,
                  slice_thickness_mm: float, thickness_samples: int = 5, exact: bool = True, *, slopes: bool = True,
                  psf_sigma_mm: float = 0.0, spread: bool = False):
    """The model image of each window pixel's tube and its derivatives for the section moving in the image.

    Returns ``(S, Sx, Sy)`` (P,): the fluid fraction of the pixel and its
    derivatives (per mm) for the section shifted along x (columns) and y (rows).
    ``exact=False``: without the edge-curvature term (a first approximation,
    for a pass whose only job is to bring the next one close). ``slopes=False``:
    ``S`` alone (``Sx``, ``Sy`` None), for a neighbour's level. ``psf_sigma_mm``:
    the image's Gaussian point spread across the section's edge; ``spread``: also
    ``Sv``, the derivative in its variance (mm^-2), as a fourth value.
    """
    rs, cs = (float(v) for v in pixel_spacing_mm)
    thick = float(slice_thickness_mm)
    kappa, s_lo, s_hi = tube_frames(model, T_F_from_I, q, tan)
    r_tube = 0.5 * model.diameter_mm
    own = win.owner
    # ---- pixels no edge crosses in any plane are wholly fluid (1) or wholly outside (0), with no slope: from
    # the middle plane, the distance to the centreline moving by at most |t_xy| T / 2 across the slab, plus the
    # half-diagonal of the pixel and the helix's sag over the window
    # (per-tube values gathered per pixel from contiguous rows: numpy's 2-d fancy indexing costs several times more)
    qx, qy = q.T.copy()
    tan_rows = tan.T.copy()
    dx0, dy0 = win.cols * cs - qx[own], win.rows * rs - qy[own]
    txy = np.hypot(tan_rows[0], tan_rows[1])
    s00 = dx0 * tan_rows[0][own] + dy0 * tan_rows[1][own]
    dist0 = np.sqrt(np.maximum(dx0 * dx0 + dy0 * dy0 - s00 * s00, 0.0))
    reach = np.hypot(dx0, dy0) + 0.5 * thick + 0.5 * math.hypot(cs, rs)
    # (per tube, then per pixel: the same values as per pixel throughout, fewer operations)
    kappa_norm = np.sqrt(np.add.reduce(kappa * kappa, axis=1))  # (np.linalg.norm's sums, without its wrapper)
    slack = ((txy * 0.5 * thick)[own] + (0.5 * kappa_norm)[own] * reach * reach
             + 0.5 * math.hypot(cs, rs) + 1e-6 + PSF_REACH_SIGMAS * psf_sigma_mm)
    clear_end = np.minimum(s_lo[own] + s00, s_hi[own] - s00) - reach
    S = np.zeros(own.size)
    Sx, Sy = (np.zeros(own.size), np.zeros(own.size)) if slopes else (None, None)
    Sv = np.zeros(own.size) if spread else None
    inner = r_tube[own] - dist0
    deep = inner > slack
    S[deep & (clear_end > 0)] = 1.0
    band = np.flatnonzero((np.abs(inner) <= slack) | (deep & (clear_end <= 0)))
    if band.size:
        drawn = _section_band(tan_rows, kappa, s_lo, s_hi, r_tube, own[band], dx0[band], dy0[band], cs, rs, thick,
                              thickness_samples, ends=bool((clear_end[band] <= 0).any()), curved=exact,
                              s00=s00[band], slopes=slopes, sigma=psf_sigma_mm, spread=spread)
        S[band] = drawn[0]
        if slopes:
            Sx[band], Sy[band] = drawn[1:3]
        if spread:
            Sv[band] = drawn[-1]
    return (S, Sx, Sy, Sv) if spread else (S, Sx, Sy)


def _section_band(tan_rows, kappa, s_lo, s_hi, r_tube, own, dx0, dy0, cs: float, rs: float, thick: float,
                  thickness_samples: int, ends: bool = True, curved: bool = True, s00=None, slopes: bool = True,
                  sigma: float = 0.0, spread: bool = False):
    """:func:`section_model` at pixels an edge may cross: every plane across the slice, the exact pixel coverage.

    ``tan_rows`` (3, K): the tubes' tangents, a row per component.

    The distance of a point to the centreline is measured from the curve
    point ``s0 t + kappa s0^2 / 2`` at its arc length ``s0`` along the
    tangent (the re-projection onto the curve moves it by a second-order
    amount, below 1e-3 mm for these curvatures). ``ends``: model the end faces;
    ``curved``: correct the coverage for the curvature of the section's edge; ``sigma``: the point spread across
    the edge (:func:`~chic_register.imaging.pixel_coverage.blurred_box_edge`), ``spread``: its variance's derivative
    last.
    """
    # (laid out plane by pixel, (nz, P): a per-pixel value broadcasts along whole rows, where the pixel-by-plane
    # layout broadcast along rows of nz; the same values, operation by operation)
    nz = thickness_samples if thick > 0 else 1
    sz = (((np.arange(nz) + 0.5) / nz - 0.5) * thick)[:, None]
    tx, ty, tz = np.take(tan_rows, own, axis=1)
    kap = np.take(kappa.T, own, axis=1)
    if s00 is None:  # (section_model has it: dx0 t_x + dy0 t_y)
        s00 = dx0 * tx + dy0 * ty
    s0 = s00 + sz * tz  # arc length along the tangent
    h = 0.5 * s0 * s0
    ex_ = dx0 - s0 * tx - h * kap[0]
    ey_ = dy0 - s0 * ty - h * kap[1]
    ez_ = sz - s0 * tz - h * kap[2]
    pxy2 = ex_ * ex_ + ey_ * ey_
    dist = np.sqrt(pxy2 + ez_ * ez_)
    inv_p = 1.0 / np.sqrt(np.maximum(pxy2, 1e-24))
    nx, ny = ex_ * inv_p, ey_ * inv_p  # the section edge's in-plane outward normal
    # in-plane signed distance to the edge (inside > 0), and the pixel's exact coverage of a straight edge
    delta = (r_tube[own] - dist) * (dist * inv_p)
    A, B = cs * np.abs(nx), rs * np.abs(ny)
    cov, dcov, *dv = blurred_box_edge(delta, A, B, sigma, spread=spread)
    # the edge is curved (curvature of the section's outline at the pixel): the inside loses kappa tau^2 / 2
    # along the chord of the pixel at the edge, tau its coordinate along the edge from the foot point (a blurred
    # edge's tail beyond the pixel: the chord at the pixel's side)
    if curved:
        cross = (ex_ * ty - ey_ * tx) * inv_p
        edge = delta if not sigma > 0 else np.clip(delta, -0.5 * (A + B), 0.5 * (A + B))
        cov -= dcov * chord_m2(edge, nx, ny, cs, rs) * (0.5 * (1.0 - cross * cross) * inv_p)
    if ends:  # the tube's end faces: a ramp across the pixel along the centreline
        inside = np.minimum(s_lo[own] + s0, s_hi[own] - s0)
        end = np.clip(0.5 + inside / np.maximum(cs * np.abs(tx) + rs * np.abs(ty), 1e-12), 0.0, 1.0)
        cov *= end
        if slopes:
            dcov *= end
        if spread:
            dv[0] = dv[0] * end
    inv_nz = 1.0 / nz
    extra = (np.ascontiguousarray(dv[0].T).sum(axis=1) * inv_nz,) if spread else ()
    if not slopes:
        return (np.ascontiguousarray(cov.T).sum(axis=1) * inv_nz,) + extra
    # moving the section by (dx, dy) raises delta by n . (dx, dy); the sums over the planes in pixel-by-plane
    # layout, as numpy orders them there (a sum's rounding depends on its order)
    cov, dcov, nx, ny = (np.ascontiguousarray(v.T) for v in (cov, dcov, nx, ny))
    return (cov.sum(axis=1) * inv_nz, np.einsum("ij,ij->i", dcov, nx) * inv_nz,
            np.einsum("ij,ij->i", dcov, ny) * inv_nz) + extra


def fit_sections(model, T_F_from_I: np.ndarray, assignment: np.ndarray, pixels: np.ndarray, pixel_spacing_mm,
                 slice_thickness_mm: float, noise_sigma: float, *, footprints=(), thickness_samples: int = 5,
                 margin_px: float = 1.5, windows: Windows | None = None,
                 shift_iterations: int = 1, exact: bool = True, joint: bool = True,
                 rician_sigma: float = 0.0, lost=None, psf_sigma_mm: float = 0.0,
                 measure_blur: bool = False) -> tuple[SectionFit, Windows]:
    """Fit each matched tube's section model to ``pixels`` (rows, cols) at the pose ``T_F_from_I`` (4x4).

    ``assignment`` (K,): blob index per tube, -1 for unmatched (not fitted);
    ``footprints``: the detector's ``(row0, col0, mask)`` per blob, whose
    pixels are left out of every other tube's window; ``noise_sigma`` scales
    the information matrices; ``windows``: the pixels to use (from an earlier
    call at a nearby pose), else :func:`section_windows` (less ``lost``);
    ``shift_iterations``: fits per tube, each with the model drawn where the
    previous one put the section (the first-order fit is then refined to
    second order); ``exact``: see :func:`section_model`; ``joint``: refit
    the tubes on the pixels they share with their neighbours, whose fitted
    sections are subtracted (:func:`joint_pass`); ``rician_sigma`` > 0: the
    pixels are magnitudes with Rician noise of that scale, and the fit is
    of their mean (:func:`~chic_register.imaging.rician.rician_model`); ``lost``: (rows, cols) bool, pixels lost to
    dropout (:mod:`chic_register.detect.dropout`; their filled values carry no information), left out of every window.
    ``psf_sigma_mm``: the image's point spread (:func:`section_model`); ``measure_blur``: also the change of its
    variance the sections' pixels ask for (:func:`blur_step`; ``SectionFit.blur_step_mm2``), from the tubes' own
    windows. Returns the fit and the windows.
    See the module docstring.
    """
    q, tan, _, found = plane_crossings(model, T_F_from_I, margin_mm=1e-9)
    K = q.shape[0]
    out_pos = np.full((K, 2), np.nan)
    out_info, out_gain = np.zeros((K, 2, 2)), np.zeros(K)
    n_pix, fitted = np.zeros(K, int), np.zeros(K, bool)
    todo = np.flatnonzero((assignment >= 0) & found)
    reach = None  # the windows' pixels and what reaches them: the joint pass's too while it fits the same tubes
    ahead = None  # the joint pass's windows when they are known now (see below)
    joint = joint and exact and int(shift_iterations) <= 1
    if windows is None:
        reach = window_pixels(model, q, tan, found, todo, pixels.shape, pixel_spacing_mm, slice_thickness_mm,
                               margin_px, lost)
        keep, shared = kept_pixels(reach, assignment, footprints)
        windows = Windows(reach.rows[keep], reach.cols[keep], reach.own[keep], shared)
        if joint and shared and todo.size >= 2:
            # a joint pass that fits the same tubes (the usual case) uses these windows and the pixels they share:
            # draw the first model on all of them at once (each pixel's value depends on that pixel alone)
            modelled = np.zeros(K, bool)
            modelled[todo] = True
            ahead = joint_windows_from_reach(reach, assignment, footprints, modelled)
            in_windows = keep[ahead[3]]  # the windows' pixels among the joint windows' (a subset)
    own = windows.owner
    if todo.size == 0 or own.size == 0:
        return SectionFit(q, out_pos, out_info, out_gain, n_pix, fitted), windows
    drawn_on = windows if ahead is None else ahead[0]
    y = np.asarray(pixels, dtype=float)[drawn_on.rows, drawn_on.cols]
    if ahead is not None:
        y_joint, y = y, y[in_windows]
    starts = np.flatnonzero(np.concatenate(([True], own[1:] != own[:-1])))  # windows are contiguous, one per tube
    at = q.copy()  # where each section model is drawn: the crossing, then the fitted position
    sel = todo
    at_crossing = None  # the model drawn at the crossings (the first fit's): the joint pass reuses it
    for _ in range(max(1, int(shift_iterations))):
        if at_crossing is None:
            S, Sx, Sy, *Sv = section_model(model, T_F_from_I, at, tan, drawn_on, pixel_spacing_mm,
                                           slice_thickness_mm, thickness_samples, exact, psf_sigma_mm=psf_sigma_mm,
                                           spread=measure_blur)
            at_crossing = (drawn_on, (S, Sx, Sy))
            if ahead is not None:
                S, Sx, Sy = S[in_windows], Sx[in_windows], Sy[in_windows]
                Sv = [v[in_windows] for v in Sv]
        else:
            S, Sx, Sy, *Sv = section_model(model, T_F_from_I, at, tan, windows, pixel_spacing_mm, slice_thickness_mm,
                                           thickness_samples, exact, psf_sigma_mm=psf_sigma_mm, spread=measure_blur)
        blur_terms = None
        if rician_sigma > 0:  # the Rician mean at each tube's gain (from its inner pixels, else a linear fit)
            gain = inner_gain(S, y, own, K, rician_sigma)
            if not gain[sel].all():
                sel_l, _, _, a_l, _ = _linear_fit(S, Sx, Sy, y, own, starts, K, sel, noise_sigma)
                lin = np.zeros(K)
                lin[sel_l] = a_l
                gain = np.where(gain > 0, gain, lin)
            gain[gain <= 0] = 1.0  # (a tube no fit locates: any gain)
            M, Mx, My, _ = rician_model(S, Sx, Sy, gain[own], None, rician_sigma)
            if measure_blur:  # (the Rician mean's slope, as for the shifts)
                blur_terms = (M, Mx, My, rician_model(S, Sv[0], Sv[0], gain[own], None, rician_sigma)[1], sel)
            sel, shift, info, a, n_pix = _linear_fit(M, Mx, My, y, own, starts, K, sel, noise_sigma)
        else:
            if measure_blur:
                blur_terms = (S, Sx, Sy, Sv[0], sel)
            sel, shift, info, a, n_pix = _linear_fit(S, Sx, Sy, y, own, starts, K, sel, noise_sigma)
        if sel.size == 0:
            return SectionFit(q, out_pos, out_info, out_gain, n_pix, fitted), windows
        at[sel] += shift
    px2 = float(pixel_spacing_mm[0]) * float(pixel_spacing_mm[1])
    blur = (0.0, 0.0, 0.0) if blur_terms is None else blur_step(*blur_terms[:4], y, own, starts, K, blur_terms[4],
                                                                 noise_sigma, BLUR_FLOOR_PX2 * px2)
    if joint and windows.shared and sel.size >= 2:
        same = reach is not None and np.array_equal(sel, todo)  # the same tubes: the same joint windows
        sel, at, info, a, n_pix = joint_pass(model, T_F_from_I, q, tan, found, pixels, pixel_spacing_mm,
                                              slice_thickness_mm, thickness_samples, exact, noise_sigma, assignment,
                                              footprints, margin_px, sel, at, info, a, n_pix,
                                              reach if same else None, at_crossing, rician_sigma,
                                              ahead[:3] + (y_joint,) if same and ahead is not None else None,
                                              lost, psf_sigma_mm)
    out_pos[sel] = at[sel]
    out_info[sel] = info
    out_gain[sel] = a
    fitted[sel] = True
    return SectionFit(q, out_pos, out_info, out_gain, n_pix, fitted, *blur), windows


def joint_pass(model, T_F_from_I, q, tan, found, pixels, pixel_spacing_mm, slice_thickness_mm: float,
                thickness_samples: int, exact: bool, noise_sigma: float, assignment, footprints, margin_px: float,
                sel, at, info, a, n_pix, reach=None, at_crossing=None, rician_sigma: float = 0.0, ahead=None,
                lost=None, psf_sigma_mm: float = 0.0):
    """Refit the tubes ``sel`` on the pixels they share with fitted neighbours, those neighbours' fitted
    sections (position ``at``, level ``a``) subtracted (:func:`joint_windows`); :data:`JOINT_PASSES` times.
    Returns ``(sel, at, info, a, n_pix)`` as :func:`_linear_fit` gives them, unchanged when no pixel is
    shared or a tube would be lost. ``at_crossing``: ``(windows, (S, Sx, Sy))``, :func:`section_model` at the
    crossings ``q`` on some windows, whose pixels are then not drawn again (the model is pixel by pixel).
    ``ahead``: ``(windows, pixel, tube, y)``, :func:`joint_windows` and their pixels' values, when ``at_crossing``
    was drawn on exactly those windows. ``lost``, ``psf_sigma_mm``: as for :func:`fit_sections`."""
    K = q.shape[0]
    if ahead is None:
        modelled = np.zeros(K, bool)
        modelled[sel] = True
        jw, nb_p, nb_k = joint_windows(model, q, tan, found, sel, pixels.shape, pixel_spacing_mm, slice_thickness_mm,
                                       modelled, assignment, footprints, margin_px, reach, lost)
    else:
        jw, nb_p, nb_k, y = ahead
    if nb_p.size == 0:
        return sel, at, info, a, n_pix
    gain = np.zeros(K)
    gain[sel] = a
    fitted_at = q.copy()
    fitted_at[sel] = at[sel]
    # only a neighbour's faint reach is used: where its model is above JOINT_NEIGHBOUR_LEVEL the subtraction would
    # carry its partial-volume model error (largest at steep, elongated sections) into the tube's fit
    neighbours = Windows(jw.rows[nb_p], jw.cols[nb_p], nb_k)
    Sn0 = section_model(model, T_F_from_I, fitted_at, tan, neighbours, pixel_spacing_mm, slice_thickness_mm,
                        thickness_samples, exact, slopes=False, psf_sigma_mm=psf_sigma_mm)[0]
    strong = np.zeros(jw.owner.size, bool)
    strong[nb_p[Sn0 > JOINT_NEIGHBOUR_LEVEL]] = True
    if strong.any():
        keep = ~strong
        remap = np.cumsum(keep) - 1
        pair_ok = keep[nb_p]
        jw = Windows(jw.rows[keep], jw.cols[keep], jw.owner[keep])
        nb_p, nb_k = remap[nb_p[pair_ok]], nb_k[pair_ok]
        if nb_p.size == 0:
            return sel, at, info, a, n_pix
        neighbours = Windows(jw.rows[nb_p], jw.cols[nb_p], nb_k)
    starts = np.flatnonzero(np.concatenate(([True], jw.owner[1:] != jw.owner[:-1])))
    if ahead is None:
        y = np.asarray(pixels, dtype=float)[jw.rows, jw.cols]
        S, Sx, Sy = model_reusing(model, T_F_from_I, q, tan, jw, pixels.shape, pixel_spacing_mm, slice_thickness_mm,
                                   thickness_samples, exact, at_crossing, psf_sigma_mm)
    else:  # at_crossing was drawn on the joint windows before the strong pixels left
        S, Sx, Sy = at_crossing[1]
        if strong.any():
            S, Sx, Sy, y = S[keep], Sx[keep], Sy[keep], y[keep]
    for n_pass in range(JOINT_PASSES):
        if n_pass == 0:
            # the same neighbours' pixels (less the strong ones) at the same fitted positions: the same model
            Sn = Sn0[pair_ok] if strong.any() else Sn0
        else:
            Sn = section_model(model, T_F_from_I, fitted_at, tan, neighbours, pixel_spacing_mm, slice_thickness_mm,
                               thickness_samples, exact, psf_sigma_mm=psf_sigma_mm)[0]
        nb_level = np.bincount(nb_p, gain[nb_k] * Sn, y.size)  # the neighbours' signal in each pixel (in order)
        if rician_sigma > 0:  # E[y] = R(a S + n): fit (R(a0 S + n) - R(n)) / a0 to y - (R(n) - R(0))
            M, Mx, My, lift = rician_model(S, Sx, Sy, gain[jw.owner], nb_level, rician_sigma)
            sel_j, shift, info_j, a_j, n_pix_j = _linear_fit(M, Mx, My, y - lift, jw.owner, starts, K, sel,
                                                             noise_sigma)
        else:
            sel_j, shift, info_j, a_j, n_pix_j = _linear_fit(S, Sx, Sy, y - nb_level, jw.owner, starts, K, sel,
                                                             noise_sigma)
        if sel_j.size < sel.size:
            break  # a tube the separate fit located would be lost: keep what is there
        fitted_at[sel_j] = q[sel_j] + shift
        gain[sel_j] = a_j
        sel, at, info, a, n_pix = sel_j, fitted_at.copy(), info_j, a_j, n_pix_j
    return sel, at, info, a, n_pix


def model_reusing(model, T_F_from_I, q, tan, win: Windows, shape, pixel_spacing_mm, slice_thickness_mm: float,
                   thickness_samples: int, exact: bool, drawn=None, psf_sigma_mm: float = 0.0):
    """:func:`section_model` at ``q`` on ``win``, taking the pixels ``drawn`` = ``(windows, (S, Sx, Sy))`` already
    has (drawn at the same ``q``, pose and settings) from it: each pixel's value depends on that pixel alone."""
    if drawn is None:
        return section_model(model, T_F_from_I, q, tan, win, pixel_spacing_mm, slice_thickness_mm,
                             thickness_samples, exact, psf_sigma_mm=psf_sigma_mm)
    old, old_S = drawn
    H, W = shape
    key_old = (old.owner * H + old.rows) * W + old.cols  # ascending as built: owners ascending, boxes row-major
    key = (win.owner * H + win.rows) * W + win.cols
    order = None if np.all(key_old[1:] > key_old[:-1]) else np.argsort(key_old, kind="stable")
    sorted_old = key_old if order is None else key_old[order]
    at = np.minimum(np.searchsorted(sorted_old, key), max(key_old.size - 1, 0))
    have = sorted_old[at] == key if key_old.size else np.zeros(key.size, bool)
    src = at[have] if order is None else order[at[have]]
    out = tuple(np.empty(key.size) for _ in range(3))
    for o, v in zip(out, old_S):
        o[have] = v[src]
    new = np.flatnonzero(~have)
    if new.size:
        fresh = section_model(model, T_F_from_I, q, tan, Windows(win.rows[new], win.cols[new], win.owner[new]),
                              pixel_spacing_mm, slice_thickness_mm, thickness_samples, exact, psf_sigma_mm=psf_sigma_mm)
        for o, v in zip(out, fresh):
            o[new] = v
    return out


def blur_step(S, Sx, Sy, Sv, y, own, starts, K: int, todo, noise_sigma: float,
              floor_mm2: float = 0.0) -> tuple[float, float, float]:
    """``(dv, information, chi2)``: the change of the point spread's variance (mm^2) the windows' pixels ``y`` ask
    for, and its information (mm^-4), from the per-window least squares ``y = b + a S + (a dx) Sx + (a dy) Sy +
    (a dv) Sv`` (``Sv``: the model's derivative in the variance) pooled over the tubes ``todo``, each weighted by
    its information on ``dv``: blur widens every section alike, so one value holds for the slice; ``chi2``: the
    tubes' own values' scatter about it over their noise and ``floor_mm2`` (what the section model's own error puts
    between them), per degree of freedom."""
    X = np.stack([np.ones_like(S), S, Sx, Sy, Sv, y])
    n = X.shape[0]
    ii, jj = np.triu_indices(n)
    sums = np.zeros((K, ii.size))
    sums[own[starts]] = np.add.reduceat(X[ii] * X[jj], starts, axis=1).T
    full = np.zeros((K, n, n))
    full[:, ii, jj] = sums
    full[:, jj, ii] = sums
    N, rhs = full[todo, :5, :5], full[todo, :5, 5]
    scale = np.sqrt(np.einsum("kii->ki", N)) + 1e-300  # (a window's own scale: a singular one shows in its inverse)
    Nn = N / scale[:, :, None] / scale[:, None, :]
    ok = np.abs(np.linalg.det(Nn)) > 1e-12 if todo.size else np.zeros(0, bool)
    if not np.any(ok):
        return 0.0, 0.0
    N, rhs = N[ok], rhs[ok]
    Ninv = np.linalg.inv(N)
    theta = np.einsum("kij,kj->ki", Ninv, rhs)
    a, c = theta[:, 1], theta[:, 4]
    var_c = Ninv[:, 4, 4] * max(noise_sigma, 1e-12) ** 2
    w = np.where((a > 0) & (var_c > 0), a * a / np.where(var_c > 0, var_c, 1.0), 0.0)
    if not w.sum() > 0:
        return 0.0, 0.0, 0.0
    own_dv = c / np.where(a > 0, a, 1.0)
    dv = float(np.sum(w * own_dv) / w.sum())
    n = int(np.count_nonzero(w))
    spread = 1.0 / np.where(w > 0, w, np.inf) + floor_mm2 ** 2
    chi2 = float(np.sum((w > 0) * (own_dv - dv) ** 2 / spread)) / (n - 1) if n > 1 else 0.0
    return dv, float(w.sum()), chi2


def _linear_fit(S, Sx, Sy, y, own, starts, K: int, todo, noise_sigma: float):
    """Per tube least squares ``y = b + a S + (a dx) Sx + (a dy) Sy`` from sums over each window.

    Returns ``(tubes fitted, shift (n, 2) mm, information (n, 2, 2), gain (n,), pixels per tube (K,))``.
    """
    # (14, P), a product per row: 1, S, Sx, Sy, y written in, then the pairwise products of rows 1-4 (_PROD_I,
    # _PROD_J) at once; summed over each window (add.reduceat sums a row's segment as it sums a column's)
    prods = np.empty((_PROD_ROW.size, S.size))
    prods[0] = 1.0
    prods[1], prods[2], prods[3], prods[4] = S, Sx, Sy, y
    np.multiply(prods[_PROD_I], prods[_PROD_J], out=prods[5:])
    sums = np.zeros((K, _PAIR_I.size))
    sums[own[starts]] = np.add.reduceat(prods, starts, axis=1).T[:, _PROD_ROW]
    # (the normal matrix's diagonal: sums 0, 4, 7, 9; rows taken with np.take: 2-d fancy indexing costs more)
    n_pix = np.rint(sums[:, 0]).astype(int)
    s_todo = np.take(sums, todo, axis=0)
    sel = todo[(n_pix[todo] >= 8) & (s_todo[:, 4] > 0) & (s_todo[:, 7] + s_todo[:, 9] > 0)]
    s_sel = np.take(sums, sel, axis=0)
    N = np.take(s_sel, _SYM, axis=1)  # (n, 4, 4)
    try:
        Ninv = np.linalg.inv(N)
    except np.linalg.LinAlgError:  # one singular window: invert one by one
        Ninv = np.zeros((sel.size, 4, 4))
        for i in range(sel.size):
            try:
                Ninv[i] = np.linalg.inv(N[i])
            except np.linalg.LinAlgError:
                Ninv[i] = np.nan
    theta = np.einsum("kij,kj->ki", Ninv, s_sel[:, 10:14])
    a = theta[:, 1]
    blk = Ninv[:, 2:4, 2:4]
    det = blk[:, 0, 0] * blk[:, 1, 1] - blk[:, 0, 1] * blk[:, 1, 0]
    ok = (a > 0) & np.isfinite(det) & (det > 0)
    if not ok.all():
        sel, theta, a, blk, det = sel[ok], theta[ok], a[ok], blk[ok], det[ok]
    # the shift (x, y) mm, and its information: (a / sigma)^2 times the inverse of its block of N^-1
    inv_blk = np.swapaxes(blk[:, ::-1, ::-1], 1, 2) * _ADJUGATE_SIGN  # [[d, -b], [-c, a]] of [[a, b], [c, d]]
    info = inv_blk / det[:, None, None] * ((a / max(noise_sigma, 1e-12)) ** 2)[:, None, None]
    return sel, theta[:, 2:4] / a[:, None], info, a, n_pix
