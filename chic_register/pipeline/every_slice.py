"""Every slice the frame is in: one pose fitted to the blob centres of all of a volume's slices at once.

A real volume's slices each hold part of the frame: the end slices cut tubes
short, a mask or the field of view hides some, anatomy adds blobs. Solving
each slice alone and keeping those that pass a fixed residual limit throws
most of them away (a real scan's tubes sit 0.2-0.6 mm from any rigid model:
gradient non-linearity 150 mm from the isocentre, the print's tolerance).
:func:`register_every_slice` instead

1. locks a few slices alone (the ones whose blob count is closest to the
   geometry's tube count, from the middle of the stack out) only to find
   starting poses;
2. fits one pose to the centres of every slice at once, each blob assigned to
   the tube whose crossing is nearest (so a slice where some tubes are cut or
   missing still counts its visible tubes);
3. reads the scatter the data show: each blob centre's noise from the image
   (:func:`~chic_register.precision.uncertainty.centroid_covariance`) plus a
   model-error term estimated from the residuals themselves (:class:`Scatter`);
4. leaves out a blob, then a whole slice, whose residual that scatter cannot
   explain (a chi-square tail below :data:`OUTLIER_P`, shared over the slices),
   refits, and fits the image's scale with the pose (:mod:`~chic_register.fit.scale`);
5. refuses a model error beyond :data:`MODEL_ERROR_SHARE` of the channel
   diameter, a distinct pose that fits nearly as well, and an imprecise pose.

Slices left out are listed with their reason and their residual under the pose.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass

import numpy as np

from chic_register.detect.blobs import detect_blobs
from chic_register.detect.detected import DetectedSlice
from chic_register.detect.disc import disc_centroid, disc_contrast
from chic_register.detect.dropout import fill_slice_dropouts
from chic_register.detect.noise import slice_noise
from chic_register.errors import AmbiguousFit, NoLock
from chic_register.fit.checks import STRETCH_P, gamma_p
from chic_register.fit.lock import lock_slice
from chic_register.fit.refine import Fit, assign_blobs, match_gate_mm, refine
from chic_register.fit.scale import fit_scale
from chic_register.fit.scatter import Scatter
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.pose import invert, near_prior, rotation_deg, slice_angles
from chic_register.model.slices import Slice
from chic_register.model.symmetry import EXACT_SHARE, candidate_rotations, frame_symmetries
from chic_register.model.tube_model import TubeModel, plane_crossings, poses_distinct, prepare_geometry
from chic_register.options import SolveOptions
from chic_register.pipeline.detection import check_pixel_range, detect_slices
from chic_register.pipeline.joint import no_slice_locked
from chic_register.pipeline.results import Registration, SkippedSlice, build_registration
from chic_register.pipeline.scaling import scale_stage
from chic_register.precision.uncertainty import centroid_covariance, scatter_uncertainty, target_point

#: A slice counts in the joint fit with at least this many of its tubes found where the pose puts them: one or two
#: blobs near predicted crossings can be chance (anatomy, a neighbouring tube's smear).
MIN_SLICE_TUBES = 3
#: A blob, then a slice, is left out when the scatter cannot explain its residual at this tail probability, shared
#: (Bonferroni) over the blobs or slices tested: with ~100 blobs a correct one is dropped about once in 1000 volumes.
OUTLIER_P = 1e-3
#: The model error (the scatter beyond each centre's own noise) may reach this share of the channel diameter: real
#: scans show 0.2-0.6 mm for 3 mm rods (gradient non-linearity far from the isocentre, print and mounting tolerance);
#: a pose whose crossings miss the blob centres by a third of a channel on average is not the frame's.
MODEL_ERROR_SHARE = 1.0 / 3.0
#: :func:`~chic_register.detect.blobs.detect_blobs`' default smallest blob area, as a share of a channel's section.
MIN_AREA_FACTOR = 0.3
#: A slice where the joint pose finds blobs for fewer tubes than it puts in it is read again
#: (:func:`_with_faint_sections`) at most this many robust noise sigmas of its smoothed image above its median
#: (``noise_threshold_sigmas``): where anatomy far brighter than the frame fills part of the field of view (a
#: patient's thighs), Otsu's split falls between tissue and background, above the rods of a fading slab's end; noise
#: alone passes such a level with odds below 1e-15, so the level adds no candidate of noise.
SCAN_LEVEL_SIGMAS = 8.0
#: Slices locked alone to find starting poses, at most (each costs 5-200 ms; the joint fit does the rest).
MAX_LONE_LOCKS = 5
#: Rounds of the joint fit taken again at the scale its slices show (:func:`_joint_fit`): the first estimate, from
#: the slices a rigid pose keeps, may see only part of a large one.
SCALE_ROUNDS = 3
#: A slice left out is said to disagree when this many channel diameters around the joint pose's crossings hold
#: blobs of at least :data:`MIN_SLICE_TUBES` of its tubes (its frame is there, elsewhere).
WIDE_GATE_SHARE = 3.0
#: The share of the tube crossings a pose puts wholly inside its slices that must show a blob: a bubble, a dim or an
#: unfilled channel lose some (three of nine), a pose that lines up a subset of the frame's blobs loses half.
EXPLAINED_SHARE = 0.75
#: A pose outside the prior that matches this share more blob centres (and at least :data:`MIN_SLICE_TUBES` more)
#: than the best within it shows the frame is not mounted as the prior says.
OUTSIDE_SHARE = 0.1
#: A distinct pose matching at least as many blobs with a scatter within this factor of the best's is a rival the
#: data cannot rule out.
RIVAL_SCATTER_RATIO = 1.5
#: :func:`_robust_pose`: rounds of reweighting, and the Cauchy weight's scale in robust sigmas (95 % efficiency
#: for Gaussian errors).
ROBUST_ROUNDS = 5
CAUCHY_C = 2.385


@dataclass(frozen=True)
class JointFit:
    """A pose fitted to every slice's centres: the fit (over all slices), which slices it uses, its scatter, and the
    slices with the centres it was fitted to (the detector's, or those of :func:`disc_centres`) and their noise."""

    fit: Fit
    used: tuple[int, ...]
    scatter: Scatter
    dropped: tuple[tuple[int, str, float], ...]  # (slice, reason, residual RMS mm under the pose)
    seen: tuple[DetectedSlice, ...]
    noise: tuple[np.ndarray, ...]


def register_every_slice(slices: list[Slice], geom: FiducialGeometry, opts: SolveOptions,
                         detect_options: dict | None = None, target_F_mm=None) -> Registration:
    """One pose from every slice of ``slices`` (a volume's) that holds enough of the frame; the others are listed in
    ``Registration.skipped``. Raises :class:`NoLock` with the reason when no pose is trustworthy."""
    t0 = time.perf_counter()
    slices, filled = fill_slice_dropouts(slices)
    lows = check_pixel_range(slices)
    model, geom_sha = prepare_geometry(geom)
    seen = _detect_at_scan_width(detect_slices(slices, lows, model, detect_options), model, opts, detect_options)
    t1 = time.perf_counter()
    pixel_noise = [slice_noise(d.slice, d.blobs.footprints) if len(d.blobs.footprints) else None for d in seen]
    noise = [_centre_noise(d, n) for d, n in zip(seen, pixel_noise)]
    parents = [enclosing_blobs(d.blobs) for d in seen]
    starts, lone_refusals = starting_poses(model, seen, opts, symmetry_twins(geom, model, opts))
    if not starts:
        raise NoLock(no_slice_locked(lone_refusals), {"n_skipped": len(lone_refusals)})
    groups: list[list] = []  # each distinct joint pose [its closest JointFit, the lone-locked slices that lead to it]
    led: list[tuple[np.ndarray, list | None]] = []  # each start's pose on all slices' blobs, and where it led
    begun = [(_joint_start(model, seen, parents, X), js) for X, js in _distinct_starts(model, starts)]
    begun.sort(key=lambda b: -b[0][1].n_matched)  # the start that explains most of the volume first
    for start, js in begun:
        X = start[1].T_F_from_scanner
        # a start the blob centres of every slice take within a millimetre and a degree of a pose found leads there
        # (the same blobs, the same fit); one taken where an earlier one went leads where that one led
        same = [g for g in groups if not poses_distinct(X, g[0].fit.T_F_from_scanner, model)]
        same = same or [g for T, g in led if not poses_distinct(X, T, model, 0.01, 0.01)]
        if same:
            if same[0] is not None:
                same[0][1].update(js)
            continue
        jf = _joint_fit(model, seen, noise, pixel_noise, start)
        if jf is None:
            led.append((X, None))
            continue
        led.append((X, _join(model, groups, jf, js)))
    fits = [g for g in groups if near_prior(g[0].fit.T_F_from_scanner, opts)]
    outside = [g[0] for g in groups if not near_prior(g[0].fit.T_F_from_scanner, opts)]
    if not fits and outside:
        o = max(outside, key=lambda f: f.fit.n_matched)
        turn = rotation_deg(o.fit.T_F_from_scanner[:3, :3].T, np.asarray(opts.prior, float)[:3, :3])
        raise NoLock(f"the slices show the frame turned {turn:.0f} deg from the prior ({o.fit.n_matched} blob centres "
                     f"fit that pose), beyond --prior-max-deg {opts.prior_max_deg:g}: no pose near the prior explains "
                     f"them; check how the frame is mounted", {"stage": "joint", "n_outside": o.fit.n_matched})
    # a pose is the volume's when two or more slices would lock at it alone, and no other pose has such support
    supported = _supported(model, fits, opts)
    faint = len(supported) > 1
    if faint:  # each read again with its faint sections: a biased slice among few can split one pose's fits in two
        merged = _merge_with_faint_sections(model, supported, seen, noise, pixel_noise, parents, detect_options)
        fits = merged + [g for g in fits if not any(g is h for h in supported)]
        supported = _supported(model, merged, opts)
    if len(supported) != 1:
        raise NoLock(f"the slices locked alone lead to {len(supported)} distinct poses that two or more of them agree "
                     f"on (of {len(fits)} poses fitted to the volume's blob centres); one is needed",
                     {"n_poses": len(supported)})
    best = supported[0][0] if faint else _with_faint_sections(model, supported[0][0], seen, noise, pixel_noise,
                                                               parents, detect_options)
    others = sorted((g[0] for g in fits if g is not supported[0]), key=lambda f: (-f.fit.n_matched, _scatter_mm(f)))
    # centres that fit no rigid pose well, or two poses nearly as well: the sections' pixels may still tell
    _check_model_error(model, best)
    _check_explained(model, best)
    _check_rivals(model, best, others)
    try:  # a refusal from here on judged a pose the slices agree on: the volume's answer, not a reason to look further
        _check_outside_prior(model, best, outside, opts)
        seen, noise = best.seen, best.noise
        used = [seen[j] for j in best.used]
        final, scale = scale_stage(model, _restrict(best.fit, best.used), used, opts)
        t2 = time.perf_counter()
        sigma = [_tube_sigmas(final.assignments[n], noise[j], best.scatter.model_error_mm)
                 for n, j in enumerate(best.used)]
        unc = scatter_uncertainty(model, final, used, sigma, target_point(geom, target_F_mm))
        return build_registration(geom, model, geom_sha, final, used, [None] * len(used), None, filled,
                                  _skipped(model, best, final), opts, target_F_mm, (t0, t1, t2), scale=scale,
                                  uncertainty=unc)
    except NoLock as exc:
        exc.detail.setdefault("stage", "joint")
        raise


def _tube_sigmas(a: np.ndarray, noise: np.ndarray, model_error_mm: float) -> np.ndarray:
    """(K,) each matched tube's centre scatter per coordinate: its blob's noise and the model error (NaN unmatched)."""
    out = np.full(a.size, math.nan)
    k = np.flatnonzero(a >= 0)
    out[k] = np.sqrt(noise[a[k]] ** 2 + model_error_mm ** 2)
    return out


def scan_blob_width_mm(seen: list[DetectedSlice], model: TubeModel, min_tubes: int) -> float:
    """The blobs' width in a scan (mm): the median of the widths measured in its slices whose blob count looks like
    the frame's (``min_tubes`` to 1.5 times the tube count: noise that splits a slice's blobs into fragments also
    makes them read narrow); NaN when no slice does."""
    K = len(model.ids)
    widths = [d.blobs.width_mm for d in seen
              if min_tubes <= d.xy_mm.shape[0] <= 1.5 * K and math.isfinite(d.blobs.width_mm)]
    return float(np.median(widths)) if widths else math.nan


def _detect_at_scan_width(seen: list[DetectedSlice], model: TubeModel, opts: SolveOptions,
                          detect_options: dict | None) -> list[DetectedSlice]:
    """Every slice detected again at the scan's blob width (:func:`scan_blob_width_mm`) rather than its own: one
    width holds for the whole scan (the point-spread and the channels are the same), and a noisy slice's own
    reading is the fragments' width."""
    width = scan_blob_width_mm(seen, model, opts.min_tubes)
    if not math.isfinite(width) or (detect_options or {}).get("size_from_image") is False:
        return seen
    return [_detect_at_width(d, model, width, detect_options) for d in seen]


def _detect_at_width(d: DetectedSlice, model: TubeModel, width: float, detect_options: dict | None,
                     **extra) -> DetectedSlice:
    """``d`` detected at the blob width ``width`` (mm), with ``detect_options`` and ``extra`` options of
    :func:`~chic_register.detect.blobs.detect_blobs`."""
    f = width / median_diameter_mm(model)
    kw = {**(detect_options or {}), "size_from_image": False,
          "min_area_factor": (detect_options or {}).get("min_area_factor", MIN_AREA_FACTOR) / max(f, 1.0) ** 2, **extra}
    b = detect_blobs(d.slice.pixels, d.slice.pixel_spacing_mm, model.diameter_mm * f, **kw)
    return DetectedSlice.of(d.slice, dataclasses.replace(b, width_mm=width), d.T_scanner_from_image)


def _with_faint_sections(model: TubeModel, best: JointFit, seen, noise, pixel_noise, parents,
                         detect_options: dict | None) -> JointFit:
    """``best``, or its pose fitted again with the faint sections of the slices where it finds blobs for fewer tubes
    than it puts wholly inside them, when that explains more of the volume without moving the pose beyond a
    millimetre and a degree: such a slice is read again at a level bounded by its noise (:data:`SCAN_LEVEL_SIGMAS`),
    kept where that finds more blobs at the pose's crossings. Anatomy far brighter than the frame (a patient's
    thighs) draws Otsu's split between tissue and background, above the rods of a slab's fading end."""
    X = best.fit.T_F_from_scanner
    gate = float(np.max(model.diameter_mm))
    again, changed = list(seen), []
    for j, d in enumerate(seen):
        whole = _interior(model, X @ d.T_scanner_from_image)
        found = int(np.sum(whole & (best.fit.assignments[j] >= 0)))
        if not whole.any() or found >= int(whole.sum()) or not math.isfinite(d.blobs.width_mm):
            continue
        faint = _detect_at_width(d, model, d.blobs.width_mm, detect_options, noise_threshold_sigmas=SCAN_LEVEL_SIGMAS)
        q, _, _, inside = plane_crossings(model, X @ d.T_scanner_from_image)
        if int(np.sum(assign_blobs(q, inside, faint.xy_mm, gate) >= 0)) > int(np.sum(
                assign_blobs(q, inside, d.xy_mm, gate) >= 0)):
            again[j] = faint
            changed.append(j)
    if not changed:
        return best
    pixel_noise = list(pixel_noise)
    noise, parents = list(noise), list(parents)
    for j in changed:
        d = again[j]
        pixel_noise[j] = slice_noise(d.slice, d.blobs.footprints) if len(d.blobs.footprints) else None
        noise[j], parents[j] = _centre_noise(d, pixel_noise[j]), enclosing_blobs(d.blobs)
    jf = _joint_fit(model, again, noise, pixel_noise, _joint_start(model, again, parents, X))
    if jf is None:
        return best
    if not poses_distinct(jf.fit.T_F_from_scanner, X, model):
        return jf if jf.fit.n_matched > best.fit.n_matched or _explains_better(jf, best) else best
    # a distinct pose: taken only where it matches as many centres RIVAL_SCATTER_RATIO times closer (``best`` then
    # fitted a biased group of slices with the others, which the faint sections outvote)
    if jf.fit.n_matched >= best.fit.n_matched and RIVAL_SCATTER_RATIO * _scatter_mm(jf) <= _scatter_mm(best):
        return jf
    return best


def _merge_with_faint_sections(model: TubeModel, groups: list[list], seen, noise, pixel_noise, parents,
                               detect_options: dict | None) -> list[list]:
    """``groups`` (``[JointFit, lone-locked slices]``) with each pose fitted again with its faint sections
    (:func:`_with_faint_sections`), those that then reach one pose merged: the closer fit kept, their slices pooled.
    Among a few slices one of a slab's biased end slices can hold two fits of one pose apart, each with a part of
    the others; the sections the faint slices hold outvote it."""
    out: list[list] = []
    for jf, js in groups:
        _join(model, out, _with_faint_sections(model, jf, seen, noise, pixel_noise, parents, detect_options), js)
    return out


def _join(model: TubeModel, groups: list[list], jf: JointFit, js) -> list:
    """The group of ``groups`` (``[JointFit, lone-locked slices]``) that ``jf`` joins, with its slices ``js``: the
    one whose pose is ``jf``'s (the closer fit kept, :func:`_explains_better`), else a new one appended."""
    same = [g for g in groups if not poses_distinct(jf.fit.T_F_from_scanner, g[0].fit.T_F_from_scanner, model)]
    if not same:
        groups.append([jf, set(js)])
        return groups[-1]
    if _explains_better(jf, same[0][0]):  # the same pose, reached through better-fitting slices: kept instead
        same[0][0] = jf
    same[0][1].update(js)
    return same[0]


def _supported(model: TubeModel, groups: list[list], opts: SolveOptions) -> list[list]:
    """The groups whose pose two or more slices would lock at alone: they did, and led to it, or the joint fit
    matches every tube it puts wholly inside them (:func:`_complete_slices`)."""
    return [g for g in groups if len(g[1] | _complete_slices(model, g[0], opts)) >= 2]


def median_diameter_mm(model: TubeModel) -> float:
    return float(np.median(model.diameter_mm))


def _centre_noise(d: DetectedSlice, pixel_noise, known: tuple[DetectedSlice, np.ndarray] | None = None) -> np.ndarray:
    """(N,) each blob centre's 1-sigma error per coordinate (mm) from the slice's image noise ``pixel_noise`` (a
    :class:`~chic_register.detect.noise.NoiseEstimate`: one per slice, whichever centres its blobs are given);
    ``known``: the same slice with other centres for some blobs, and its errors (a footprint it shares is not
    measured again)."""
    b = d.blobs
    if not len(b.footprints) or pixel_noise is None:
        return np.zeros(0)
    n = pixel_noise
    out = []
    for i, fp in enumerate(b.footprints):
        if known is not None and fp is known[0].blobs.footprints[i]:
            out.append(float(known[1][i]))
            continue
        C = centroid_covariance(d.slice.pixels, fp, b.background, n, d.slice.pixel_spacing_mm)
        out.append(math.sqrt(max(0.5 * float(np.trace(C)), 0.0)) if np.all(np.isfinite(C)) else math.inf)
    return np.array(out)


def enclosing_blobs(blobs) -> np.ndarray:
    """(N,) per candidate, the index of the larger candidate whose footprint holds its centre (the detector offers a
    blob that may be two touching tubes both whole and split), or -1."""
    n = len(blobs.footprints)
    out = np.full(n, -1)
    for i in range(n):
        r, c = blobs.centres_rc[i]
        for j, (r0, c0, mask) in enumerate(blobs.footprints):
            if j == i or blobs.area_px[j] <= blobs.area_px[i]:
                continue
            rr, cc = int(round(r)) - r0, int(round(c)) - c0
            if 0 <= rr < mask.shape[0] and 0 <= cc < mask.shape[1] and mask[rr, cc]:
                if out[i] < 0 or blobs.area_px[j] > blobs.area_px[out[i]]:
                    out[i] = j
    return out


def _candidates(model: TubeModel, d: DetectedSlice, parent: np.ndarray, X: np.ndarray | None, gate: float):
    """Indices of the blobs the joint fit matches in slice ``d``: every whole blob, and the parts of one only where
    the pose ``X`` puts two tubes' crossings within ``gate`` of it (two touching tubes), not the whole then."""
    whole = np.flatnonzero(parent < 0)
    if X is None or not np.any(parent >= 0):
        return whole
    q, _, _, inside = plane_crossings(model, X @ d.T_scanner_from_image)
    q = q[inside]
    shared = [w for w in whole if np.any(parent == w)
              and int(np.sum(np.linalg.norm(q - d.xy_mm[w], axis=1) < gate)) >= 2]
    if not shared:
        return whole
    keep = [i for i in range(parent.size) if (parent[i] < 0 and i not in shared) or parent[i] in shared]
    return np.array(keep, dtype=int)


def symmetry_twins(geom: FiducialGeometry, model: TubeModel, opts: SolveOptions) -> list[np.ndarray]:
    """With a prior, the motions ``H`` (4x4, in F) of every rotation that maps the frame onto itself within the
    channels' print tolerance (z001's half turn): a pose ``X`` and ``H^-1 X`` show the same image."""
    if opts.prior is None:
        return []
    found, _ = frame_symmetries(geom, EXACT_SHARE * float(np.min(model.diameter_mm)))
    c = np.array([0.0, 0.0, 0.5 * model.length_mm])
    out = []
    for sym in found:
        R = dict(candidate_rotations(model.length_mm))[sym.what]
        H = np.eye(4)
        H[:3, :3], H[:3, 3] = R, c - R @ c
        out.append(H)
    return out


def starting_poses(model: TubeModel, seen: list[DetectedSlice], opts: SolveOptions, twins=()):
    """``(slice, T_F_from_scanner, tubes explained)`` of up to :data:`MAX_LONE_LOCKS` slices locked alone (whatever
    the prior), with their close rivals; and the slices that did not lock (:class:`SkippedSlice`, with their
    reasons). Slices whose blob count is nearest the tube count go first, from the middle out. ``twins``
    (:func:`symmetry_twins`): each start is taken as the one of its symmetric twins nearest the prior (a slice
    alone locks either, at random where the image is stretched a little)."""
    K = len(model.ids)
    # without the prior: a pose outside it that explains more of the frame is evidence against the prior's pose
    lone = dataclasses.replace(opts, max_rms_px=max(opts.max_rms_px, 1.5), prior=None)
    middle = 0.5 * (len(seen) - 1)
    order = sorted((j for j, d in enumerate(seen) if d.xy_mm.shape[0] >= opts.min_tubes),
                   key=lambda j: (abs(seen[j].xy_mm.shape[0] - K), abs(j - middle)))
    starts = []
    refusals = [SkippedSlice(d.source, f"found {d.xy_mm.shape[0]} candidate tube cross-sections; need at least "
                                       f"{opts.min_tubes}") for d in seen if d.xy_mm.shape[0] < opts.min_tubes]
    for j in order[:MAX_LONE_LOCKS]:
        d = seen[j]
        try:
            fits, _ = lock_slice(model, d.xy_mm, d.T_scanner_from_image, lone, d.resolution_mm)
        except NoLock as exc:
            refusals.append(SkippedSlice(d.source, exc.reason))
            continue
        top = fits[0].n_matched
        starts += [(j, _nearest_prior([f.T_F_from_scanner] + [invert(H) @ f.T_F_from_scanner for H in twins], opts),
                    f.n_matched) for f in fits if f.n_matched >= top - 1]
    return starts, refusals


def _nearest_prior(poses: list[np.ndarray], opts: SolveOptions) -> np.ndarray:
    """The pose (``T_F_from_scanner``) of ``poses`` turned least from the prior (the first without one)."""
    if opts.prior is None or len(poses) == 1:
        return poses[0]
    R_prior = np.asarray(opts.prior, float)[:3, :3]
    return min(poses, key=lambda X: rotation_deg(X[:3, :3].T, R_prior))


def _distinct_starts(model: TubeModel, starts) -> list[tuple[np.ndarray, set]]:
    """``(T_F_from_scanner, slices)``: the starting poses (``starts``: slice, pose, tubes it explains there), those
    within a millimetre and a degree of each other taken as one, with every lone-locked slice that gave it; a pose
    that explains two tubes fewer than the best of any slice does (a slice of the four parallel rods alone locks in
    four turns of them, all wrong but one) is dropped unless a better start gave it too."""
    reps: list[tuple[np.ndarray, set, list]] = []
    for j, X, n in starts:
        for Y, js, best in reps:
            if not poses_distinct(X, Y, model):
                js.add(j)
                best[0] = max(best[0], n)
                break
        else:
            reps.append((X, {j}, [n]))
    top = max((best[0] for _, _, best in reps), default=0)
    return [(X, js) for X, js, best in reps if best[0] >= top - 1]


def _explains_better(a: JointFit, b: JointFit) -> bool:
    """Whether joint fit ``a`` matches at least as many blob centres as ``b`` with a smaller scatter. Two fits within
    a millimetre and a degree of each other are one pose; the slices each kept can differ (a start among a scan's
    biased end slices, its tubes part-filled, keeps them and fits them all loosely), and the closer fit is the pose's."""
    return a.fit.n_matched >= b.fit.n_matched and _scatter_mm(a) < _scatter_mm(b)


def _scatter_mm(jf: JointFit) -> float:
    return float(np.median(jf.scatter.sigma_mm)) if jf.scatter.sigma_mm.size else math.inf


def _residual_rows(fit: Fit, noise, js):
    """Per slice in ``js``: (tube indices matched, squared residual lengths (mm^2), their centres' noise (mm))."""
    rows = []
    for j in js:
        a, r = fit.assignments[j], fit.residuals[j]
        k = np.flatnonzero((a >= 0) & np.isfinite(r))
        rows.append((k, r[k] ** 2, noise[j][a[k]]))
    return rows


def _joint_start(model: TubeModel, seen, parents, X: np.ndarray) -> tuple[list[np.ndarray], Fit, np.ndarray]:
    """``(idx, fit, X)``: per slice the blobs that are candidates for tubes (:func:`_candidates`), the pose near
    ``X`` fitted to them on every slice, and ``X`` itself (the start of :func:`_joint_fit`)."""
    gate = match_gate_mm(model, max(d.resolution_mm for d in seen))
    K = len(model.ids)
    excl = [np.zeros(K, bool) for _ in seen]
    keep = list(range(len(seen)))
    idx = [_candidates(model, d, p, None, gate) for d, p in zip(seen, parents)]
    fit = _fit_on(model, seen, idx, X, keep, excl, (1.5 * gate, gate, 0.6 * gate))
    again = [_candidates(model, d, p, fit.T_F_from_scanner, gate) for d, p in zip(seen, parents)]
    if any(a.size != b.size or np.any(a != b) for a, b in zip(again, idx)):  # touching tubes: their parts instead
        idx = again
        fit = _fit_on(model, seen, idx, fit.T_F_from_scanner, keep, excl, (0.6 * gate,))
    return idx, fit, X


def _gate(model: TubeModel, seen) -> float:
    """The joint fit's widest blob-to-tube gate (mm) over the slices ``seen``."""
    return match_gate_mm(model, max(d.resolution_mm for d in seen))


def _joint_fit(model: TubeModel, seen, noise, pixel_noise, start: tuple[list[np.ndarray], Fit, np.ndarray]
               ) -> JointFit | None:
    """The pose fitted to every slice from ``start`` (:func:`_joint_start`), blobs and then slices the scatter
    cannot explain left out; None when fewer than two slices keep :data:`MIN_SLICE_TUBES` tubes.

    Where the fitted slices show a scale (:func:`~chic_register.fit.scale.fit_scale`'s F test), the centres and
    slices are taken at that scale and the blobs and slices chosen again: a few per cent across a volume's slices
    (the gradients' non-linearity far from the isocentre) puts the end slices' sections a millimetre off any rigid
    pose, which would otherwise leave them out. The fit is then the scaled data's; ``JointFit.seen`` stays the
    image's own (the registration fits the scale again on it, :func:`~chic_register.pipeline.scaling.scale_stage`)."""
    gate = _gate(model, seen)
    idx, fit, X0 = start
    keep = list(range(len(seen)))
    excl = [np.zeros(len(model.ids), bool) for _ in seen]
    seen, noise, fit = _better_centres(model, seen, noise, pixel_noise, idx, fit, keep, excl, gate)
    screened = _screen_slices(model, seen, noise, fit, X0)
    kept = [j for j in keep if j not in {j for j, _, _ in screened}]
    if screened:
        fit = _fit_on(model, seen, idx, fit.T_F_from_scanner, kept, excl, (0.6 * gate,))
    jf = _prune(model, seen, noise, idx, fit, gate, kept, screened)
    if jf is None:
        return None
    scaled, rigid = list(seen), jf
    for _ in range(SCALE_ROUNDS):
        sf = fit_scale(model, _restrict(jf.fit, jf.used), [scaled[j] for j in jf.used])
        if sf is None or not sf.p < STRETCH_P:
            break
        scaled = [_at_scale(d, sf, model) for d in scaled]
        again = _prune(model, scaled, noise, idx, _fit_on(model, scaled, idx, sf.T_F_from_scanner, keep, excl,
                                                          (gate, 0.6 * gate)), gate)
        if (again is None or again.fit.n_matched < jf.fit.n_matched
                or _scatter_mm(again) > RIVAL_SCATTER_RATIO * _scatter_mm(jf)):
            break  # (a scale that takes in more slices only by fitting them all loosely is not the image's)
        jf = again
    return jf if jf is rigid else dataclasses.replace(jf, seen=tuple(seen))


def _at_scale(d: DetectedSlice, sf, model: TubeModel) -> DetectedSlice:
    """``d`` as a rigid image of the fiducial at the scale ``sf`` (a :class:`~chic_register.fit.scale.ScaleFit`):
    its centres stretched about the fiducial's centre in the image plane, the slice moved along its normal by the
    through-plane scale times its distance from that centre."""
    X = sf.T_F_from_scanner
    S = d.T_scanner_from_image
    centre = invert(S) @ (invert(X) @ np.array([0.0, 0.0, 0.5 * model.length_mm, 1.0]))
    s = np.zeros(3)
    s[:sf.scale.size] = sf.scale
    xy = centre[:2] + (1.0 + s[:2]) * (d.xy_mm - centre[:2])
    shift = np.eye(4)
    shift[2, 3] = -s[2] * centre[2]  # the slice lies -centre[2] from the centre along its normal
    return dataclasses.replace(d, xy_mm=xy, T_scanner_from_image=S @ shift)


def _robust_pose(model: TubeModel, seen, fit: Fit, X0: np.ndarray, rounds: int = ROBUST_ROUNDS) -> Fit:
    """A pose fitted to ``fit``'s blob assignments with Cauchy weights (iteratively reweighted least squares from
    ``X0``, the start a slice locked alone gave): a blob ``r`` from its crossing counts ``1 / (1 + (r / (c sigma))^2)``,
    ``sigma`` the residuals' robust scale per coordinate and ``c`` :data:`CAUCHY_C`. A group of slices whose centres
    are biased the same way (channels part filled at one end of a frame, a slab's fading edge) then pulls the pose
    much less than in plain least squares, which ``fit`` is."""
    js = [j for j, a in enumerate(fit.assignments) if np.count_nonzero(a >= 0) >= MIN_SLICE_TUBES]
    if len(js) < 3:
        return fit
    xy = [seen[j].xy_mm for j in js]
    S = [seen[j].T_scanner_from_image for j in js]
    assign = [fit.assignments[j] for j in js]
    sub = refine(model, xy, S, X0, gates_mm=(), assign0=assign, final_iters=0)  # (the residuals at X0)
    X, res = X0, sub.residuals
    for _ in range(rounds):
        r2 = np.concatenate([r[(a >= 0) & np.isfinite(r)] ** 2 for a, r in zip(assign, res)])
        sigma2 = float(np.median(r2)) / (2.0 * math.log(2.0)) if r2.size else 0.0
        if not sigma2 > 0:
            return fit
        W = []
        for a, r in zip(assign, res):
            w = np.where((a >= 0) & np.isfinite(r), 1.0 / (1.0 + np.nan_to_num(r) ** 2 / (CAUCHY_C ** 2 * sigma2)), 0.0)
            W.append(np.sqrt(w)[:, None, None] * np.eye(2))
        sub = refine(model, xy, S, X, gates_mm=(), assign0=assign, final_iters=3, weights=W)
        X, assign, res = sub.T_F_from_scanner, sub.assignments, sub.residuals
    K = len(model.ids)
    a_all = [np.full(K, -1) for _ in seen]
    r_all = [np.full(K, math.nan) for _ in seen]
    for n, j in enumerate(js):
        a_all[j], r_all[j] = assign[n], res[n]
    return Fit(X, a_all, r_all, fit.inside, sub.n_matched, sub.rms_mm, None)  # (over the slices it weighed)


def _screen_slices(model: TubeModel, seen, noise, fit: Fit, X0: np.ndarray) -> list[tuple[int, str, float]]:
    """Slices left out before the joint fit's pruning: those whose residuals under :func:`_robust_pose` the scatter
    of the others cannot explain (a chi-square tail below :data:`OUTLIER_P`, shared over the slices), as
    :func:`_prune` reasons them. Plain least squares over every slice can spread a biased group's error over all of
    them until none stands out; the robust pose leaves it where it is. Nothing is left out when that would leave
    fewer than half the slices (the robust pose is then no majority's)."""
    robust = _robust_pose(model, seen, fit, X0)
    if robust is fit:
        return []
    ok = [(j, row) for j, row in zip(range(len(seen)), _residual_rows(robust, noise, range(len(seen))))
          if row[0].size >= MIN_SLICE_TUBES]
    if len(ok) < 3:
        return []
    r2 = np.concatenate([row[1] for _, row in ok])
    sig2 = Scatter.of(r2, np.concatenate([row[2] for _, row in ok])).sigma_mm ** 2
    out = [(j, *_disagreement(r2j, sig2, p, "pose the others agree on, where they"))
           for (j, (_, r2j, _)), p in zip(ok, _slice_tails(ok, sig2)) if p < OUTLIER_P / len(ok)]
    return out if 2 * len(out) <= len(ok) else []


def _slice_tails(ok, sig2: np.ndarray) -> list[float]:
    """Per slice of ``ok`` (``(slice, (tubes, squared residuals, noise))``, as :func:`_residual_rows`), the tail
    probability of its residuals under the blobs' scatter ``sig2`` (M,): chi-square with 2 degrees of freedom a tube."""
    out, pos = [], 0
    for _, (k, r2j, _) in ok:
        out.append(1.0 - gamma_p(float(k.size), 0.5 * float(np.sum(r2j / sig2[pos:pos + k.size]))))
        pos += k.size
    return out


def _disagreement(r2j: np.ndarray, sig2: np.ndarray, p: float, against: str) -> tuple[str, float]:
    """``(reason, RMS mm)`` of a slice left out with squared residuals ``r2j`` and tail ``p`` (:func:`_slice_tails`),
    ``against`` naming the pose and the slices it is measured against."""
    rms = float(np.sqrt(np.mean(r2j)))
    return (f"disagrees with the other slices: its {r2j.size} tubes sit {rms:.3f} mm RMS from the {against} "
            f"scatter by {math.sqrt(2.0 * float(np.median(sig2))):.3f} mm (chi-square tail {p:.1e})", rms)


def _prune(model: TubeModel, seen, noise, idx, fit: Fit, gate: float, keep: list[int] | None = None,
           dropped: list | None = None) -> JointFit | None:
    """From ``fit`` on the slices ``keep`` (default every slice; ``dropped``: those already left out, with their
    reasons): blobs, then slices, whose residuals the scatter cannot explain left out in turn (:data:`OUTLIER_P`),
    the pose refitted after each; None when fewer than two slices keep :data:`MIN_SLICE_TUBES` tubes."""
    K = len(model.ids)
    excl = [np.zeros(K, bool) for _ in seen]
    keep = list(range(len(seen))) if keep is None else list(keep)
    dropped = list(dropped or [])
    for _ in range(2 * len(seen) + 4 * K):
        rows = _residual_rows(fit, noise, keep)
        ok = [(j, row) for j, row in zip(keep, rows) if row[0].size >= MIN_SLICE_TUBES]
        if len(ok) < 2:
            return None
        r2 = np.concatenate([row[1] for _, row in ok])
        sc = Scatter.of(r2, np.concatenate([row[2] for _, row in ok]))
        sig2 = sc.sigma_mm ** 2
        z_blob = r2 / sig2
        worst = int(np.argmax(z_blob))
        if math.exp(-0.5 * float(z_blob[worst])) < OUTLIER_P / r2.size:  # chi-square, 2 dof: P(> z) = exp(-z / 2)
            offs = np.cumsum([0] + [row[0].size for _, row in ok])
            s = int(np.searchsorted(offs, worst, side="right") - 1)
            j, (k, _, _) = ok[s]
            excl[j][k[worst - offs[s]]] = True
            fit = _fit_on(model, seen, idx, fit.T_F_from_scanner, keep, excl, (0.6 * gate,))
            continue
        p_slice = _slice_tails(ok, sig2)
        s = int(np.argmin(p_slice))
        if p_slice[s] < OUTLIER_P / len(ok) and len(ok) > 2:
            j, (_, r2j, _) = ok[s]
            dropped.append((j, *_disagreement(r2j, sig2, p_slice[s], "joint pose's crossings, where the others")))
            keep = [i for i in keep if i != j]
            fit = _fit_on(model, seen, idx, fit.T_F_from_scanner, keep, excl, (0.6 * gate,))
            continue
        return JointFit(fit, tuple(j for j, _ in ok), sc, tuple(dropped), tuple(seen), tuple(noise))
    return None


def disc_centres(model: TubeModel, d: DetectedSlice, a: np.ndarray, T_F_from_scanner: np.ndarray) -> DetectedSlice:
    """``d`` with each matched blob's centre (``a`` (K,): per tube its blob, -1 none) and footprint those of
    :func:`~chic_register.detect.disc.disc_centroid` over a disc of the scan's blob width in radius: a disc twice
    the blob's width holds its whole section, blur included, however the detection level cut it. Pixels nearer
    another tube's section (its blob, else the pose's crossing) stay out; a blob whose disc wanders keeps its own."""
    b, sl = d.blobs, d.slice
    rs, cs = (float(v) for v in sl.pixel_spacing_mm)
    width = b.width_mm if math.isfinite(b.width_mm) else median_diameter_mm(model)
    radius_px = width / math.sqrt(rs * cs)
    q, _, _, inside = plane_crossings(model, T_F_from_scanner @ d.T_scanner_from_image)
    k_m = np.flatnonzero(a >= 0)
    seeds = np.stack([q[:, 1] / rs, q[:, 0] / cs], axis=1)
    seeds[k_m] = b.centres_rc[a[k_m]]
    present = inside.copy()
    present[k_m] = True
    centres, feet = b.centres_rc.copy(), list(b.footprints)
    for k in k_m:
        i = int(a[k])
        got = disc_centroid(sl.pixels, b.background, b.centres_rc[i], radius_px,
                            seeds[present & (np.arange(a.size) != k)])
        if got is not None:
            centres[i], feet[i] = got
    blobs = dataclasses.replace(b, centres_rc=centres, footprints=tuple(feet))
    return DetectedSlice.of(sl, blobs, d.T_scanner_from_image)


def _better_centres(model: TubeModel, seen, noise, pixel_noise, idx, fit: Fit, keep: list[int], excl, gate: float):
    """``(seen, noise, fit)``: the detector's centres or the disc centres (:func:`disc_centres`) of the matched
    blobs, whichever the pose fits with the smaller median residual (the data say which is the less noisy
    measurement: the detector's footprint on clean sections, the disc where texture or a faint slab breaks them
    up), and the pose fitted to them."""
    X = fit.T_F_from_scanner
    disc = [disc_centres(model, d, fit.assignments[j], X) if j in keep else d for j, d in enumerate(seen)]
    disc_noise = [_centre_noise(d, pixel_noise[j], (seen[j], noise[j])) if j in keep else noise[j]
                  for j, d in enumerate(disc)]
    refit = _fit_on(model, disc, idx, X, keep, excl, (0.6 * gate,))

    def median_r2(f: Fit) -> float:
        r2 = np.concatenate([row[1] for row in _residual_rows(f, noise, keep)])
        return float(np.median(r2)) if r2.size else math.inf

    if refit.n_matched >= fit.n_matched and median_r2(refit) < median_r2(fit):
        return disc, disc_noise, refit
    return seen, noise, fit


def _fit_on(model: TubeModel, seen, idx, X: np.ndarray, keep: list[int], excl, gates) -> Fit:
    """The pose refitted from ``X`` on the slices ``keep`` (their blobs ``idx``, tubes ``excl`` left out), written
    out over every slice with blob indices into each slice's own blobs (the others unassigned)."""
    sub = refine(model, [seen[i].xy_mm[idx[i]] for i in keep], [seen[i].T_scanner_from_image for i in keep], X,
                 gates_mm=gates, iters_per_gate=3, final_iters=3, exclude=[excl[i] for i in keep])
    K = len(model.ids)
    a = [np.full(K, -1) for _ in seen]
    r = [np.full(K, math.nan) for _ in seen]
    ins = [np.zeros(K, bool) for _ in seen]
    for n, i in enumerate(keep):
        a_n = sub.assignments[n]
        a[i] = np.where(a_n >= 0, idx[i][np.maximum(a_n, 0)] if idx[i].size else -1, -1)
        r[i], ins[i] = sub.residuals[n], sub.inside[n]
    return Fit(sub.T_F_from_scanner, a, r, ins, sub.n_matched, sub.rms_mm, None)


def _restrict(fit: Fit, used) -> Fit:
    """``fit`` over the slices ``used`` only."""
    a = [fit.assignments[j] for j in used]
    r = [fit.residuals[j] for j in used]
    n = sum(int(np.sum(x >= 0)) for x in a)
    sq = sum(float(np.nansum(x ** 2)) for x in r)
    return Fit(fit.T_F_from_scanner, a, r, [fit.inside[j] for j in used], n, math.sqrt(sq / n) if n else math.inf,
               None)


def _check_rivals(model: TubeModel, best: JointFit, others: list[JointFit]) -> None:
    """:class:`AmbiguousFit` when a distinct pose matches as many blobs with a scatter near the best's."""
    for o in others:
        if (o.fit.n_matched >= best.fit.n_matched and _scatter_mm(o) <= RIVAL_SCATTER_RATIO * _scatter_mm(best)
                and poses_distinct(o.fit.T_F_from_scanner, best.fit.T_F_from_scanner, model)):
            raise AmbiguousFit(f"ambiguous fit: two distinct poses each explain {best.fit.n_matched} blob centres "
                               f"of the volume, with scatters {_scatter_mm(best):.3f} and {_scatter_mm(o):.3f} mm",
                               {"n_tubes": best.fit.n_matched})


def _check_outside_prior(model: TubeModel, best: JointFit, outside: list[JointFit], opts: SolveOptions) -> None:
    """:class:`NoLock` when a pose the prior rules out matches clearly more blob centres than the best it allows: the
    frame is not mounted as the prior says (upside down, say), and the prior's pose explains only part of it."""
    more = [o for o in outside if o.fit.n_matched >= best.fit.n_matched + max(MIN_SLICE_TUBES,
                                                                            OUTSIDE_SHARE * best.fit.n_matched)
            and _scatter_mm(o) <= RIVAL_SCATTER_RATIO * _scatter_mm(best)]
    if more:
        o = max(more, key=lambda f: f.fit.n_matched)
        raise NoLock(f"a pose turned more than {opts.prior_max_deg:g} deg from the prior explains {o.fit.n_matched} "
                     f"blob centres of the volume, the best near it only {best.fit.n_matched}: the frame is not "
                     f"mounted as --prior says", {"n_outside": o.fit.n_matched, "n_tubes": best.fit.n_matched})


def _check_explained(model: TubeModel, best: JointFit) -> None:
    """:class:`NoLock` when the pose finds blobs for fewer than :data:`EXPLAINED_SHARE` of the tubes it puts wholly
    inside the slices it uses: a pose of the frame explains its image (a bubble or an unfilled channel loses a few
    tubes); one that explains half is a guess that lines up a subset."""
    X = best.fit.T_F_from_scanner
    inner = matched = 0
    for j in best.used:
        whole = _interior(model, X @ best.seen[j].T_scanner_from_image)
        inner += int(whole.sum())
        matched += int(np.sum(whole & (best.fit.assignments[j] >= 0)))
    if inner and matched < EXPLAINED_SHARE * inner:
        raise NoLock(f"the pose fitted to the volume's blob centres finds blobs for only {matched} of the {inner} "
                     f"tube crossings it puts wholly inside its {len(best.used)} slices", {"explained": matched})


def _complete_slices(model: TubeModel, jf: JointFit, opts: SolveOptions) -> set[int]:
    """The slices of ``jf`` that would lock alone at its pose: at least ``opts.min_tubes`` tubes matched, among them
    every tube whose section the pose puts wholly inside the slice (:func:`_interior`). A noisy scan's slices may
    fail to lock alone while the joint fit finds their whole pattern; a slice that shows only the tubes every
    slice shows alike (a Z-frame's parallel rods) is no such evidence."""
    X = jf.fit.T_F_from_scanner
    out = set()
    for j in jf.used:
        a = jf.fit.assignments[j]
        matched = a >= 0
        if int(matched.sum()) >= opts.min_tubes and not np.any(_interior(model, X @ jf.seen[j].T_scanner_from_image)
                                                               & ~matched):
            out.add(j)
    return out


def _interior(model: TubeModel, T_F_from_I: np.ndarray) -> np.ndarray:
    """(K,) the tubes whose crossing lies a channel's width inside their ends (a section there is whole)."""
    _, _, z_F, inside = plane_crossings(model, T_F_from_I)
    d = float(np.max(model.diameter_mm))
    return inside & (z_F >= model.z_lo + d) & (z_F <= model.z_hi - d)


#: A section too faint to detect is named in a left-out slice's reason when the mean over a disc of the blob width at
#: the pose's crossing stands this many pixel noise sigmas above the background: plain to the eye (noise alone, over
#: a disc of ~30 pixels, reaches it with odds below 1e-20).
FAINT_SIGMAS = 2.0


def _faint_note(model: TubeModel, d: DetectedSlice, q: np.ndarray, where: np.ndarray) -> str:
    """What a left-out slice shows at the pose's crossings ``q`` (K, 2) of the tubes ``where`` (K,) that have no
    blob: faint sections a person sees but the detector's level does not reach (a slab's fading end)."""
    b, sl = d.blobs, d.slice
    if not where.any() or not b.noise_sigma > 0:
        return ""
    rs, cs = (float(v) for v in sl.pixel_spacing_mm)
    width = b.width_mm if math.isfinite(b.width_mm) else median_diameter_mm(model)
    radius_px = 0.5 * width / math.sqrt(rs * cs)
    z = [disc_contrast(sl.pixels, b.background, b.noise_sigma, (q[k, 1] / rs, q[k, 0] / cs), radius_px)
         for k in np.flatnonzero(where)]
    faint = sorted(v for v in z if v >= FAINT_SIGMAS)
    if not faint:
        return f"; nothing stands out at the {len(z)} crossings without one"
    span = f"{faint[0]:.1f}" if len(faint) == 1 else f"{faint[0]:.1f}-{faint[-1]:.1f}"
    return (f"; at {len(faint)} of the {len(z)} crossings without one a section shows, too faint to locate ({span} "
            f"noise sigmas above the background over the blob's width)")


def _check_model_error(model: TubeModel, best: JointFit) -> None:
    """:class:`NoLock` when the blobs sit further from the pose's crossings than any real frame's model error."""
    limit = MODEL_ERROR_SHARE * float(np.median(model.diameter_mm))
    m = best.scatter.model_error_mm
    if m > limit:
        raise NoLock(f"the blob centres sit {m:.3f} mm (per coordinate, beyond their noise) from the crossings of the "
                     f"best pose, more than a third of the channel diameter ({limit:.2f} mm): the image does not show "
                     f"this frame rigidly", {"model_error_mm": round(m, 4)})


def _skipped(model: TubeModel, best: JointFit, final: Fit) -> list[SkippedSlice]:
    """Every slice not used, in order, with its reason (and its residual under the pose when it has one)."""
    seen = best.seen
    reasons = {j: (why, rms) for j, why, rms in best.dropped}
    out = []
    for j, d in enumerate(seen):
        if j in best.used:
            continue
        if j in reasons:
            why, rms = reasons[j]
            out.append(SkippedSlice(d.source, why, rms))
            continue
        T_F_from_I = final.T_F_from_scanner @ d.T_scanner_from_image
        inside = plane_crossings(model, T_F_from_I)[3]
        if not inside.any():
            depth = float(slice_angles(T_F_from_I).depth_mm)
            out.append(SkippedSlice(d.source, f"the slice misses the frame (it crosses the axis at depth {depth:.1f} "
                                              f"mm, outside the body [0, {model.length_mm:g}] mm)"))
            continue
        a = best.fit.assignments[j]
        n = int(np.sum(a >= 0))
        rms = float(np.sqrt(np.nanmean(best.fit.residuals[j][a >= 0] ** 2))) if n else None
        q = plane_crossings(model, T_F_from_I)[0]
        wide = assign_blobs(q, inside, d.xy_mm, WIDE_GATE_SHARE * float(np.max(model.diameter_mm)))
        if int(np.sum(wide >= 0)) >= max(MIN_SLICE_TUBES, n + 1):  # its blobs are there, but off the pose's crossings
            off = float(np.sqrt(np.mean(np.sum((q[wide >= 0] - d.xy_mm[wide[wide >= 0]]) ** 2, axis=1))))
            out.append(SkippedSlice(d.source, f"disagrees with the other slices: {int(np.sum(wide >= 0))} of its "
                                              f"blobs lie {off:.3f} mm RMS from the crossings of the joint pose "
                                              f"(within {n} of them: {MIN_SLICE_TUBES} needed)", off))
            continue
        if d.xy_mm.shape[0] == 0:
            why = f"found 0 candidate tube cross-sections (the pose puts {int(inside.sum())} tubes in the slice)"
        elif n == 0:
            why = f"no blob where the pose puts the {int(inside.sum())} tubes that cross the slice"
        else:
            why = (f"only {n} of the {int(inside.sum())} tubes the pose puts in the slice show a blob there "
                   f"(a slice counts with {MIN_SLICE_TUBES})")
        out.append(SkippedSlice(d.source, why + _faint_note(model, d, q, inside & (a < 0)), rms))
    return out
