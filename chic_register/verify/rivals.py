"""Rival poses: the other answers a slice could have, each of which the pixels must reject by a clear margin.

The verification (:mod:`chic_register.verify.pixels`) proves a pose against
the image; here is its last question, whether another pose explains the
pixels nearly as well. The rivals are the first-guess stage's other refined
hypotheses, the pose turned about the axis by each near-symmetry of the
straight tubes (:func:`_turned_rivals`), and, when a bright blob on the
tubes' circle is left unexplained, the slice solved again without each
blob the pose matched (:func:`stray_rivals`), and the slice solved again
on the blobs the pose leaves over (a second copy of the pattern, a motion
ghost: :func:`second_copy_rivals`). In a series a rival is
refined on all slices' blobs, each distinct one compared once, and the
evidence of all slices adds up (:func:`check_rivals`). A rival that the
pixels do not reject gets the pose's own refinement, the section fit,
before it is called one: started there, it may fall back onto the pose
(:func:`falls_onto_pose`).
"""

from __future__ import annotations

import functools
import math

import numpy as np

from chic_register.detect.detected import DetectedSlice
from chic_register.detect.filters import dilate
from chic_register.errors import NoLock
from chic_register.fit.accuracy import section_refine
from chic_register.fit.lock import lock_slice
from chic_register.fit.refine import match_gate_mm, refine
from chic_register.imaging.psf import gaussian_blur
from chic_register.model.pose import near_prior, slice_angles
from chic_register.model.tube_model import poses_distinct
from chic_register.util.lapack import lstsq
from chic_register.verify.windows import MODEL_FLOOR, tube_windows

#: A rival pose must explain the pixels worse by this many noise variances (a log-likelihood margin of half of
#: it) plus the model's own error, else the slice is ambiguous.
RIVAL_MARGIN = 50.0
#: Straight tubes this close in angle after a turn about the axis count as mapped onto each other (the turn is a
#: near-symmetry whose pose is tried as a rival).
SYMMETRY_TOL_DEG = 3.0
#: A rival whose section fit ends within this share of the trust limits of the pose (their 1 sigma, as
#: fit_checks.STRETCH_MOVE_SHARE) has fallen back onto the pose: the same answer, not a rival.
FALLBACK_SHARE = 1.0 / 3.0
#: Fewest matched tubes of a rival worth comparing: fewer than the solver needs to answer (a pose that explains
#: the blobs it matches and predicts no tube the image lacks can disprove one that matches more but predicts
#: sections that are not there), more than the three that fix a pose.
RIVAL_MIN_TUBES = 4

def slice_contenders(model, fit, rivals, strays, xy: np.ndarray, S: np.ndarray, j: int, sl, opts) -> list:
    """The distinct rival poses (``T_F_from_scanner``) of slice ``j`` that fit its blobs within the solver's limits.

    ``rivals``: the slice's other refined hypotheses; ``strays``: unexplained
    blobs on the tubes' circle (their rivals are sought too).
    """
    px = float(max(sl.pixel_spacing_mm))
    turned = _turned_rivals(model, fit.T_F_from_scanner, xy, S, px)
    if strays:
        turned += stray_rivals(model, xy, S, fit.assignments[j], opts, px)
    turned += second_copy_rivals(model, xy, S, fit.assignments[j], opts, px)
    out = []
    for other in list(rivals) + turned:
        if (other.n_matched < RIVAL_MIN_TUBES or other.rms_mm > opts.max_rms_px * px
                or not poses_distinct(other.T_F_from_scanner, fit.T_F_from_scanner, model)
                or not near_prior(other.T_F_from_scanner, opts)):  # the user's prior orientation excludes it
            continue
        out.append(other.T_F_from_scanner)
    return out


class BetterRival(NoLock):
    """A distinct rival explains the pixels better than the pose by more than the margin: the pose is the wrong one
    of two that fit the blob centres equally (a slice's mirrored tilt); ``T_F_from_scanner`` is the rival's."""

    def __init__(self, reason: str, T_F_from_scanner: np.ndarray, detail: dict | None = None):
        super().__init__(reason, detail)
        self.T_F_from_scanner = T_F_from_scanner


