"""Accuracy refinement: the locked pose refitted on better tube positions than the blob centroids.

The default mode fits each matched tube's section model to its pixels
(:func:`section_refine`, through :mod:`chic_register.fit.section`); the
centroid model (:func:`centroid_refine`) instead predicts each blob's
centroid as the detector measures it (:func:`centroid_offsets`), then
refines on template fits of the rendered sections (:func:`_template_refine`,
:func:`template_shifts`). Both render or model the sections at the pose, so
they run after a lock, never in the search for one.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from chic_register.detect.blobs import median, pixel_mm
from chic_register.detect.detected import DetectedSlice
from chic_register.detect.filters import dilate
from chic_register.errors import NoLock
from chic_register.fit.refine import (
    Fit,
    refine,
    scanner_crossing_jacobian,
    whitened_residuals,
)
from chic_register.fit.section import fit_sections
from chic_register.imaging.render import render_tubes
from chic_register.imaging.rician import rayleigh_sigma
from chic_register.model.pose import invert
from chic_register.model.tube_model import TubeModel, plane_crossings, section_extent

#: A fitted section disagrees with the pose the other sections give when its whitened residual (chi-square, 2 degrees
#: of freedom, under its own information) exceeds this (a 4e-6 tail) ...
SECTION_OUTLIER_CHI2 = 25.0
#: ... and this many times the median of the other matched sections' (a model error shared by every section, a
#: blurred or mis-scaled image, raises them all alike and drops none): a blob on the tubes' circle, a stripe, a
#: ghost or lost pixels over one section pull its position by a fraction of a pixel, which a clean section's noise
#: does not. Such a section is left out and the pose refitted on the rest (at most :data:`MAX_SECTION_OUTLIERS`).
SECTION_OUTLIER_RATIO = 10.0
MAX_SECTION_OUTLIERS = 2


def centroid_offsets(tubes, model: TubeModel, T_F_from_I: np.ndarray, assignment: np.ndarray, footprints,
                     pixel_spacing_mm, slice_thickness_mm: float, *, supersample: int = 5,
                     thickness_samples: int = 5, purity: bool = False):
    """Where the detector sees each matched tube, relative to its centreline crossing; (K, 2) image mm.

    The centre the detector reports is the intensity centroid of the blob's
    footprint, not the centreline crossing: a helix's section is curved, a
    section is clipped by the tube's end and a neighbour can spill into the
    footprint. So each matched tube's footprint (``footprints[assignment[k]]``
    = (row0, col0, mask), from :class:`~chic_register.detect.blobs.Blobs`) is
    rendered noise-free at the pose ``T_F_from_I`` (4x4) with every tube
    (``tubes``, the geometry's objects) that reaches it, by the simulator's
    exact partial-volume renderer over the slice thickness; the offset is
    that footprint's centroid minus the crossing. Zero for unmatched tubes.
    Returns ``(offsets (K, 2), purity (K,))``; with ``purity=True`` that is
    the share of the tube's own signal inside its footprint times the share
    of the footprint's signal that is the tube's own (1: a clean blob; less:
    a touching neighbour or a footprint split through the section, whose
    centre follows the pose only weakly), else ones.
    """
    q, tan, _, found = plane_crossings(model, T_F_from_I, margin_mm=5.0)
    K = q.shape[0]
    off = np.zeros((K, 2))
    pure = np.ones(K)
    rs, cs = (float(v) for v in pixel_spacing_mm)
    px = max(rs, cs)
    half_len, half_wid, u = section_extent(model, tan, slice_thickness_mm)
    render = {"pixel_spacing_mm": (rs, cs), "slice_thickness_mm": slice_thickness_mm,
              "supersample": supersample, "thickness_samples": thickness_samples}
    for k in np.flatnonzero(assignment >= 0):
        r0, c0, mask = footprints[int(assignment[k])]
        h, w = mask.shape
        centre = np.array([(c0 + (w - 1) / 2) * cs, (r0 + (h - 1) / 2) * rs])
        half = 0.5 * math.hypot(h * rs, w * cs) + 2 * px
        d = centre - q
        along = np.abs(np.einsum("ij,ij->i", d, u))
        across = np.abs(u[:, 0] * d[:, 1] - u[:, 1] * d[:, 0])
        near = np.flatnonzero(found & (along < half + half_len) & (across < half + half_wid))
        near = np.union1d(near, [k])
        img = render_tubes([tubes[i] for i in near], T_F_from_I, (h, w), center_px=(-float(r0), -float(c0)),
                           **render)
        wgt = np.where(mask, img, 0.0)
        total = wgt.sum()
        if total <= 0:
            pure[k] = 0.0
            continue
        r = (wgt.sum(axis=1) @ np.arange(h)) / total + r0
        c = (wgt.sum(axis=0) @ np.arange(w)) / total + c0
        off[k] = (c * cs - q[k, 0], r * rs - q[k, 1])
        if purity:
            # the tube alone, in a window holding its whole section and the footprint
            ex = abs(u[k, 0]) * half_len[k] + abs(u[k, 1]) * half_wid[k] + 2 * px
            ey = abs(u[k, 1]) * half_len[k] + abs(u[k, 0]) * half_wid[k] + 2 * px
            R0 = min(r0, int(math.floor((q[k, 1] - ey) / rs)))
            C0 = min(c0, int(math.floor((q[k, 0] - ex) / cs)))
            R1 = max(r0 + h, int(math.ceil((q[k, 1] + ey) / rs)) + 1)
            C1 = max(c0 + w, int(math.ceil((q[k, 0] + ex) / cs)) + 1)
            own = render_tubes([tubes[k]], T_F_from_I, (R1 - R0, C1 - C0), center_px=(-float(R0), -float(C0)),
                               **render)
            own_total = own.sum()
            own_in = float(np.where(mask, own[r0 - R0:r0 - R0 + h, c0 - C0:c0 - C0 + w], 0.0).sum())
            pure[k] = (own_in / own_total) * (own_in / total) if own_total > 0 else 0.0
    return off, pure


def template_shifts(tubes, model: TubeModel, T_F_from_I: np.ndarray, assignment: np.ndarray, pixels: np.ndarray,
                    footprints, pixel_spacing_mm, slice_thickness_mm: float, *, supersample: int = 5,
                    thickness_samples: int = 5, grow_px: int = 2, step_px: float = 0.1):
    """Where each matched tube's section lies in the image by a template fit; (K, 2) image mm from its crossing.

    The centroid of a footprint sums the noise of every pixel in it; a
    matched filter uses only the section's edges and is about twice as
    precise in white noise. So for each matched tube, the noise-free image of
    its section at the pose ``T_F_from_I`` (4x4), rendered by the
    simulator's partial-volume renderer like :func:`centroid_offsets`, is
    fitted to ``pixels`` (rows, cols) over the blob's footprint grown by
    ``grow_px`` (less the other blobs' footprints):
    ``I = b + a (T(x - d) + N(x))``, N the neighbouring tubes at the pose,
    linear in (b, a, a d) once ``T(x - d)`` is expanded to first order (the
    derivative from renders shifted by ``+-step_px``). The shift is small
    near the converged pose, and the caller iterates at the refitted pose.
    Returns ``(shift (K, 2) mm, gain a (K,), fitted (K,) bool)``: the
    template's own position is the crossing plus ``shift`` (no centroid
    bias); ``fitted`` is False for unmatched tubes (gain 0), degenerate fits
    (gain NaN) and fits without a positive gain.
    """
    q, tan, _, found = plane_crossings(model, T_F_from_I, margin_mm=5.0)
    K = q.shape[0]
    shift, gain, fitted = np.zeros((K, 2)), np.zeros(K), np.zeros(K, bool)
    rs, cs = (float(v) for v in pixel_spacing_mm)
    px = max(rs, cs)
    H, W = pixels.shape
    half_len, half_wid, u = section_extent(model, tan, slice_thickness_mm)
    render = {"pixel_spacing_mm": (rs, cs), "slice_thickness_mm": slice_thickness_mm,
              "supersample": supersample, "thickness_samples": thickness_samples}
    g = int(grow_px)
    for k in np.flatnonzero(assignment >= 0):
        i = int(assignment[k])
        fr0, fc0, fmask = footprints[i]
        r0, c0 = max(0, fr0 - g), max(0, fc0 - g)
        r1, c1 = min(H, fr0 + fmask.shape[0] + g), min(W, fc0 + fmask.shape[1] + g)
        h, w = r1 - r0, c1 - c0
        own = np.zeros((h, w), bool)
        own[fr0 - r0:fr0 - r0 + fmask.shape[0], fc0 - c0:fc0 - c0 + fmask.shape[1]] = fmask
        mask = dilate(own, g) if g > 0 else own.copy()
        for n, (or0, oc0, omask) in enumerate(footprints):
            if n == i or or0 >= r1 or oc0 >= c1 or or0 + omask.shape[0] <= r0 or oc0 + omask.shape[1] <= c0:
                continue
            a0, b0 = max(or0, r0), max(oc0, c0)
            a1, b1 = min(or0 + omask.shape[0], r1), min(oc0 + omask.shape[1], c1)
            other = omask[a0 - or0:a1 - or0, b0 - oc0:b1 - oc0]
            sub = mask[a0 - r0:a1 - r0, b0 - c0:b1 - c0]
            sub &= ~(other & ~own[a0 - r0:a1 - r0, b0 - c0:b1 - c0])
        centre = np.array([(c0 + (w - 1) / 2) * cs, (r0 + (h - 1) / 2) * rs])
        half = 0.5 * math.hypot(h * rs, w * cs) + 2 * px
        d = centre - q
        along = np.abs(np.einsum("ij,ij->i", d, u))
        across = np.abs(u[:, 0] * d[:, 1] - u[:, 1] * d[:, 0])
        near = [n for n in np.flatnonzero(found & (along < half + half_len) & (across < half + half_wid)) if n != k]

        def draw(tube_list, dr_px=0.0, dc_px=0.0):
            # the section moved by (dr, dc) pixels: the grid's origin moves the other way
            return render_tubes(tube_list, T_F_from_I, (h, w), center_px=(-float(r0) + dr_px, -float(c0) + dc_px),
                                **render)

        # composited as the image is: the brighter of the tube and its neighbours (touching sections overlap)
        # (forward differences: a derivative a little off costs a little precision, never bias, since the
        # residual vanishes at the true pose whatever the derivative)
        nbr = draw([tubes[n] for n in near]) if near else np.zeros((h, w))
        tpl = np.maximum(draw([tubes[k]]), nbr)
        dT_dr = (np.maximum(draw([tubes[k]], step_px), nbr) - tpl) / step_px
        dT_dc = (np.maximum(draw([tubes[k]], 0.0, step_px), nbr) - tpl) / step_px
        m = mask.ravel()
        A = np.stack([np.ones(int(m.sum())), tpl.ravel()[m], dT_dr.ravel()[m], dT_dc.ravel()[m]], axis=1)
        y = np.asarray(pixels[r0:r1, c0:c1], float).ravel()[m]
        try:
            coef, _, rank, _ = np.linalg.lstsq(A, y, rcond=None)
        except np.linalg.LinAlgError:
            continue
        gain[k] = coef[1] if rank == 4 else math.nan
        if not gain[k] > 0:
            continue
        # first order: a T(x - d) = a T(x) + (a d) . dT/dd
        shift[k] = (coef[3] / coef[1] * cs, coef[2] / coef[1] * rs)
        fitted[k] = True
    return shift, gain, fitted


def centroid_refine(model: TubeModel, tubes, fit: Fit, seen: list[DetectedSlice], opts) -> Fit:
    """Refit ``fit`` with the centroid model (:func:`centroid_offsets`).

    A fixed-point iteration: offsets at the current pose, refit, repeated
    until the pose moves less than 1e-4 (mm and rad) or ``centroid_iterations``
    times. Tubes whose blob is not clean (purity below
    ``centroid_min_purity``: a touching neighbour, a footprint split through
    the section) are left out while enough tubes remain: their centre
    follows the pose only weakly, which the fixed point follows slowly,
    and a split's boundary moves with the noise.
    """
    slices = [d.slice for d in seen]
    xys = [d.xy_mm for d in seen]
    Ss = [d.T_scanner_from_image for d in seen]
    blob_sets = [d.blobs for d in seen]
    assign = [a.copy() for a in fit.assignments]
    for it in range(opts.centroid_iterations):
        X0 = fit.T_F_from_scanner
        offs = []
        for j, (sl, S, b) in enumerate(zip(slices, Ss, blob_sets)):
            off, pure = centroid_offsets(
                tubes, model, fit.T_F_from_scanner @ S, assign[j], b.footprints, sl.pixel_spacing_mm,
                float(sl.slice_thickness_mm), supersample=opts.centroid_supersample,
                thickness_samples=opts.centroid_thickness_samples, purity=it == 0)
            offs.append(off)
            if it == 0:
                for k in np.argsort(pure):
                    if pure[k] >= opts.centroid_min_purity:
                        break
                    n_all = sum(int((a >= 0).sum()) for a in assign)
                    n_depth = sum(int(((a >= 0) & model.depth_coding).sum()) for a in assign)
                    if n_all <= opts.min_tubes or (model.depth_coding[k] and n_depth <= opts.min_depth_tubes):
                        continue
                    assign[j][k] = -1
        fit = refine(model, xys, Ss, fit.T_F_from_scanner, gates_mm=(), final_iters=6, assign0=assign,
                     offsets_mm=offs, strict_ends=False)
        d = invert(X0) @ fit.T_F_from_scanner
        if max(abs(d[:3, 3]).max(), abs(d[:3, :3] - np.eye(3)).max()) < 1e-4:
            break
    if opts.template_iterations > 0:
        fit = _template_refine(model, tubes, fit, assign, xys, Ss, slices, blob_sets, opts, offs)
    return fit


def _template_refine(model: TubeModel, tubes, fit: Fit, assign, xys, Ss, slices, blob_sets, opts,
                     centroid_offs) -> Fit:
    """Refit ``fit`` on template-fitted tube positions (:func:`template_shifts`), ``template_iterations`` times.

    Each matched tube's measurement becomes the position of its fitted
    template (crossing plus shift, offset zero); a tube whose template fit
    is degenerate keeps its centroid and centroid-model offset. Raises
    :class:`NoLock` when a template lands more than ``template_max_disagreement_px``
    from where the centroid model puts the tube, or fits with no positive
    gain: the blob is not the clean section the model expects.
    """
    for it in range(opts.template_iterations):
        X0 = fit.T_F_from_scanner
        new_xys, offs = [], []
        for j, (sl, S, b) in enumerate(zip(slices, Ss, blob_sets)):
            T_F_from_I = fit.T_F_from_scanner @ S
            a = assign[j]
            render = {"supersample": opts.centroid_supersample, "thickness_samples": opts.centroid_thickness_samples}
            thick = float(sl.slice_thickness_mm)
            shift, gain, ok = template_shifts(tubes, model, T_F_from_I, a, np.asarray(sl.pixels), b.footprints,
                                              sl.pixel_spacing_mm, thick, **render)
            matched = a >= 0
            if np.any(matched & (gain <= 0)):  # (NaN, a degenerate fit, keeps the centroid instead)
                k = int(np.flatnonzero(matched & (gain <= 0))[0])
                raise NoLock(f"{sl.source}: tube {model.ids[k]} matches a blob its template does not fit "
                             f"(gain {gain[k]:.3g})", {"n_tubes": int(matched.sum())})
            rest = np.where(ok, -1, a)
            if it == 0:  # the centroid model's last offsets (the pose has barely moved since)
                off = centroid_offs[j].copy()
            elif np.any(rest >= 0):
                off = centroid_offsets(tubes, model, T_F_from_I, rest, b.footprints, sl.pixel_spacing_mm, thick,
                                       **render)[0]
            else:
                off = np.zeros((a.size, 2))
            q = plane_crossings(model, T_F_from_I, margin_mm=5.0)[0]
            kk = np.flatnonzero(ok)
            xy = xys[j].copy()
            if it == 0 and kk.size:
                gap = np.linalg.norm(xy[a[kk]] - off[kk] - (q[kk] + shift[kk]), axis=1)
                limit = opts.template_max_disagreement_px * pixel_mm(sl)
                if gap.max() > limit:
                    k = int(kk[np.argmax(gap)])
                    raise NoLock(f"{sl.source}: tube {model.ids[k]}'s template fit is {gap.max():.3f} mm from its "
                                 f"centroid fit (limit {opts.template_max_disagreement_px:g} px)",
                                 {"n_tubes": int(matched.sum())})
            xy[a[kk]] = q[kk] + shift[kk]
            off[kk] = 0.0
            new_xys.append(xy)
            offs.append(off)
        fit = refine(model, new_xys, Ss, fit.T_F_from_scanner, gates_mm=(), final_iters=6, assign0=assign,
                     offsets_mm=offs, strict_ends=False)
        d = invert(X0) @ fit.T_F_from_scanner
        if max(abs(d[:3, 3]).max(), abs(d[:3, :3] - np.eye(3)).max()) < 1e-5:
            break
    return fit


#: A section's point spread is measured up to this many tube radii (sigma): blobs wider than that are the blurred
#: model's (:mod:`chic_register.fit.blurred`).
MAX_PSF_RADII = 0.5
#: The passes stop once the point spread's sigma moves by less than this share of a pixel.
SPREAD_DONE_PX = 0.02
#: The tubes' own point-spread steps may scatter about the slice's by this many times their noise and the model's
#: floor (:data:`~chic_register.fit.section.BLUR_FLOOR_PX2`; chi-square per degree of freedom): at most 14 (95 % below
#: 5.2) over 64 k-space slices of the printed body, noise-free to SNR 10, with or without a scanner's filter; 34 and
#: 166-208 at two wrong poses of damaged hunt slices (a distractor taken for a section), which a fitted spread made
#: pass, 110 deg and 0.7 deg off.
MAX_BLUR_CHI2 = 20.0


def section_refine(model: TubeModel, fit: Fit, seen: list[DetectedSlice], opts) -> Fit | None:
    """Refit ``fit`` on section-fitted tube positions (:func:`~chic_register.fit.section.fit_sections`).

    Up to ``section_iterations`` passes: fit every matched tube's section
    model at the current pose, then refit the pose on the fitted positions,
    each weighted by its information matrix. A tube whose section cannot be fitted
    (window too small, no positive gain) is left out, and so is one whose
    fitted section lies more than ``section_max_shift_px`` from where the
    pose predicts it or has less than half the median gain (not the clean
    section the model expects). Fewer than ``min_tubes`` clean sections
    (tubes in tissue, blobs much wider than the channels) return ``None``:
    the blob-centre pose then stands, and is verified like any other.

    Each slice's point spread is measured on the way (``opts.section_blur``): every exact pass also fits the
    change of its variance the sections' pixels ask for (:func:`~chic_register.fit.section.blur_step`), a
    Gauss-Newton step from none; the passes go on until neither the pose nor the spread moves. Where the
    sections disagree on it at the end (:data:`MAX_BLUR_CHI2`: not one blurred image of the tubes, as at a wrong
    pose or under tissue) the refinement is done again with sharp sections: a spread fitted to such sections
    would only make a wrong pose fit its pixels better.
    """
    slices = [d.slice for d in seen]
    xys = [d.xy_mm for d in seen]
    Ss = [d.T_scanner_from_image for d in seen]
    blob_sets = [d.blobs for d in seen]
    assign = [a.copy() for a in fit.assignments]
    wins = [None] * len(slices)  # each tube's pixels: chosen at the first pass, kept (the pose barely moves)
    px = min(pixel_mm(sl) for sl in slices)
    spread = [0.0] * len(slices)  # each slice's point-spread variance (mm^2)
    agree = [0.0] * len(slices)  # each slice's sections' agreement on it (the last exact pass's chi-square)
    start = fit
    limit = (MAX_PSF_RADII * 0.5 * median(model.diameter_mm)) ** 2
    exact = True
    for it in range(opts.section_iterations):
        X0 = fit.T_F_from_scanner
        new_xys, Ls, q_before = [], [], []
        spread_moved = 0.0  # how far a slice's point spread (sigma, mm) moved in this pass
        # a pass far from the fit's fixed point only has to bring the next one close: a coarser model (3 planes,
        # straight edges) and one Gauss-Newton step of the pose do for it; exact passes repeat until one moves
        # the tube crossings by less than section_done_px (its first-order fit is then exact to ~1e-3 px)
        for j, (sl, S, b) in enumerate(zip(slices, Ss, blob_sets)):
            a = assign[j]
            sf, wins[j] = fit_sections(model, X0 @ S, a, np.asarray(sl.pixels), sl.pixel_spacing_mm,
                                       float(sl.slice_thickness_mm), b.noise_sigma, footprints=b.footprints,
                                       thickness_samples=(opts.section_thickness_samples if exact
                                                          else min(3, opts.section_thickness_samples)),
                                       windows=wins[j], exact=exact,
                                       rician_sigma=rayleigh_sigma(b.background, b.noise_sigma) if opts.section_rician
                                       else 0.0, lost=sl.lost, psf_sigma_mm=math.sqrt(spread[j]),
                                       measure_blur=opts.section_blur and exact)
            q_before.append(sf.predicted_mm)
            if sf.blur_info > 0:
                agree[j] = sf.blur_chi2
                before = math.sqrt(spread[j])
                spread[j] = min(max(spread[j] + sf.blur_step_mm2, 0.0), limit)
                spread_moved = max(spread_moved, abs(math.sqrt(spread[j]) - before))
            info = sf.info  # a window too thin to locate the section both ways (lost pixels) is no measurement
            a00, a11 = info[:, 0, 0], info[:, 1, 1]
            ok = sf.fitted & (a00 > 0) & (a00 * a11 - info[:, 0, 1] * info[:, 1, 0] > 1e-9 * a00 * a11)
            if ok.any():  # a section far from where the locked pose puts it, or faint, is not the tube's
                shift = np.linalg.norm(sf.position_mm - sf.predicted_mm, axis=1)
                ok &= (shift <= opts.section_max_shift_px * pixel_mm(sl)) & (sf.gain >= 0.5 * median(sf.gain[ok]))
            a[(a >= 0) & ~ok] = -1
            k = np.flatnonzero(a >= 0)
            xy = xys[j].copy()
            xy[a[k]] = sf.position_mm[k]
            new_xys.append(xy)
            L = np.zeros_like(sf.info)
            L[k] = np.swapaxes(np.linalg.cholesky(sf.info[k]), 1, 2)
            Ls.append(L)
        n_all = sum(int((a >= 0).sum()) for a in assign)
        if n_all < opts.min_tubes:
            return None
        fit = refine(model, new_xys, Ss, X0, gates_mm=(), final_iters=6 if exact else 1, assign0=assign,
                     strict_ends=False, weights=Ls, tol=1e-5)  # (1e-5 rad, mm: far below the noise)
        fit = dataclasses.replace(fit, measurements=[(xy, L, float(b.noise_sigma))
                                                     for xy, L, b in zip(new_xys, Ls, blob_sets)])
        moved = 0.0  # how far the matched tubes' crossings moved in this pass (mm)
        for j, S in enumerate(Ss):
            k = np.flatnonzero(assign[j] >= 0)
            q0 = q_before[j][k]
            q1 = plane_crossings(model, fit.T_F_from_scanner @ S, margin_mm=1e-9)[0][k]
            moved = max(moved, float(np.max(np.linalg.norm(q1 - q0, axis=1), initial=0.0)))
        if exact and moved < opts.section_done_px * px and spread_moved < SPREAD_DONE_PX * px:
            break
        exact = moved < opts.section_close_px * px
    if opts.section_blur and max(agree) > MAX_BLUR_CHI2:
        return section_refine(model, start, seen, dataclasses.replace(opts, section_blur=False))
    return fit


def _whitened_sections(model: TubeModel, fit: Fit, assign, Ss, jacobian: bool = False):
    """``(keys, r, J)`` of every matched section at ``fit``: ``keys`` (n,) its index among the slices' tubes laid
    end to end, ``r`` (n, 2) its whitened residual ``L (predicted - fitted)`` under its section fit's information
    (``fit.measurements``), ``J`` (n, 2, 6) the whitened Jacobian of its crossing in the pose's scanner twist (None
    unless ``jacobian``)."""
    K = len(model.ids)
    keys, rs, Js = [], [], []
    for j, S in enumerate(Ss):
        a = assign[j]
        k = np.flatnonzero(a >= 0)
        if k.size == 0:
            continue
        q, tan, _, _ = plane_crossings(model, fit.T_F_from_scanner @ S, margin_mm=1e-9)
        rs.append(whitened_residuals(fit.measurements[j], q, a, k))
        keys.extend(j * K + k)
        if jacobian:
            J = scanner_crossing_jacobian(q[k], tan[k], S)
            Js.append(np.einsum("kij,kjl->kil", fit.measurements[j][1][k], J))
    r = np.concatenate(rs) if rs else np.zeros((0, 2))
    return np.asarray(keys, dtype=int), r, (np.concatenate(Js) if Js else None)


def section_chi2(model: TubeModel, fit: Fit, assign, Ss) -> np.ndarray:
    """Each matched tube's whitened residual ``|L (predicted - fitted)|^2`` under its section fit's information
    (``fit.measurements``), the slices' tubes laid end to end (``len(Ss) * K``); NaN for unmatched tubes."""
    keys, r, _ = _whitened_sections(model, fit, assign, Ss)
    out = np.full(len(Ss) * len(model.ids), np.nan)
    out[keys] = np.einsum("ki,ki->k", r, r)
    return out


