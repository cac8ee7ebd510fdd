"""Register a volume's native slices: all of those that show the fiducial, or the ones asked for.

Real volumes are often masked or empty outside the frame, and the end
slices cut the tubes short: :func:`register_volume` without indices tries
every slice, registers jointly those where the fiducial locks and reports the
others (:attr:`~chic_register.pipeline.register.Registration.skipped`, with the reason,
and the residual of a slice that disagrees with the rest).
:func:`parse_slice_indices` reads ``--slices`` values (``5``, ``5-11``).
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from chic_register.detect.blobs import detect_blobs, median
from chic_register.detect.detected import DetectedSlice
from chic_register.detect.wide_blobs import WIDE_RATIO, blob_width_ratio
from chic_register.errors import ChicRegisterError, NoLock, SliceRefused
from chic_register.fit.blurred import blurred_stage
from chic_register.fit.refine import assign_blobs, refine
from chic_register.guess.volume_search import volume_first_guesses
from chic_register.io.volumes import Volume
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.pose import near_prior, rotation_deg, slice_angles
from chic_register.model.tube_model import plane_crossings, prepare_geometry
from chic_register.options import SolveOptions
from chic_register.pipeline.every_slice import register_every_slice
from chic_register.pipeline.register import refuse_self_symmetric, register
from chic_register.pipeline.results import Registration, SkippedSlice, build_registration
from chic_register.pipeline.scaling import with_calibrated_scale
from chic_register.verify.pixels import verify_fit

#: A volume whose slices give no pose, with wide blobs: the pixels of this many slices, spread over those that
#: cross the fiducial, are fitted through the blurred model (CPU grows with them; 6 slices carry ~60 sections).
WIDE_SLICES = 6


def parse_slice_indices(tokens, n_slices: int, source: str = "--slices") -> list[int]:
    """Slice indices from tokens such as ``"5"``, ``"5-11"`` (inclusive), ``"-1"`` (the last); in order, no repeats.

    Raises :class:`ChicRegisterError` naming the bad token and what is allowed.
    """
    out: list[int] = []
    for tok in tokens:
        text = str(tok).strip()
        try:
            if "-" in text[1:]:  # a range; a leading '-' alone is a negative index
                cut = text.index("-", 1)
                a, b = int(text[:cut]), int(text[cut + 1:])
                if a > b:
                    raise ChicRegisterError(f"{source} {text}: a range runs from low to high (e.g. 5-11)")
                values = range(a, b + 1)
            else:
                values = [int(text)]
        except ValueError:
            raise ChicRegisterError(f"{source} {text}: not a slice index or range; use e.g. 5 or 5-11") from None
        for k in values:
            if not -n_slices <= k < n_slices:
                raise ChicRegisterError(f"{source} {text}: slice index {k} is outside 0..{n_slices - 1}")
            k %= n_slices
            if k not in out:
                out.append(k)
    return out


def register_volume(volume: Volume, geom: FiducialGeometry, indices=None, **options) -> Registration:
    """One pose from a volume's native k-slices.

    ``indices`` None: the pose fitted to every slice that holds enough of the
    frame (:func:`~chic_register.pipeline.every_slice.register_every_slice`;
    the others are listed with their reasons); where its blob centres give no
    pose, the sections' pixels: the volume's wide blobs through the blurred
    model, or each slice's section fit and verification
    (:func:`~chic_register.pipeline.register.register`). Else exactly those
    slices, each of which must lock. ``options`` go to
    :func:`~chic_register.pipeline.register.register`.
    """
    nk = volume.shape[0]
    ks = range(nk) if indices is None else indices
    slices = [volume.native_slice(k) for k in ks]
    opts = dataclasses.replace(options.get("options") or SolveOptions(),
                               **{k: v for k, v in options.items() if k not in _NOT_OPTIONS})
    opts = with_calibrated_scale(opts, geom)
    refuse_self_symmetric(geom, opts)  # before any work: no image can choose between the twins
    if indices is not None:
        return register(slices, geom, **options)
    try:
        return register_every_slice(slices, geom, opts, options.get("detect_options"), options.get("target_F_mm"))
    except NoLock as exc:
        if exc.detail.get("stage") == "joint":
            raise  # the slices agreed on a pose and its tests refused it: no other path would see more
        first = exc
    # no pose the slices' centres agree on, or centres no rigid pose fits: the sections' own pixels may still tell
    may_widen = opts.blurred_fit and opts.verify and not opts.centroid_model
    looked_wide = may_widen and _looks_wide(volume, geom)
    if looked_wide:  # merged neighbours in every slice: the pose from the voxels, fitted to the pixels
        try:
            wide = _register_wide(volume, geom, opts, options.get("target_F_mm"))
        except NoLock as exc:
            wide, first = None, exc  # a pose found from the voxels and refused says more than the centres
        if wide is not None:
            return wide
    try:
        return register(slices, geom, skip_failed=True, **options)
    except NoLock:
        if may_widen and not looked_wide:
            wide = _register_wide(volume, geom, opts, options.get("target_F_mm"))
            if wide is not None:
                return wide
        raise first from None


#: A volume whose sampled slices' blobs read this many times the channels' width (detect's ``width_mm``, median;
#: merged neighbours widen it: 1.15x blobs read ~1.5, 1.6x ~2.0) or that show blobs too merged to measure goes to
#: the wide-blob path first.
LOOKS_WIDE_RATIO = 1.8


def _looks_wide(volume: Volume, geom: FiducialGeometry) -> bool:
    """Whether about eight slices spread over the volume show blobs much wider than the channels."""
    d = float(np.median([t.diameter for t in geom.tubes]))
    nk = volume.shape[0]
    ratios = []
    for k in range(nk // 16, nk, max(1, nk // 8)):
        sl = volume.native_slice(k)
        b = detect_blobs(sl.pixels, sl.pixel_spacing_mm, d)
        if len(b):
            ratios.append(b.width_mm / d if math.isfinite(b.width_mm) else math.inf)
    return len(ratios) >= 2 and median(ratios) >= LOOKS_WIDE_RATIO


_NOT_OPTIONS = ("options", "detect_options", "target_F_mm")


def _register_wide(volume: Volume, geom: FiducialGeometry, opts: SolveOptions, target_F_mm=None):
    """A volume of wide blobs (merged neighbours in every slice, so no slice gives a pose): the pose from the
    voxels (:mod:`chic_register.guess.volume_search`), fitted to the pixels of :data:`WIDE_SLICES` spread slices through
    the blurred model (:mod:`chic_register.fit.blurred`) and verified on them. Every pose the voxels rate nearly
    as well (:data:`RIVAL_SHARE`) is fitted and verified too: two distinct poses that both verify are refused as
    ambiguous. None when the blobs are not wide or no pose is found (the slices' own reason stands);
    :class:`NoLock` when the poses found fail their checks."""
    t0 = time.perf_counter()
    model, geom_sha = prepare_geometry(geom)
    guesses = [g for g in volume_first_guesses(volume.voxels, volume.affine_lps, model) if near_prior(g[1], opts)]
    if not guesses:
        return None
    all_slices = [volume.native_slice(k) for k in range(volume.shape[0])]
    t1 = time.perf_counter()
    passed, tried, first_refusal, unfitted, rivals = None, [], None, [], []
    for score, X in guesses:
        if score < RIVAL_SHARE * guesses[0][0] or any(not _far(X, Y, model) for Y in tried):
            continue
        tried.append(X)
        try:  # the first pose that verifies is the answer's candidate; later ones are only fitted, as its rivals
            out = _fit_and_verify(geom, model, X, all_slices, opts, verify=passed is None)
        except NoLock as exc:
            first_refusal = first_refusal or exc
            if "residual_sigma" in exc.detail:  # fitted, then refused (verification, stretch, not converged): ranked
                rivals.append((exc.detail["residual_sigma"], X))
            else:  # no evidence against the pose: it could not be judged
                unfitted.append(score)
            continue
        if out is None:
            if passed is None and first_refusal is None:
                return None  # sharp sections, or too few slices: not this path's case
            unfitted.append(score)
        elif passed is None:
            passed = out
        else:
            rivals.append((out[-1].noise_sigma, out[0].T_F_from_scanner))
    if passed is None:
        raise first_refusal or NoLock("the volume's wide blobs: no pose found from the voxels fits the pixels")
    # a distinct pose whose blurred model leaves a residual variance under RIVAL_VARIANCE_RATIO times the answer's
    # (verified or not) means the pixels cannot tell them apart (a near-symmetric layout's turned twin: 1.14-2.05x)
    close = [n for n, Y in rivals if n ** 2 < RIVAL_VARIANCE_RATIO * passed[-1].noise_sigma ** 2
             and _far(Y, passed[0].T_F_from_scanner, model)]
    if close:
        raise NoLock(f"ambiguous fit: the volume's wide blobs fit two distinct poses with residuals "
                     f"{passed[-1].noise_sigma:.3g} and {close[0]:.3g}", {"n_tubes": passed[0].n_matched})
    if unfitted:  # a distinct pose the voxels rate nearly as well was neither fitted nor refused by the pixels
        raise NoLock(f"ambiguous fit: the volume's wide blobs fit a pose, but a distinct one the voxels rate nearly as "
                     f"well (centreline score {max(unfitted):.3f}) could not be fitted to the pixels to rule it out")
    best, seen, checks, skipped, blurred = passed
    t2 = time.perf_counter()
    used = {d.source for d in seen} | {s.source for s in skipped}
    skipped += [SkippedSlice(sl.source, f"not fitted: the volume's wide blobs were fitted on {len(seen)} slices "
                                        "spread over the fiducial") for sl in all_slices if sl.source not in used]
    order = {sl.source: k for k, sl in enumerate(all_slices)}
    skipped.sort(key=lambda s: order.get(s.source, 0))
    return build_registration(geom, model, geom_sha, best, seen, [None] * len(seen), checks, {}, skipped, opts,
                              target_F_mm, (t0, t1, t2), pixel_fit=blurred)


#: Poses from the voxels scoring at least this share of the best are fitted and verified as well.
RIVAL_SHARE = 0.93
#: Of two distinct verified poses, the other's residual variance must exceed the best's this many times.
RIVAL_VARIANCE_RATIO = 1.1


def _fit_and_verify(geom, model, X: np.ndarray, all_slices, opts: SolveOptions, verify: bool = True):
    """The pose near ``X`` (T_F_from_scanner) fitted through the blurred model to spread slices and verified:
    ``(fit, seen, checks, skipped, BlurredFit)`` (``seen``: the slices fitted, with their blobs); None when the blobs are not wide or too few slices cross
    the body; :class:`NoLock` when it does not converge or fails its verification (its detail then holds the fit's
    ``residual_sigma``). ``verify`` False: fitted only (``checks`` None)."""
    Ss_all = [sl.T_scanner_from_image() for sl in all_slices]
    crossing = [k for k in range(len(all_slices)) if _mid_body(model, X @ Ss_all[k])]
    if len(crossing) < 2:
        return None
    pick = sorted({crossing[int(round(i))] for i in np.linspace(0, len(crossing) - 1, min(WIDE_SLICES, len(crossing)))})
    seen = [DetectedSlice.of(all_slices[k], detect_blobs(all_slices[k].pixels, all_slices[k].pixel_spacing_mm,
                                                          model.diameter_mm), Ss_all[k]) for k in pick]
    xys, Ss = [d.xy_mm for d in seen], [d.T_scanner_from_image for d in seen]
    gate = 1.5 * float(model.diameter_mm.max())
    assign = [assign_blobs(*plane_crossings(model, X @ S)[0:4:3], xy, gate) for xy, S in zip(xys, Ss)]
    if blob_width_ratio(model, seen, assign) < WIDE_RATIO:
        return None  # sharp sections: the slices' own refusal is the answer
    for _ in range(2):  # from the voxels' pose; once more from where the pixels took it, if that was over 1 mm / 1 deg
        assign = [assign_blobs(*plane_crossings(model, X @ S)[0:4:3], xy, gate) for xy, S in zip(xys, Ss)]
        start = dataclasses.replace(refine(model, xys, Ss, X, gates_mm=(), final_iters=0, assign0=assign),
                                    T_F_from_scanner=X)
        best, precision, blurred = blurred_stage(model, start, seen, len(seen))  # NoLock: a stretch
        if precision is not None or blurred is None:
            break
        X = blurred.T_F_from_scanner
    if blurred is None:
        raise NoLock("the volume's wide blobs: fewer than six sections where the pose found from the voxels puts them")
    if precision is None:  # still moving: not a pose, but its residual ranks it
        raise NoLock("the volume's wide blobs: the pose found from the voxels did not converge when fitted to the "
                     "pixels of its slices through the blurred model",
                     {"residual_sigma": round(blurred.noise_sigma, 6)})
    skipped = []
    if not verify:
        return best, seen, None, skipped, blurred
    rivals = [[] for _ in seen]
    while True:
        try:
            checks = verify_fit(geom, model, best, rivals, seen, opts, precision=precision, name_slice=True,
                                psf_px=blurred.psf_px)
            return best, seen, checks, skipped, blurred
        except SliceRefused as exc:
            out = {j for j, _ in exc.refused}
            for j, reason in exc.refused:
                skipped.append(SkippedSlice(seen[j].source, reason.removeprefix(f"{seen[j].source}: ")))
            keep = [i for i in range(len(seen)) if i not in out]
            if len(keep) < 2:
                raise NoLock(f"the volume's wide blobs: the pose fitted to them fails in {len(out)} of its "
                             f"{len(seen)} slices; e.g. {exc.refused[0][1]}",
                             {"residual_sigma": round(blurred.noise_sigma, 6)}) from None
            seen = [seen[i] for i in keep]
            rivals = rivals[:len(keep)]
            best = dataclasses.replace(refine(model, [d.xy_mm for d in seen], [d.T_scanner_from_image for d in seen],
                                              best.T_F_from_scanner, gates_mm=(), final_iters=0,
                                              assign0=[best.assignments[i] for i in keep]),
                                       T_F_from_scanner=best.T_F_from_scanner)
        except NoLock as exc:  # the pose as a whole refused: its residual still ranks it against the others
            raise NoLock(exc.reason, {**exc.detail, "residual_sigma": round(blurred.noise_sigma, 6)}) from None


#: Slices used for a wide volume cross the axis this far (a share of the body's length) from both end faces: near
#: them tubes end inside blurred sections, which the verification rightly cannot tell from a wrong pose.
END_SHARE = 0.15


def _mid_body(model, T_F_from_I: np.ndarray) -> bool:
    """The slice crosses the fiducial's axis away from its end faces, with every tube's section in it."""
    depth = float(slice_angles(T_F_from_I).depth_mm)
    L = model.length_mm
    return END_SHARE * L <= depth <= (1 - END_SHARE) * L and bool(plane_crossings(model, T_F_from_I)[3].all())


def _far(T1: np.ndarray, T2: np.ndarray, model) -> bool:
    """Two poses another solution apart, not one pose found twice: more than a channel's width at a tube end, or
    more than 5 degrees."""
    L = model.length_mm
    rmax = float(np.max(model.axis_radius_mm)) if model.axis_radius_mm.size else 0.0
    pts = np.array([[rmax, 0, 0], [-rmax, 0, L], [0, rmax, L / 2], [0, 0, 0], [0, 0, L]])
    a = pts @ T1[:3, :3].T + T1[:3, 3]
    b = pts @ T2[:3, :3].T + T2[:3, 3]
    return (rotation_deg(T1[:3, :3], T2[:3, :3]) > 5.0
            or float(np.max(np.linalg.norm(a - b, axis=1))) > float(model.diameter_mm.max()))