def check_rivals(geom, model, fit, contenders, checks, seen: list[DetectedSlice], opts, section_pose: bool = False) -> None:
    """:class:`NoLock` ("ambiguous") when a distinct rival explains the pixels of the slices nearly as well.

    A rival pose must explain every slice of a series nearly as well: the
    evidence of all slices adds up; a rival one slice offered is first
    refined on the blobs of all of them (it may fall back onto the pose).
    ``section_pose``: ``fit`` is the section fit's pose;
    a rival that explains the pixels nearly as well is then section-fitted
    too, and is no rival when that lands on the pose.
    """
    slices = [d.slice for d in seen]
    xys = [d.xy_mm for d in seen]
    Ss = [d.T_scanner_from_image for d in seen]
    if len(slices) > 1 and contenders:
        gate = match_gate_mm(model, max(float(max(sl.pixel_spacing_mm)) for sl in slices))
        refined = [refine(model, xys, Ss, T, gates_mm=(gate, 0.6 * gate)) for T in contenders]
        # (on all slices' blobs a rival must still fit within the solver's own RMS limit, as a single slice's must)
        px_min = min(float(max(sl.pixel_spacing_mm)) for sl in slices)
        contenders = [r.T_F_from_scanner for r in refined
                      if r.n_matched >= opts.min_tubes and r.rms_mm <= opts.max_rms_px * px_min
                      and poses_distinct(r.T_F_from_scanner, fit.T_F_from_scanner, model)
                      and near_prior(r.T_F_from_scanner, opts)]
    # one comparison per distinct rival (a volume's slices offer the same turned pose dozens of times)
    unique = []
    for T in contenders:
        if all(poses_distinct(T, U, model) for U in unique):
            unique.append(T)
    for T_rival in unique:
        scores = [_compare_rival(geom, model, check, T_rival @ S, sl) for check, S, sl in zip(checks, Ss, slices)]
        gap, margin = sum(g for g, _ in scores), sum(m for _, m in scores)
        if gap < -margin:  # the rival, not the pose, is what the pixels show
            raise BetterRival(f"{slices[0].source}: ambiguous: a distinct pose explains the pixels better than the "
                              f"pose found (residual smaller by {-gap:.3g}; margin {margin:.3g})", T_rival,
                              {"n_tubes": int(fit.n_matched)})
        if gap < margin and not (section_pose and falls_onto_pose(model, fit, T_rival, seen, opts)):
            a = slice_angles(T_rival @ Ss[0])
            where = slices[0].source if len(slices) == 1 else f"{len(slices)} slices"
            raise NoLock(f"{where}: ambiguous: a distinct pose (depth {a.depth_mm:.1f} mm, tilt {a.tilt_deg:.1f} deg) "
                         f"explains the image{'s' if len(slices) > 1 else ''} nearly as well (residual larger by "
                         f"{gap:.3g}; margin needed {margin:.3g})", {"n_tubes": int(fit.n_matched)})


def falls_onto_pose(model, fit, T_rival: np.ndarray, seen: list[DetectedSlice], opts) -> bool:
    """Does the section fit started at a rival pose (``T_F_from_scanner``) end on the pose ``fit``?

    The pose was refined on the tube sections themselves
    (:func:`~chic_register.fit.accuracy.section_refine`), a rival only on the
    blob centres; the pixels may tell the two apart only by a few per cent of
    their energy (a slice near normal to the axis, its tilt mirrored). Given
    the same refinement, a rival in the pose's basin (1-10 deg away in the
    hunt) falls back within :data:`FALLBACK_SHARE` of the trust limits, and
    was never a second answer; one that stays away is (a distinct rival that
    verifies by every check of the pose, as the hunt's mirrored tilts do).
    """
    slices = [d.slice for d in seen]
    xys = [d.xy_mm for d in seen]
    Ss = [d.T_scanner_from_image for d in seen]
    gate = match_gate_mm(model, min(float(max(sl.pixel_spacing_mm)) for sl in slices))
    start = refine(model, xys, Ss, T_rival, gates_mm=(gate, 0.6 * gate))
    fine = section_refine(model, start, seen, opts)
    return fine is not None and not poses_distinct(fine.T_F_from_scanner, fit.T_F_from_scanner, model,
                                              FALLBACK_SHARE * opts.trust_tre_mm, FALLBACK_SHARE * opts.trust_rot_deg)


def stray_rivals(model, xy: np.ndarray, S: np.ndarray, assignment: np.ndarray, opts, pixel_mm: float) -> list:
    """Poses that put a tube on a stray blob: the slice solved again without each blob the pose matched.

    A bright blob on the tubes' circle that the pose leaves unexplained may be
    a tube of a different pose (one that leaves out a blob this pose uses).
    The first-guess stage, seeing every blob, may not have offered it; with
    each matched blob removed in turn, it does. Each such fit is a rival for
    :func:`_compare_rival`.
    """
    out = []
    for m in sorted({int(i) for i in assignment if i >= 0}):
        try:
            fits, _ = lock_slice(model, np.delete(xy, m, axis=0), S, opts, pixel_mm)
        except NoLock:
            continue
        out.extend(fits)
    return out