def drop_section_outliers(model: TubeModel, fit: Fit, Ss, opts) -> Fit:
    """``fit`` (a :func:`section_refine` result) refitted without the sections that alone disagree with the
    others' pose (:data:`SECTION_OUTLIER_CHI2`, :data:`SECTION_OUTLIER_RATIO`), one at a time, up to
    :data:`MAX_SECTION_OUTLIERS`; never below ``min_tubes`` / ``min_depth_tubes``. ``fit`` itself when none does.

    Each time the section with the largest residual is the candidate, judged by its deleted residual: its
    chi-square against the pose refitted without it, over the median of the others' in that refit, both
    studentized (:func:`studentized_chi2`)."""
    if fit.measurements is None:
        return fit
    assign = fit.assignments
    xys = [m[0] for m in fit.measurements]  # the fitted positions and weights stay; only the tubes used change
    Ls = [m[1] for m in fit.measurements]
    for _ in range(MAX_SECTION_OUTLIERS):
        flat = section_chi2(model, fit, assign, Ss)
        if np.isfinite(flat).sum() <= opts.min_tubes:
            break
        worst = int(np.nanargmax(flat))
        j, k = divmod(worst, len(model.ids))
        n_depth = sum(int(((a >= 0) & model.depth_coding).sum()) for a in assign)
        if model.depth_coding[k] and n_depth <= opts.min_depth_tubes:
            break
        without = [a.copy() for a in assign]
        without[j][k] = -1
        refit = refine(model, xys, Ss, fit.T_F_from_scanner, gates_mm=(), final_iters=6, assign0=without,
                       strict_ends=False, weights=Ls, tol=1e-5)
        refit = dataclasses.replace(refit, measurements=fit.measurements)
        # judged against the pose the others give: a section that pulled the whole fit towards itself (a blob matched
        # in a tube's place) hides among raised residuals, and stands out once the fit no longer follows it
        deleted = studentized_chi2(model, refit, assign, Ss, worst)
        rest = np.delete(deleted, worst)
        rest = rest[np.isfinite(rest)]
        if not (deleted[worst] > SECTION_OUTLIER_CHI2 and deleted[worst] > SECTION_OUTLIER_RATIO * median(rest)):
            break
        assign, fit = without, refit
    return fit


