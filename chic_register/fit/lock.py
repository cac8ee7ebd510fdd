"""One slice's lock search: first guesses (:mod:`chic_register.guess.hypotheses`) turned into refined, ranked fits.

:func:`lock_slice` takes the paper's closed form when the layout allows it,
else the generic first guess; :func:`_refine_guesses` refines the guesses
that line up the most tubes, and any close rival for the ambiguity check.
"""

from __future__ import annotations

import numpy as np

from chic_register.detect.blobs import median
from chic_register.errors import NoLock
from chic_register.fit.refine import (
    assign_blobs,
    match_gate_mm,
    rank_fits,
    refine,
    reject_outliers,
    unexplained_tubes,
)
from chic_register.guess.ellipse import fit_ellipse_robust
from chic_register.guess.generic import family_hypotheses, parallel_family
from chic_register.guess.hypotheses import ellipse_layout, initial_hypotheses
from chic_register.model.pose import invert, near_prior
from chic_register.model.tube_model import (
    TubeModel,
    crossings_memo,
    inside_mask,
    poses_distinct,
)
from chic_register.options import SolveOptions

#: A slice with more candidate sections than this many per tube (a CT's phantom grid, bone specks) is first guessed
#: from its :data:`BRIGHT_PER_TUBE` brightest candidates per tube: the tubes of one fiducial hold one fill, so they are
#: among the brightest sections, and every triple of hundreds of candidates is too many to try (the generic guess
#: then samples them at random). The fits are refined on every candidate all the same.
MANY_PER_TUBE = 4
BRIGHT_PER_TUBE = 2


def lock_slice(model: TubeModel, xy: np.ndarray, S: np.ndarray, opts: SolveOptions, pixel_mm: float,
               contrast: np.ndarray | None = None):
    """Refined hypotheses of one slice, best first, and the ellipse (or None). Raises NoLock if there are none.

    First guesses come from the paper's closed form when the layout allows it
    (:func:`~chic_register.guess.hypotheses.ellipse_layout`), else, or when that
    yields no acceptable fit, from the generic stage
    (:func:`~chic_register.guess.generic.family_hypotheses`). Every guess gets a
    short refinement; the best, and any distinct rival as good as it, are then
    refined to convergence. With a prior orientation (``opts.prior``), guesses
    and fits farther from it are dropped. ``contrast`` (N,), each candidate's
    contrast, orders the generic stage's guesses in a slice with many
    candidates (:data:`MANY_PER_TUBE`).
    """
    if xy.shape[0] < opts.min_tubes:
        raise NoLock(f"found {xy.shape[0]} candidate tube cross-sections; need at least {opts.min_tubes}",
                     {"n_candidates": int(xy.shape[0])})
    gate = match_gate_mm(model, pixel_mm)
    limit = opts.max_rms_px * pixel_mm
    fits, ell = [], None
    if ellipse_layout(model):
        radius = median(model.axis_radius_mm)
        ell_fit = fit_ellipse_robust(xy, radius, max_tilt_deg=opts.max_tilt_deg,
                                     tol_mm=max(0.08 * radius, 1.5 * pixel_mm))
        if ell_fit is not None:
            ell, inl = ell_fit
            hyps = initial_hypotheses(model, xy[inl], ell, max_hypotheses=opts.max_hypotheses)
            fits = _refine_guesses(model, xy, S, hyps, opts, pixel_mm, gate)
    if not fits or fits[0].n_matched < opts.min_tubes or fits[0].rms_mm > limit:
        if parallel_family(model) is None:
            if not fits:
                raise NoLock("the geometry has no family of three parallel straight tubes that are not in one "
                             "plane, which the generic first guess needs, and no ellipse of tube centres "
                             "was found", {"n_candidates": int(xy.shape[0])})
        else:
            hyps = []
            n_tubes = len(model.ids)
            if contrast is not None and len(contrast) == xy.shape[0] and xy.shape[0] > MANY_PER_TUBE * n_tubes:
                bright = np.argsort(-np.asarray(contrast, float), kind="stable")[:BRIGHT_PER_TUBE * n_tubes]
                hyps = family_hypotheses(model, xy[np.sort(bright)], gate_mm=gate, max_tilt_deg=opts.max_tilt_deg,
                                         max_hypotheses=6 * opts.max_hypotheses)
            hyps += family_hypotheses(model, xy, gate_mm=gate, max_tilt_deg=opts.max_tilt_deg,
                                      max_hypotheses=6 * opts.max_hypotheses)
            extra = _refine_guesses(model, xy, S, hyps, opts, pixel_mm, gate)
            if ell is not None or ellipse_layout(model):
                # a fallback where the closed form applies but found nothing: only a fit that explains
                # (nearly) every tube it puts in the slice, as the closed form's fits would
                extra = [f for f in extra if unexplained_tubes(f) <= 1]
            fits = rank_fits(fits + extra, limit)
    if not fits:
        raise NoLock("the detected centres do not match the geometry's tube pattern",
                     {"n_candidates": int(xy.shape[0])})
    return fits, ell


def _refine_guesses(model: TubeModel, xy: np.ndarray, S: np.ndarray, hyps: list, opts: SolveOptions,
                    pixel_mm: float, gate: float) -> list:
    """Rank first guesses ``T_F_from_I`` by the tubes they line up, refine the best; fits best first."""
    S_inv = invert(S)
    # rank the guesses by how many tubes they line up before refining any
    scored = []
    for T in hyps:
        X = T @ S_inv
        if not near_prior(X, opts):
            continue
        hit = crossings_memo(model, np.asarray(T, dtype=float))  # plane_crossings' numbers, less its copies
        scored.append((int((assign_blobs(hit[0][:, :2], inside_mask(model, hit, 5.0), xy, gate) >= 0).sum()), X))
    scored.sort(key=lambda t: -t[0])

    def full(X):
        return refine(model, [xy], [S], X, gates_mm=(2 * gate, 0.6 * gate), iters_per_gate=3, final_iters=2)

    # refine in order until a fit explains at least as many tubes as any guess
    # still untried lines up; those rivals (for the ambiguity check) get a short
    # refinement first and a full one only if they come close
    fits = []
    limit = opts.max_rms_px * pixel_mm
    for count, X in scored:
        if fits and count < fits[0].n_matched and fits[0].rms_mm <= limit:
            break
        if fits:
            quick = refine(model, [xy], [S], X, gates_mm=(gate,), iters_per_gate=2, final_iters=0)
            if (quick.n_matched < fits[0].n_matched or quick.rms_mm > 2 * limit
                    or not poses_distinct(quick.T_F_from_scanner, fits[0].T_F_from_scanner, model)):
                fits.append(quick)
                continue
        fit = reject_outliers(model, [xy], [S], full(X), [pixel_mm], opts)
        if near_prior(fit.T_F_from_scanner, opts):
            fits = rank_fits(fits + [fit], limit)
    return fits