def second_copy_rivals(model, xy: np.ndarray, S: np.ndarray, assignment: np.ndarray, opts,
                        pixel_mm: float) -> list:
    """Poses fitted to the blobs the pose leaves unmatched: a second copy of the whole pattern.

    A motion ghost (the object repeated along the phase-encoding direction,
    dimmer) or a second fiducial in the field of view shows every tube
    twice; the first-guess stage fits one copy, and which one is not the
    brightest by design. With :data:`~chic_register.pipeline.register.SolveOptions.min_tubes`
    or more blobs left over, the slice is solved again on them alone; each
    such fit is a rival for :func:`_compare_rival`, where the copy that
    explains less of the pixels (the ghost) loses.
    """
    unused = np.ones(len(xy), bool)
    unused[assignment[assignment >= 0]] = False
    rest = np.flatnonzero(unused)  # (np.setdiff1d's unique imports numpy.ma: ~40 ms of a one-shot solve)
    if rest.size < opts.min_tubes:
        return []
    try:
        fits, _ = lock_slice(model, xy[rest], S, opts, pixel_mm)
    except NoLock:
        return []
    return fits


def _turned_rivals(model, T_F_from_scanner: np.ndarray, xy: np.ndarray, S: np.ndarray, pixel_mm: float) -> list:
    """The pose turned about the fiducial axis by each near-symmetry of its straight tubes, each refined.

    A turn that maps three or more axial tubes onto axial tubes (within
    :data:`SYMMETRY_TOL_DEG`) is a pose the first-guess stage may never have
    offered (the 90 deg turns of four diametric tubes, say); refined against
    the same blobs, it is a rival for :func:`_compare_rival`.
    """
    gate = match_gate_mm(model, pixel_mm)
    out = []
    for d in _symmetry_turns(model):
        c, s_ = math.cos(d), math.sin(d)
        Rz = np.array([[c, -s_, 0, 0], [s_, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
        out.append(refine(model, [xy], [S], Rz @ T_F_from_scanner, gates_mm=(2 * gate, 0.6 * gate),
                          iters_per_gate=3, final_iters=2))
    return out


@functools.lru_cache(maxsize=16)
def _symmetry_turns(model) -> tuple[float, ...]:
    """The turns (rad) about the axis that map three or more axial tubes onto axial tubes (a geometry's own:
    computed once per tube model, which is hashed by identity)."""
    ang = model.angle_rad[model.axial]
    tol = math.radians(SYMMETRY_TOL_DEG)
    turns = []
    for a in ang:
        for b in ang:
            d = float((b - a + math.pi) % (2 * math.pi) - math.pi)
            if abs(d) < tol or any(abs(d - t) < tol for t in turns):
                continue
            moved = (ang[:, None] + d - ang[None, :] + math.pi) % (2 * math.pi) - math.pi
            if int(np.sum(np.min(np.abs(moved), axis=1) < tol)) >= 3:
                turns.append(d)
    return tuple(turns)


def _compare_rival(geom, model, check, T_F_from_I_rival: np.ndarray, sl) -> tuple[float, float]:
    """How much worse a distinct rival pose explains a slice's pixels than the pose: ``(gap, margin)``.

    Both model images (the rival's rendered as the pose's) are fitted to the
    pixels over the union of their sections grown by a pixel (``b + a model``);
    ``gap`` is the rival's residual sum of squares less the pose's, and
    ``margin`` what it must exceed: :data:`RIVAL_MARGIN` noise variances plus
    the model error (:data:`~chic_register.verify.pixels.MODEL_FLOOR` of the
    signal energy). A margin from the pose's own misfit (0.5-3 %) locked 15
    more hunt slices, but a print's scale error the pose absorbs leaves little
    misfit: 0.1-0.2 % of scale then locked slices 0.51-0.54 deg off that the
    fixed floor refuses (``benchmarks/hunt_print.py --kind scale``), so the
    floor stays fixed.
    """
    pixels = np.asarray(sl.pixels, float)
    _, rival = tube_windows(geom, model, T_F_from_I_rival, pixels.shape, tuple(float(v) for v in sl.pixel_spacing_mm),
                        float(sl.slice_thickness_mm), canvas_only=True)
    rival = gaussian_blur(rival, check.psf_rc_px)  # drawn as the pose's model was
    region = dilate((check.canvas > 0.02) | (rival > 0.02), 1)
    y = pixels[region]
    sse = []
    for img in (check.canvas, rival):
        A = np.stack([np.ones(y.size), img[region]], axis=1)
        coef = lstsq(A, y)[0]
        r = y - A @ coef
        sse.append(float(r @ r))
    signal = check.level ** 2 * float(np.sum(check.canvas[region] ** 2))
    return sse[1] - sse[0], RIVAL_MARGIN * check.noise_sigma ** 2 + MODEL_FLOOR * signal