def studentized_chi2(model: TubeModel, fit: Fit, assign, Ss, left_out: int) -> np.ndarray:
    """Each matched section's whitened residual at ``fit`` (a fit without section ``left_out``, an index into the
    slices' tubes laid end to end), as a chi-square with 2 degrees of freedom under the sections' own information:
    ``r^T (I - H)^-1 r`` for the sections the fit used (``H`` the 2x2 block of the hat matrix: a fitted section's
    residual is smaller than its noise, the more the fit leans on it) and ``e^T (I + P)^-1 e`` for the one left out
    (``P`` the pose's covariance through its Jacobian: its prediction carries the pose's error too). So the one left
    out and the rest are on the same footing. NaN for tubes not matched."""
    keys, r, J = _whitened_sections(model, fit, assign, Ss, jacobian=True)
    used = keys != left_out
    A = np.einsum("kil,kim->lm", J[used], J[used])
    C = np.linalg.pinv(A)
    out = np.full(len(Ss) * len(model.ids), np.nan)
    for n, key in enumerate(keys.tolist()):
        H = J[n] @ C @ J[n].T
        M = np.eye(2) + H if key == left_out else np.eye(2) - H
        vals, vecs = np.linalg.eigh(M)
        w = vecs.T @ r[n]
        out[key] = float(np.sum(w * w / np.maximum(vals, 1e-6)))
    return out
