"""A verified pose or none: the last check before the solver says ``ok``.

The solver fits a pose to the blob centres it chose; a wrong pose can fit a
subset of them well (a slice through an end face, a wrong pixel spacing, a
mirror pattern). So the pose is proved against the image itself, slice by
slice (:func:`verify_fit`):

1. **Envelope**: the found plane passes the design's plane checks
   (:func:`chic_register.model.envelope.plane_status`, the code behind
   ``chic-design check``'s tilt limits) for the slice's pixel size and
   thickness: no tube crossed twice, no two sections merged. A tube the plane
   misses (a slice through an end face) is allowed: the rest must verify.
2. **Every predicted tube appears where predicted, with its size and shape**:
   the model is rendered at the pose by the simulator's partial-volume
   renderer (:func:`chic_register.imaging.render.render_tubes`) tube by tube in a
   window around its section; its fluid level is fitted to the pixels
   (``pixels = background + gain * section + gain' * neighbours``). A tube
   whose gain is below :data:`PRESENT_FRACTION` of the matched tubes' or not
   :data:`PRESENT_SIGMA` noise sigmas above zero is missing; the residual
   energy left by the section must stay below what a :data:`POSITION_TOL_PX`
   misplacement leaves (:func:`shape_tolerance`), plus noise, and the shift
   of the section that best explains its residual (:func:`section_shift`)
   must stay within :data:`SHIFT_TOL_PX`: an elongated section predicted a
   few pixels along its length from where it is leaves less residual energy
   than the disc-based tolerance allows.
3. **Missing tubes** are flagged (``missing_tubes`` of the slice result) when
   the section lies well inside the body (an unfilled channel or a bubble);
   a missing tube whose section the pose puts near an end face is a refusal:
   there a wrong pose and a cut tube look alike.
4. **Nothing bright unexplained on the tubes' circle**: a detected blob not
   explained by the model, lying where the plane meets the circle of tube
   centres inside the body, may be a tube of another pose: the slice is
   solved again without each blob the pose uses, and those poses are rivals
   (6.). Outside the envelope, beside a missing tube, or with more than
   :data:`MAX_STRAYS` such blobs, the pattern is not the one the pose says:
   a refusal.
5. **Pixel spacing**: the sections seen must have the size and aspect the
   pose predicts; a stretch of the image along rows or columns (a wrong
   ``--pixel-spacing``) shows as an anisotropic scale of every section
   (:data:`SPACING_TOL`, or three standard errors of its estimate if larger:
   from the tubes' scatter or from their pixel noise, whichever is larger).
   The section positions are asked the same question (:func:`stretch_test`):
   a pose tilted to absorb a stretch leaves a residual pattern that a
   stretch explains and noise does not (alike along both axes, a scale: a
   print that shrank looks the same, and the refusal says so); a
   significant one is refused above 2 %, or when fitting it moves the pose
   by more than a third of the trust limits (a small isotropic stretch turns
   a tilted slice by about ``s cot(tilt)``).
6. **Rivals**: a distinct rival pose (the solver's other hypotheses, the
   pose turned about the axis by each near-symmetry of the straight tubes,
   and a second copy of the pattern in the blobs the pose leaves over, a
   motion ghost) that explains the pixels nearly as well makes the slice
   ambiguous: "nearly" is within the noise and the model error
   (:data:`MODEL_FLOOR`); a rival that falls back onto the pose when given
   the pose's own section fit is none (:mod:`chic_register.verify.rivals`).
7. **Precision**: the predicted 3-sigma error must be within the trust
   limits (:func:`pose_precision`). Its estimate comes from the fit's own
   residual scatter, so a damaged image whose tubes fit worse than its
   noise predicts widens it: it is the last net for a wrong pose that
   passed the tests above. The covariance from the pixel noise is held to
   the same limits once the pose is found
   (:func:`~chic_register.fit.checks.check_noise_precision`): a lucky small
   scatter does not make a pose more precise than its pixels allow.

Every threshold is in units of what the image resolves (pixels, noise sigma,
the section's own size); each has its reason beside it.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from chic_register.detect.blobs import Blobs, median
from chic_register.detect.detected import DetectedSlice
from chic_register.detect.noise import correlation_inflation, noise_correlation_axes
from chic_register.errors import ImprecisePose, NoLock, SliceRefused
from chic_register.fit.checks import (
    PRECISION_SIGMAS,
    STRETCH_MOVE_SHARE,
    STRETCH_P,
    anisotropic_stretch,
    pose_precision,
    position_precision,
    stretch_test,
    twist_covariance,
    weakest_rotation_text,
)
from chic_register.fit.scatter import Scatter
from chic_register.imaging.psf import blurred_windows, fit_psf
from chic_register.model.envelope import plane_status
from chic_register.model.pose import invert, slice_angles
from chic_register.model.tube_model import plane_crossings, section_extent
from chic_register.model.tubes import sample_centreline
from chic_register.verify.rivals import check_rivals, slice_contenders
from chic_register.verify.windows import (
    MODEL_FLOOR,
    aspect_error,
    fit_window,
    section_shift,
    shape_excess,
    tube_windows,
    window_spread,
)

#: A present tube's fitted fluid level, as a share of the median of the tubes the solver matched. A correctly
#: placed section (partial volume and slab smear are in the model) gives ~1 at any SNR above a few; a section
#: predicted where the image has background gives ~0 and one predicted half off its blob ~0.5.
PRESENT_FRACTION = 0.5
#: ... and that level must be this many noise sigmas (of the gain estimate) above zero.
PRESENT_SIGMA = 5.0
#: How far (pixels) a section may sit from where the pose predicts it before its shape counts as wrong: the
#: solver's own RMS limit (SolveOptions.max_rms_px) plus the fast mode's centroid bias at curved, clipped sections.
POSITION_TOL_PX = 0.75
#: A section seen further than this (pixels) from where the pose predicts it is not explained by the pose: the
#: section fit's own limit (SolveOptions.section_max_shift_px). Correct locks read 0.05 px (median) to 0.9 px (worst
#: of 139, hunt seed 3); a pose fitted to half-blobs of elongated sections read 1.5-2.1 px at four tubes.
SHIFT_TOL_PX = 1.0
#: ... beyond this many standard errors of the shift's estimate (a faint or small section locates itself poorly).
SHIFT_SIGMAS = 4.0
#: Anisotropic scale between the sections seen and predicted above which the pixel spacing is called wrong.
#: A 3 mm tube is 6 px across at 0.5 mm: the moment estimate of its width is good to ~1 %; 4 % leaves room for
#: the rendered model's error and slab smear and still catches a 5 % spacing error.
SPACING_TOL = 0.04
#: Standard error of the median of the tubes' aspects against that of their plain mean (the median's asymptotic
#: sqrt(pi / 2)): the spacing test's tolerance from the sections' pixel noise.
MEDIAN_SE = math.sqrt(math.pi / 2)
#: A stretch whose smaller axis is at least this share of its larger, with the same sign, is a scale of the whole
#: image (or of the print) rather than a wrong spacing along one axis: the refusal says so.
ISOTROPIC_SHARE = 0.5
#: Sections farther than this from an end face (in section lengths) are "well inside the body": a tube missing
#: there is an unfilled channel, not a sign of a wrong pose.
END_CLEARANCE_SECTIONS = 1.0
#: A pixel belongs to a predicted section where the rendered fluid fraction exceeds this ...
SECTION_LEVEL = 0.1
#: ... and a detected blob is explained by the pose when this share of its footprint does.
EXPLAINED_SHARE = 0.3
#: Blob widths the verification will model when the sections look wider than drawn (real images: point spread,
#: partial volume, fluid spread in a printed channel make blobs 0.7-2.5x the tube): the Gaussian point spread
#: sigmas tried, in tube radii (0.15 r barely widens a section; 2 r is a blob ~2.7x the tube's width), the best
#: refined between its neighbours (:func:`chic_register.imaging.psf.fit_psf`).
PSF_SIGMAS_RADII = (0.15, 0.25, 0.35, 0.5, 0.7, 1.0, 1.4, 2.0, 2.8)
#: A fitted point spread below this (sigma, pixels) is no blur the image can show: the sharp model's refusal stands
#: (in the wide-blob hunt a 0.3 px "blur" turned a marginal shape refusal into a pose 0.52 deg off).
PSF_MIN_PX = 0.5
#: More detected blobs than this on the tubes' circle that the pose does not explain: the pattern is not the pose's
#: (up to this many, each gets its rival poses, :func:`_stray_rivals`, and the pixels decide).
MAX_STRAYS = 2
@dataclass(frozen=True)
class SliceCheck:
    """What the verification saw in one slice: tubes found present, missing (flagged) and the spacing scale."""

    present: tuple[str, ...]
    missing: tuple[str, ...]
    spacing_scale: tuple[float, float]
    envelope: str
    merged: tuple[str, ...] = ()
    canvas: np.ndarray = None  # the model image at the pose (fluid fraction)
    level: float = 1.0  # fitted fluid level
    noise_sigma: float = 0.0
    psf_px: float = 0.0  # Gaussian point spread (sigma, pixels: the mean of rows' and columns') the model was blurred by
    strays: tuple[int, ...] = ()  # detected blobs on the tubes' circle inside the body that the pose leaves unexplained
    psf_rc_px: tuple = (0.0, 0.0)  # the point spread's sigma along rows and along columns (pixels that are not square)
    offsets_mm: tuple = ()  # per present tube alone in its window: (its section's distance from the pose's, its SE) mm


def shape_tolerance(radius_px: float) -> float:
    """Residual energy (share of the section's energy) left by a section misplaced by ``POSITION_TOL_PX``.

    Shifting a partial-volume disc of radius r px by d px changes about a
    one-pixel band along its rim by ``d`` of the fluid level: energy ``~2 pi r d^2``
    against the disc's ``pi r^2``, i.e. ``2 d^2 / r``.
    """
    return 2.0 * POSITION_TOL_PX ** 2 / max(radius_px, 1.0) + MODEL_FLOOR


def verify_slice(geom, model, T_F_from_I: np.ndarray, pixels: np.ndarray, spacing, thickness_mm: float,
                 blobs: Blobs, assignment: np.ndarray, source: str, *,
                 check_envelope: bool = True, psf_px: float | None = None, check_aspect: bool = True) -> SliceCheck:
    """Prove one slice's pose against its pixels; :class:`NoLock` with the reason, else what was seen.

    ``psf_px``: the point spread's sigma (pixels) when a fit to the pixels found it
    (:mod:`chic_register.fit.blurred`); else it is fitted here when the sharp model fails.
    ``check_aspect``: refuse sections wider along one image axis than the other (a wrong
    pixel spacing); off when the tube positions already rule out such a stretch
    (:func:`positions_rule_out_stretch`).
    """
    rs, cs = (float(v) for v in spacing)
    px = max(rs, cs)
    ang = slice_angles(T_F_from_I)
    where = f"depth {ang.depth_mm:.1f} mm, tilt {ang.tilt_deg:.1f} deg"
    envelope, merged = "ok", ()
    if check_envelope:
        st = plane_status(geom, ang.depth_mm, ang.tilt_deg, ang.azimuth_deg, px, thickness_mm)
        if st.twice:
            raise NoLock(f"{source}: the pose ({where}) is outside the design's usable envelope: tube(s) "
                         f"{', '.join(st.twice)} cross the slice twice", {"envelope": f"tube_crosses_twice:{st.twice[0]}"})
        # the envelope's merge rule: sections closer than a pixel cannot be located apart; they are no evidence
        # of the pose's precision (pose_precision leaves them out)
        merged = tuple(sorted({t for pair in st.merged for t in pair}))
        envelope = st.failure or "ok"
    shape = np.asarray(pixels).shape
    sigma = max(float(blobs.noise_sigma), 1e-12)
    L = model.length_mm
    q, tan, zF, _ = plane_crossings(model, T_F_from_I, margin_mm=5.0)
    half_len = section_extent(model, tan, thickness_mm)[0]

    def assess(wins, canvas, psf_px):
        fits = {}
        for w in wins:
            f = fit_window(pixels, w)
            if f is not None:
                fits[w.k] = (w, *f)
        matched = [k for k in fits if assignment[k] >= 0]
        gains = np.array([fits[k][1][1] for k in matched])
        if gains.size == 0 or not median(gains) > 0:
            raise NoLock(f"{source}: the rendered model at the pose ({where}) does not match the pixels of the "
                         f"tubes it was fitted to", {"n_tubes": len(matched)})
        level = median(gains)
        present, missing, cut_missing, offsets = [], [], [], []
        scales, aspect_se = [], []
        for k, (w, coef, y, fit) in fits.items():
            own = w.own.ravel()
            a = float(coef[1])
            energy = float(own @ own)
            se = sigma / math.sqrt(max(energy, 1e-12))
            tid = model.ids[k]
            if a < PRESENT_FRACTION * level or a < PRESENT_SIGMA * se:
                tz = max(abs(float(tan[k, 2])), 1e-3)
                clear = min(zF[k], L - zF[k]) - END_CLEARANCE_SECTIONS * (half_len[k] * math.sqrt(1 - tz * tz) + 0.5 * model.diameter_mm[k])
                (missing if clear > 0 else cut_missing).append(tid)
                continue
            # shape: the residual over the section (own support grown by a pixel), beyond noise and model error
            hh, ww = w.own.shape
            # judged against this tube's own fluid level when it is brighter than the median (rods differ: fill,
            # bubbles, coil); a dimmer one as before, against the median (never a stricter test)
            excess, chi_tol, sup = shape_excess(w, y, fit, sigma, max(a, level))
            r_px = 0.5 * float(model.diameter_mm[k]) / px
            if excess > shape_tolerance(r_px) + chi_tol:
                raise NoLock(f"{source}: tube {tid}'s section does not have the shape and place the pose ({where}) "
                             f"predicts (residual {excess:.2f} of its energy; allowed {shape_tolerance(r_px) + chi_tol:.2f})",
                             {"tube": tid, "shape_residual": round(excess, 3)})
            shift, shift_se = section_shift(w, y, coef, sigma)
            if shift > SHIFT_TOL_PX + SHIFT_SIGMAS * shift_se:
                raise NoLock(f"{source}: tube {tid}'s section lies {shift:.1f} px from where the pose ({where}) "
                             f"predicts it", {"tube": tid, "shift_px": round(shift, 3)})
            present.append(tid)
            if tid not in merged and w.others.max() < 0.05:  # (a neighbour's overlap would bias its place)
                offsets.append((shift * px, shift_se * px))
            # second moments of the section seen vs predicted (pixels), tubes with no neighbour in the window
            if w.others.max() < 0.05:
                obs = np.clip((y - coef[0]), 0.0, None).reshape(hh, ww) * sup.reshape(hh, ww)
                mod = (fit - coef[0]).reshape(hh, ww) * sup.reshape(hh, ww)
                so, sm = window_spread(obs), window_spread(mod)
                if so is not None and sm is not None:
                    scales.append(np.sqrt(so / sm))
                    # (every pixel of the support counts as noisy, those clipped at zero too: at low SNR the clip
                    # biases the aspect along an elongated support, and counting them covers that bias; with only
                    # the unclipped ones, hunt slices with the right spacing read 4-6 % stretched)
                    aspect_se.append(aspect_error(obs, sup.reshape(hh, ww), so, sigma))
        if cut_missing:
            raise NoLock(f"{source}: tube(s) {', '.join(cut_missing)} predicted near an end face at the pose ({where}) "
                         f"are not in the image: a cut tube and a wrong pose look alike there",
                         {"missing_tubes": cut_missing})
        scale = (1.0, 1.0)
        if len(scales) >= 3:
            s = np.array(scales)  # (n, 2): row, col scale seen / predicted
            ratio = s[:, 1] / s[:, 0]
            mean = median(ratio)
            each = np.asarray(aspect_se)  # (n,) each tube's aspect error from its pixel noise
            noise_se = MEDIAN_SE * math.sqrt(float(np.sum(each ** 2))) / len(each)  # of their (unweighted) median
            se = max(float(np.std(ratio) / math.sqrt(len(ratio))), noise_se)  # the tubes' scatter, or their noise
            tol = max(SPACING_TOL, 3 * se)
            scale = (median(s[:, 0]), median(s[:, 1]))
            if abs(mean - 1.0) > tol and check_aspect:
                raise NoLock(f"{source}: the tube sections are {abs(mean - 1) * 100:.0f} % "
                             f"{'wider' if mean > 1 else 'narrower'} along the columns than along the rows relative to "
                             f"the pose's prediction: is the pixel spacing ({rs:g}, {cs:g}) mm right?",
                             {"spacing_ratio": round(mean, 4)})
        strays = _unexplained(model, T_F_from_I, blobs, assignment, canvas, (rs, cs), geom.body)
        # a stray blob beside a missing tube is the signature of a wrong pose (the tube is there, elsewhere)
        if strays and (envelope != "ok" or len(strays) > MAX_STRAYS or missing):
            r, c = blobs.centres_rc[strays[0]]
            raise NoLock(f"{source}: a bright blob at pixel ({r:.0f}, {c:.0f}) lies where the tubes run, inside "
                         f"the body, where the pose ({where}) predicts no tube",
                         {"blob_rc": [round(float(r), 1), round(float(c), 1)]})
        psf_rc = (float(psf_px), float(psf_px)) if np.ndim(psf_px) == 0 else tuple(float(v) for v in psf_px)
        return SliceCheck(tuple(present), tuple(missing), scale, envelope, merged, canvas, level, sigma,
                          0.5 * (psf_rc[0] + psf_rc[1]), strays=tuple(strays), psf_rc_px=psf_rc,
                          offsets_mm=tuple(offsets))

    wins, canvas = tube_windows(geom, model, T_F_from_I, shape, (rs, cs), float(thickness_mm))
    try:
        return assess(wins, canvas, 0.0)
    except NoLock as exc:
        # what a blur explains: a section's shape, the level of the sections, their second moments (a blur widens a
        # section more across its width than along its length: the aspect test misreads it as a spacing error)
        if not ({"shape_residual", "shift_px", "n_tubes", "spacing_ratio"} & set(exc.detail)) or not PSF_SIGMAS_RADII:
            raise
        if envelope != "ok":  # a blurred model is weaker evidence: only where the design's envelope holds
            raise
        # the blobs may be wider than the tubes drawn (point spread, partial volume, fluid in a printed channel):
        # fit a Gaussian point spread to the matched sections and judge the blurred model by the same rules
        r_px = 0.5 * median(model.diameter_mm) / px
        # the windows reach three sigmas of the widest blur tried (of the blur given, when a pixel fit found it)
        reach_px = 3.0 * (PSF_SIGMAS_RADII[-1] * r_px if psf_px is None else float(np.max(psf_px)))
        wide, wide_canvas = tube_windows(geom, model, T_F_from_I, shape, (rs, cs), float(thickness_mm),
                                     margin_px=2.0 + math.ceil(reach_px))
        def misfit(w):  # the squared residual over the whole window: the same pixels for every blur tried
            f = fit_window(pixels, w)
            return math.inf if f is None else float(np.sum((f[1] - f[2]) ** 2))

        # the point spread is round in millimetres: in pixels that are not square it is not (sigma along rows, columns)
        r_mm = r_px * px
        if psf_px is not None:  # found by a fit to the pixels (chic_register.fit.blurred)
            psf = (float(psf_px), float(psf_px)) if np.ndim(psf_px) == 0 else tuple(float(v) for v in psf_px)
        else:
            psf = fit_psf(wide, {int(k) for k in np.flatnonzero(assignment >= 0)},
                          [(f * r_mm / rs, f * r_mm / cs) for f in PSF_SIGMAS_RADII], misfit)
        if psf is None or max(psf) < PSF_MIN_PX:  # no blur the pixels can show: the sharp model's verdict stands
            raise
        try:
            return assess(*blurred_windows(wide, wide_canvas, psf), psf)
        except NoLock:
            raise exc from None


@functools.lru_cache(maxsize=8)
def tube_tracks_xy(model) -> np.ndarray:
    """Every tube centreline's points seen along z of F (M, 2), 1 mm apart: where a slice can meet a tube."""
    return np.concatenate([sample_centreline(t, 1.0)[:, :2] for t in model.tubes])


def _unexplained(model, T_F_from_I, blobs: Blobs, assignment, canvas, spacing, body=None) -> list[int]:
    """Indices of the detected blobs the model does not explain that sit where tubes run, inside the body.

    Where tubes run: on the circle of tube centres (a round body), or, in a
    square or box frame, within a tube diameter of a tube centreline seen
    along z (a Z-frame's faces, an N-localizer's plates). A blob
    is explained when :data:`EXPLAINED_SHARE` of its footprint lies on a
    predicted section (``canvas`` > :data:`SECTION_LEVEL`): split halves and
    edges of predicted sections are.
    """
    rs, cs = spacing
    used = {int(i) for i in assignment if i >= 0}
    R = T_F_from_I[:3, :3]
    o = T_F_from_I[:3, 3]
    r_lo = float(model.axis_radius_mm.min() - model.diameter_mm.max())
    r_hi = float(model.axis_radius_mm.max() + model.diameter_mm.max())
    on = canvas > SECTION_LEVEL
    walls = body is not None and body.shape != "annulus"
    grow = float(model.diameter_mm.max())
    out = []
    for i, (r, c) in enumerate(blobs.centres_rc):
        if i in used:
            continue
        p = R @ np.array([c * cs, r * rs, 0.0]) + o
        if not 0.0 <= p[2] <= model.length_mm:
            continue
        if walls:
            if float(np.min(np.hypot(*(tube_tracks_xy(model) - p[:2]).T))) > grow:
                continue
        elif not r_lo <= math.hypot(p[0], p[1]) <= r_hi:
            continue
        if i < len(blobs.footprints):
            r0, c0, mask = blobs.footprints[i]
            cover = on[r0:r0 + mask.shape[0], c0:c0 + mask.shape[1]]
            if cover.shape == mask.shape and cover[mask].mean() >= EXPLAINED_SHARE:
                continue
        out.append(i)
    return out


#: The tube positions rule out a stretch of the image along one axis when they measure it to within this share of
#: the stretch the sections' aspect shows (three standard errors), and see none of it.
STRETCH_RESOLUTION_SHARE = 1.0 / 3.0


def positions_rule_out_stretch(model, fit, xys, Ss, aspect_stretch: float) -> bool:
    """Do the tube positions show the image is not stretched by ``aspect_stretch`` (the relative difference of the
    column and row scales the sections' second moments read)? True when the positions measure that difference
    with a standard error under :data:`STRETCH_RESOLUTION_SHARE` of it and find it within three standard errors of
    zero: a frame whose rods span the image (an N-localizer, a Z-frame) pins both axes' scales, and its
    sections' aspect is then the point spread's, not the spacing's. A small fiducial reads a stretch as a tilt:
    its positions cannot rule one out, and the aspect test stands."""
    diff, se = anisotropic_stretch(model, fit, xys, Ss)
    if not (math.isfinite(diff) and math.isfinite(se) and se > 0):
        return False
    return 3 * se <= STRETCH_RESOLUTION_SHARE * abs(aspect_stretch) and abs(diff) <= 3 * se


def _check_stretch(model, fit, xys, Ss, opts, slices, scale_fitted: bool) -> None:
    """:class:`NoLock` naming the axis when the tube positions fit a stretch of the image (a wrong pixel spacing,
    :func:`stretch_test`) beyond ``opts.max_scale_error`` (2 %), or one that moves the pose by more than a third of
    the trust limits unless ``scale_fitted``: the pose is fitted with the scale afterwards (``opts.fit_scale``, a
    pose of several slices fitted to positions: :mod:`chic_register.pipeline.scaling`; one slice alone reads an
    image's stretch as a tilt).

    A stretch alike along both axes (:data:`ISOTROPIC_SHARE`) is a scale: a
    wrong spacing, a scanner's gradient calibration or a print of another
    size than its file (a print that shrank looks like a spacing declared
    too small) look the same; the reason says so, and which spacing would
    register that scale."""
    scale, _, p, (moved_mm, moved_deg) = stretch_test(model, fit, xys, Ss)
    moves = moved_mm > STRETCH_MOVE_SHARE * opts.trust_tre_mm or moved_deg > STRETCH_MOVE_SHARE * opts.trust_rot_deg
    too_large = float(np.max(np.abs(scale))) > opts.max_scale_error
    # a scale within the tolerance is fitted with the pose afterwards (chic_register.fit.scale), not refused
    if not (p < STRETCH_P and (too_large or (moves and not scale_fitted))):
        return
    sx, sy = (float(v) for v in scale)
    detail = {"stretch": [round(sx, 4), round(sy, 4)], "stretch_p": float(p)}
    test = f"F test p = {p:.1g}; it moves the pose by {moved_mm:.2f} mm, {moved_deg:.2f} deg"
    if sx * sy > 0 and min(abs(sx), abs(sy)) >= ISOTROPIC_SHARE * max(abs(sx), abs(sy)):
        s = 0.5 * (sx + sy)
        spacings = {tuple(float(v) for v in sl.pixel_spacing_mm) for sl in slices}
        hint = ""
        if len(spacings) == 1:  # x scales the columns' spacing, y the rows' (xy = (col, row) * spacing)
            rs, cs = spacings.pop()
            hint = (f"; a pixel spacing of {rs * (1 + sy):.5g} x {cs * (1 + sx):.5g} mm (row, col) registers that "
                    f"scale (--pixel-spacing for a plain image)")
        size = "smaller" if s > 0 else "larger"  # positions that fit better scaled up: the fiducial seen is smaller
        raise NoLock(f"the tube positions fit best with the image scaled {100 * s:+.2f} % along both axes ({test}): "
                     f"the pixel spacing or the scanner's gradient calibration is off by that much, or the printed "
                     f"fiducial is that much {size} than its geometry file says; check the spacing and the print"
                     f"{hint}", detail)
    axis = "columns (x)" if abs(sx) >= abs(sy) else "rows (y)"
    worst = sx if abs(sx) >= abs(sy) else sy
    if too_large:
        raise NoLock(f"the tube positions fit best with the image stretched {100 * worst:+.1f} % along its {axis} "
                     f"({test}): the pixel spacing looks wrong; check --pixel-spacing or the file's PixelSpacing",
                     detail)
    raise NoLock(f"the tube positions fit best with the image stretched {100 * worst:+.1f} % along its {axis} "
                 f"({test}), within the {100 * opts.max_scale_error:g} % a scanner's gradient calibration explains, "
                 f"but this slice alone cannot tell that stretch from a tilt: register several slices or a volume (fitted "
                 f"together, they measure it)", detail)


def section_model_error_mm(checks: list[SliceCheck]) -> float:
    """The model error (mm per coordinate) of the verified sections' places: the scatter of their offsets from the
    pose's crossings (:attr:`SliceCheck.offsets_mm`) beyond their pixel noise, robust
    (:class:`~chic_register.fit.scatter.Scatter`); 0 with fewer than three sections. A simulation puts them within
    about twice their noise; real Z-frame slices put them 0.05-0.7 mm off, 10-25 times it."""
    rows = [o for c in checks for o in c.offsets_mm if math.isfinite(o[1])]
    if len(rows) < 3:
        return 0.0
    d, se = np.array(rows).T
    return Scatter.of(d * d, se).model_error_mm


def verify_fit(geom, model, fit, rivals, seen: list[DetectedSlice], opts, precision=None,
               name_slice: bool = False, psf_px: float | None = None,
               precision_sigmas: float = PRECISION_SIGMAS) -> list[SliceCheck]:
    """Verify a solved pose (a ``solve._Fit``) in every slice, and that no distinct rival verifies as well.

    ``rivals``: per slice, the other refined hypotheses of that slice alone
    (``solve._Fit`` in the slice's own scanner frame, as ``fit``);
    ``precision``: the pose's 1-sigma ``(TRE mm, rotation deg)`` when the
    pose was fitted to the pixels (:mod:`chic_register.fit.blurred`), else
    from the positions' residuals (:func:`pose_precision`), within the trust
    limits at ``precision_sigmas`` of it; ``name_slice``: a
    series' slices that fail their own checks raise :class:`SliceRefused`
    naming them all (a volume's registration leaves them out). Raises
    :class:`NoLock` with the first failure; returns one :class:`SliceCheck` per slice.
    """
    slices = [d.slice for d in seen]
    xys = [d.xy_mm for d in seen]
    Ss = [d.T_scanner_from_image for d in seen]
    blob_sets = [d.blobs for d in seen]
    scale_fitted = opts.fit_scale and precision is None and len(seen) > 1  # (chic_register.pipeline.scaling)
    out, contenders, refused = [], [], []
    for j, (sl, S, b) in enumerate(zip(slices, Ss, blob_sets)):
        T_F_from_I = fit.T_F_from_scanner @ S
        try:
            check = verify_slice(geom, model, T_F_from_I, np.asarray(sl.pixels), sl.pixel_spacing_mm,
                                 float(sl.slice_thickness_mm), b, fit.assignments[j], sl.source, psf_px=psf_px)
        except NoLock as exc:
            if "shift_px" in exc.detail:  # sections off where the pose puts them: a wrong spacing says why, if it is one
                _check_stretch(model, fit, xys, Ss, opts, slices, scale_fitted)
            check = None
            if "spacing_ratio" in exc.detail and positions_rule_out_stretch(model, fit, xys, Ss,
                                                                            exc.detail["spacing_ratio"] - 1.0):
                try:  # the sections' aspect is the image's point spread (an MR phase-encoding blur), not its spacing
                    check = verify_slice(geom, model, T_F_from_I, np.asarray(sl.pixels), sl.pixel_spacing_mm,
                                         float(sl.slice_thickness_mm), b, fit.assignments[j], sl.source,
                                         psf_px=psf_px, check_aspect=False)
                except NoLock as again:
                    exc = again
            if check is not None:
                contenders += slice_contenders(model, fit, rivals[j] if rivals is not None else (), check.strays,
                                               xys[j], S, j, sl, opts)
                out.append(check)
                continue
            if not name_slice or len(slices) < 2:
                raise
            refused.append((j, exc.reason))
            continue
        contenders += slice_contenders(model, fit, rivals[j] if rivals is not None else (), check.strays,
                                       xys[j], S, j, sl, opts)
        out.append(check)
    if refused:
        raise SliceRefused(refused[0][1], {"n_refused": len(refused)}, refused)
    # a rival gets the section fit when the pose had it (not one fitted through a blurred or a centroid model)
    section_pose = precision is None and opts.section_fit and not opts.centroid_model
    check_rivals(geom, model, fit, contenders, out, seen, opts, section_pose)
    if precision is not None:  # a pose fitted through a blurred model is weaker evidence: only inside the envelope
        outside = [(j, f"{sl.source}: the pose fitted to the blurred sections lies outside the design's usable "
                       f"envelope ({c.envelope}): wide blobs there cannot be told apart")
                   for j, (sl, c) in enumerate(zip(slices, out)) if c.envelope != "ok"]
        if outside and name_slice and len(outside) < len(slices):  # a volume: those slices are left out
            raise SliceRefused(outside[0][1], {"n_refused": len(outside)}, outside)
        if outside:
            raise NoLock(outside[0][1], {"envelope": out[outside[0][0]].envelope})
    _check_stretch(model, fit, xys, Ss, opts, slices, scale_fitted)
    px = min(max(sl.pixel_spacing_mm) for sl in slices)
    tre, rot = precision or pose_precision(model, fit, Ss, px, exclude=[c.merged for c in out])
    noise_only, m = (tre, rot), 0.0
    if precision is not None:  # the pixel fit's covariance holds its pixels' noise, not where the sections really lie
        m = section_model_error_mm(out)
        if m > 0:
            tre_m, rot_m = position_precision(model, fit, Ss, m, exclude=[c.merged for c in out])
            tre, rot = math.hypot(tre, tre_m), math.hypot(rot, rot_m)
    # noise shared between neighbouring pixels (an interpolated or smoothed image) makes every estimate that takes
    # them as independent too optimistic: widened by the worst slice's correlation factor
    f = max(correlation_inflation(noise_correlation_axes(np.asarray(sl.pixels), b.footprints))
            for sl, b in zip(slices, blob_sets))
    tre, rot = tre * f, rot * f
    k = precision_sigmas
    tre_tol, rot_tol = opts.trust_tre_mm, opts.trust_rot_deg
    if k * tre > tre_tol or k * rot > rot_tol:
        why = "a tilted slice or several parallel slices are more precise"
        if m > 0 and k * f * noise_only[0] <= tre_tol and k * f * noise_only[1] <= rot_tol:  # the model error decides
            why = (f"its sections lie {m:.2f} mm (per coordinate) from where the pose puts them, beyond their noise: "
                   f"the scanner's distortion or the print, which several slices or a volume average out")
        C = None if precision is not None else twist_covariance(model, fit, Ss, px, exclude=[c.merged for c in out])
        weakest = f"; {weakest_rotation_text(C * f * f, fit)}" if C is not None and k * rot > rot_tol else ""
        raise ImprecisePose(f"the pose is not precise enough to trust: {k:g} sigma of its predicted error is "
                            f"{k * tre:.2f} mm at the frame centre and {k * rot:.2f} deg (limits {tre_tol:g} mm, "
                            f"{rot_tol:g} deg{weakest}; {why}; --trust MM DEG sets the limits)",
                            {"sigma_tre_mm": round(tre, 4), "sigma_rot_deg": round(rot, 4),
                             **({"sections_model_error_mm": round(m, 4)} if m > 0 else {}),
                             "refused_T_scanner_from_fiducial": invert(fit.T_F_from_scanner).tolist()})
    return out


