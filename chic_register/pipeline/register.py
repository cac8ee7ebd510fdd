"""The pose solver: detected tube centres in one or more slices -> the fiducial's 6-DOF pose.

The chain follows the paper, then goes further:

1. a robust ellipse fit of the blob centres (image mm) gives the centre of
   the cross-section, the tilt (``acos(minor/major)``) and the direction of
   the major axis (the azimuth, up to a two-fold sign);
2. "unrolling" every blob onto the cylinder (angle about the axis and height
   relative to the centre) for each of the four sign choices (which end of
   the major axis is up; which side the image is viewed from), the tubes that
   are straight and parallel to the axis fix the rotation about the axis (the
   twist) and the helices fix the depth (:meth:`HelixTube.z_at_angle`);
3. every resulting hypothesis is refined on all six degrees of freedom by
   Gauss-Newton on the model: the predicted crossings of every tube
   centreline of the geometry file with the image plane against the detected
   centres, with the blob-to-tube assignment re-solved (Hungarian) on the
   way, so extra and missing blobs are simply left unassigned;
4. trust checks turn every doubtful outcome into :class:`NoLock`.

Several slices are registered jointly: one ``T_scanner_from_fiducial`` fitted
to the correspondences of every slice. Nothing here assumes the CHIC layout:
the tube list, roles and angles all come from the geometry file.

This module is the public API (:func:`register`, :class:`SolveOptions`,
:class:`Registration`, :class:`SliceResult`); the stages live in
:mod:`~chic_register.model.tube_model` (model, crossings), :mod:`~chic_register.guess.hypotheses`
(first guesses), :mod:`~chic_register.fit.lock` (one slice's fits),
:mod:`~chic_register.fit.refine` (Gauss-Newton), :mod:`~chic_register.verify.trust`
(trust checks), :mod:`~chic_register.pipeline.joint` (several slices) and
:mod:`~chic_register.fit.accuracy` (section and centroid-model refinement). Their
names used elsewhere stay importable from here (the ``noqa: F401`` imports).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from chic_register.detect.blobs import Blobs, centres_xy_mm, detect_blobs, resolution_mm
from chic_register.detect.dropout import fill_slice_dropouts
from chic_register.detect.filters import SAFE_MAGNITUDE
from chic_register.detect.magnitude import refuse_signed
from chic_register.detect.noise import difference_sigma
from chic_register.detect.wide_blobs import blobs_wide
from chic_register.errors import AmbiguousFit, ImprecisePose, NoLock, SliceRefused
from chic_register.fit.accuracy import (
    centroid_refine,
    drop_section_outliers,
    section_refine,
)
from chic_register.fit.checks import (
    OUTLIER_PRECISION_SIGMAS,
    PRECISION_SIGMAS,
    check_noise_precision,
)
from chic_register.fit.lock import lock_slice
from chic_register.fit.refine import refine, unexplained_tubes
from chic_register.guess.ellipse import Ellipse
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.pose import invert, slice_angles
from chic_register.model.slices import Slice
from chic_register.model.symmetry import EXACT_SHARE, prior_needed
from chic_register.model.tube_model import (
    TubeModel,
    plane_crossings,
    poses_distinct,
    prepare_geometry,
)
from chic_register.options import SolveOptions
from chic_register.pipeline.joint import (
    joint_fit,
    no_slice_locked,
    solve_order,
    track_pose,
)
from chic_register.precision.uncertainty import pixel_fit_uncertainty, registration_uncertainty, target_point
from chic_register.verify.pixels import verify_fit
from chic_register.verify.trust import check_trust

# --------------------------------------------------------------------------- public API


@dataclass(frozen=True)
class SliceResult:
    """The registered pose of one slice relative to the fiducial.

    ``residuals_mm`` and ``assignment`` are keyed by tube id (matched tubes
    only); ``blobs_rc`` (N, 2) are all detected candidate centres (row, col),
    ``predicted_rc`` {tube id: (row, col)} the model's crossings, ``ellipse``
    the fitted ellipse of tube centres in image mm (or None).
    """

    source: str
    depth_mm: float
    tilt_deg: float
    azimuth_deg: float
    twist_deg: float
    residual_rms_mm: float
    residuals_mm: dict
    n_tubes: int
    assignment: dict
    blobs_rc: np.ndarray = field(repr=False, default=None)
    predicted_rc: dict = field(repr=False, default=None)
    ellipse: Ellipse | None = field(repr=False, default=None)
    missing_tubes: tuple[str, ...] = ()
    filled_pixels: int = 0  # lost pixels (scattered exact zeros) filled before the solve (chic_register.detect.dropout)

    def to_dict(self) -> dict:
        return {
            **({"missing_tubes": list(self.missing_tubes)} if self.missing_tubes else {}),
            **({"filled_pixels": self.filled_pixels} if self.filled_pixels else {}),
            "source": self.source,
            "depth_mm": round(self.depth_mm, 6),
            "tilt_deg": round(self.tilt_deg, 6),
            "azimuth_deg": round(self.azimuth_deg, 6),
            "twist_deg": round(self.twist_deg, 6),
            "residual_rms_mm": round(self.residual_rms_mm, 6),
            "n_tubes": self.n_tubes,
            "residuals_mm": {k: round(v, 6) for k, v in self.residuals_mm.items()},
            "assignment": dict(self.assignment),
        }


@dataclass(frozen=True)
class SkippedSlice:
    """A slice left out of a joint registration: why, and (for one that disagrees) its residual under the pose."""

    source: str
    reason: str
    residual_rms_mm: float | None = None

    def to_dict(self) -> dict:
        out = {"source": self.source, "reason": self.reason}
        if self.residual_rms_mm is not None:
            out["residual_rms_mm"] = round(self.residual_rms_mm, 6)
        return out


@dataclass(frozen=True)
class Registration:
    """A trusted pose: ``T_scanner_from_fiducial`` (4x4, mm) and one :class:`SliceResult` per slice."""

    status: str
    T_scanner_from_fiducial: np.ndarray
    slices: tuple[SliceResult, ...]
    timing_ms: dict
    geometry_name: str = ""
    geometry_sha256: str = ""
    skipped: tuple = ()
    uncertainty: object = field(repr=False, default=None)  # chic_register.precision.uncertainty.PoseUncertainty

    def to_dict(self) -> dict:
        """JSON-ready object, CONTRACT.md section 4 plus extra keys (``covariance``, ``noise``,
        ``target_F_mm``, ``predicted_tre_mm``: :meth:`~chic_register.precision.uncertainty.PoseUncertainty.to_dict`)."""
        return {
            "status": self.status,
            "T_scanner_from_fiducial": [[float(v) for v in row] for row in self.T_scanner_from_fiducial],
            "slices": [s.to_dict() for s in self.slices],
            "n_slices_used": len(self.slices),
            "skipped_slices": [s.to_dict() for s in self.skipped],
            "timing_ms": {k: round(v, 3) for k, v in self.timing_ms.items()},
            "geometry": {"name": self.geometry_name, "sha256": self.geometry_sha256},
            **(self.uncertainty.to_dict() if self.uncertainty is not None else {}),
        }


def register(slices: list[Slice], geom: FiducialGeometry, *, options: SolveOptions | None = None,
             detect_options: dict | None = None, skip_failed: bool = False, target_F_mm=None,
             **overrides) -> Registration:
    """Register one or more slices of the fiducial: one ``T_scanner_from_fiducial`` from all.

    Each slice is detected and solved on its own, then all correspondences
    are refined jointly. By default every slice must lock; with
    ``skip_failed`` (a volume's slices, most of which may miss the fiducial)
    slices that do not lock are skipped, later slices are first tried from
    the pose already found (tracking), and a slice that disagrees with the
    joint pose is dropped; each is listed in ``Registration.skipped`` with
    its reason. ``overrides`` set fields of :class:`SolveOptions` (e.g.
    ``max_rms_px=0.4``); ``detect_options`` go to
    :func:`~chic_register.detect.blobs.detect_blobs`. ``target_F_mm``: the
    point of F whose predicted TRE is reported (default: the geometry's tool
    tip, else the body's centre on its axis). Raises :class:`NoLock` with a
    reason when no trustworthy pose exists.
    """
    opts = dataclasses.replace(options or SolveOptions(), **overrides)
    if not slices:
        raise NoLock("no slices given")
    if opts.prior is None:  # a self-symmetric frame (z001): no image can choose; say so before any work

        # only a symmetry within the channels' own print tolerance: a near-twin a pixel or so away (the needle
        # guide's half turn, 0.63 mm) is for the pixels and the rival poses to decide, as every other ambiguity
        why = prior_needed(geom, EXACT_SHARE * min(t.diameter for t in geom.tubes))
        if why:
            raise AmbiguousFit(why, {"needs_prior": True})
    t0 = time.perf_counter()
    slices, filled = fill_slice_dropouts(slices)
    lows = _check_pixel_range(slices)
    model, geom_sha = prepare_geometry(geom)
    blob_sets, xys = [], []
    for sl, lo in zip(slices, lows):
        b = detect_blobs(sl.pixels, sl.pixel_spacing_mm, model.diameter_mm, **(detect_options or {}))
        refuse_signed(sl.pixels, b, sl.source, lo)
        blob_sets.append(b)
        xys.append(centres_xy_mm(b, sl))
    t1 = time.perf_counter()
    Ss = [sl.T_scanner_from_image() for sl in slices]
    res_mm = [resolution_mm(sl, b) for sl, b in zip(slices, blob_sets)]
    per_slice = [None] * len(slices)
    rivals = [[] for _ in slices]  # per slice: the distinct fits that came close (for the verification)
    skipped = []
    anchor = None
    undecided = []  # slices of a series that alone fit two distinct poses: the series decides (joint.py)
    for j in solve_order(xys, model, skip_failed):
        sl, xy, S = slices[j], xys[j], Ss[j]
        if anchor is not None:
            fit = track_pose(model, xy, S, anchor, sl, opts, res_mm[j])
            if fit is not None:
                per_slice[j] = (fit, None)
                continue
        try:
            try:
                fits, ell = lock_slice(model, xy, S, opts, res_mm[j])
                check_trust(fits[0], fits[1:], model, [sl], opts, [S], [res_mm[j]])
            except AmbiguousFit:
                if len(slices) == 1 and opts.verify and not skip_failed:
                    # two poses fit the blob centres about as well: the pixels decide (the verification's rival
                    # test, to which fits[1:] go), the best held to the rest of the trust checks
                    check_trust(fits[0], [], model, [sl], opts, [S], [res_mm[j]])
                elif len(slices) == 1 or skip_failed:
                    raise
                else:
                    undecided.append(j)  # fits[0] and its rivals are all kept: the joint fit tries each
            except NoLock as first:
                if ((detect_options or {}).get("flatten_background")
                        or not _worth_flattening(blob_sets[j], model, sl.pixels)):
                    raise
                # tissue touching the tubes or a dim side of the image: once more on the flattened image
                b = detect_blobs(sl.pixels, sl.pixel_spacing_mm, model.diameter_mm, flatten_background=True,
                                 **(detect_options or {}))
                xy2, res2 = centres_xy_mm(b, sl), resolution_mm(sl, b)
                try:
                    fits, ell = lock_slice(model, xy2, S, opts, res2)
                    check_trust(fits[0], fits[1:], model, [sl], opts, [S], [res2])
                    if unexplained_tubes(fits[0]) > 1:  # a second look is held to explaining (nearly) every tube
                        raise NoLock("more than one predicted tube unexplained on the flattened image")
                except NoLock:
                    raise first from None  # the plain image's reason says more
                xy = xys[j] = xy2
                blob_sets[j], res_mm[j] = b, res2
        except NoLock as exc:
            reason = exc.reason if exc.reason.startswith(f"{sl.source}: ") else f"{sl.source}: {exc.reason}"
            if skip_failed:
                skipped.append((j, SkippedSlice(sl.source, reason[len(sl.source) + 2:])))
                continue
            if len(slices) > 1:
                raise NoLock(reason, exc.detail) from None
            raise
        per_slice[j] = (fits[0], ell)
        rivals[j] = fits[1:]
        if skip_failed and anchor is None:
            anchor = fits[0].T_F_from_scanner
    skipped = [s for _, s in sorted(skipped, key=lambda js: js[0])]  # in the slices' order
    used = [j for j in range(len(slices)) if per_slice[j] is not None]
    if not used:
        raise NoLock(no_slice_locked(skipped), {"n_skipped": len(skipped)})
    starts = [f.T_F_from_scanner for j in undecided for f in [per_slice[j][0], *rivals[j]]]
    slices, xys, Ss, blob_sets, res_mm, per_slice, rivals = (
        [seq[j] for j in used] for seq in (slices, xys, Ss, blob_sets, res_mm, per_slice, rivals))
    if len(slices) == 1:
        best = per_slice[0][0]
    else:
        best, dropped = joint_fit(model, slices, xys, Ss, res_mm, per_slice, opts, skip_failed, starts)
        if dropped:
            skipped += [SkippedSlice(slices[j].source, why, rms) for j, why, rms in dropped]
            keep = [j for j in range(len(slices)) if j not in {d[0] for d in dropped}]  # the fit's slices, in order
            slices, xys, Ss, blob_sets, res_mm, per_slice, rivals = (
                [seq[j] for j in keep] for seq in (slices, xys, Ss, blob_sets, res_mm, per_slice, rivals))
    locked = best  # the pose fitted to the blob centres
    moved = False  # the section fit moved the pose more than 1 mm or 1 deg from the blob fit
    precision = None  # the pose's (TRE mm, rotation deg) 1-sigma when fitted to the pixels, not to positions
    blurred = None  # that pixel fit (chic_register.fit.blurred.BlurredFit)
    wide = opts.blurred_fit and not opts.centroid_model and blobs_wide(model, slices, blob_sets, best.assignments)
    if wide:  # the sections are blurred: the sharp section model does not describe them, a blurred one does
        from chic_register.fit.blurred import blurred_stage  # deferred: only wide blobs need it (one-shot start-up)

        best, precision, blurred = blurred_stage(model, best, xys, Ss, slices, blob_sets)
    elif opts.section_fit and not opts.centroid_model:
        fine = section_refine(model, best, xys, Ss, slices, blob_sets, opts)
        if fine is not None:
            check_trust(fine, [], model, slices, opts, Ss, res_mm)
            if poses_distinct(fine.T_F_from_scanner, best.T_F_from_scanner, model):
                if not (opts.verify and len(slices) == 1):
                    raise NoLock("the section fit moved the pose by more than 1 mm or 1 degree: the fit is not stable",
                                 {"n_tubes": fine.n_matched})
                # blob centres pulled by damage (lost pixels, a blob beside a section) can put the blob fit 1-3 deg
                # off where the sections themselves are right: the section fit's pose is verified, never the blob
                # fit's, and held to the stricter precision of a pose refitted without its outlier sections (at
                # 3 sigma, hunt seeds 3 and 5 each locked one such pose 0.59 and 1.49 deg off)
                moved = True
                locked = fine
            best = fine
    if opts.centroid_model:
        corrected = centroid_refine(model, geom.tubes, best, xys, Ss, slices, blob_sets, opts)
        check_trust(corrected, [], model, slices, opts, Ss)  # only ever stricter: the lock was checked above
        if poses_distinct(corrected.T_F_from_scanner, best.T_F_from_scanner, model):
            raise NoLock("the centroid model moved the pose by more than 1 mm or 1 degree: the fit is not stable",
                         {"n_tubes": corrected.n_matched})
        best = corrected
    checks = None
    if opts.verify:  # the last word: the pose proved against the pixels (chic_register.verify.pixels)
        try:
            while True:
                try:
                    checks = verify_fit(geom, model, best, rivals, slices, Ss, blob_sets, opts, precision=precision,
                                        name_slice=skip_failed,
                                        precision_sigmas=OUTLIER_PRECISION_SIGMAS if moved else PRECISION_SIGMAS)
                    break
                except SliceRefused as exc:  # a volume: those slices are left out, the rest verified again
                    out = {j for j, _ in exc.refused}
                    for j, reason in exc.refused:
                        prefix = f"{slices[j].source}: "
                        skipped.append(SkippedSlice(slices[j].source, reason.removeprefix(prefix)))
                    keep = [i for i in range(len(slices)) if i not in out]
                    if len(keep) == 0:
                        raise NoLock(no_slice_locked(skipped), {"n_skipped": len(skipped)}) from None
                    slices, xys, Ss, blob_sets, res_mm, per_slice, rivals = (
                        [seq[i] for i in keep] for seq in (slices, xys, Ss, blob_sets, res_mm, per_slice, rivals))
                    best = _only_slices(model, best, keep, xys, Ss)
                    locked = _only_slices(model, locked, keep, xys, Ss) if locked is not best else best
        except ImprecisePose:
            if opts.centroid_model or precision is not None:
                raise
            checks = None
            if best is not locked:
                # one section pulled off by damage (a blob on it, a stripe, lost pixels) spoils the scatter the
                # precision test sees: the pose refitted without it, held to a stricter precision
                checks, best = _without_outlier_sections(geom, model, best, rivals, slices, Ss, blob_sets, opts)
            if checks is None and not opts.refine_when_imprecise:
                raise
            if checks is None:
                if best is not locked:
                    # the precision test estimates the noise from the residual scatter, unweighted: the section
                    # fit's residuals along elongated sections make it pessimistic, so the centroid fit is judged
                    # as it is without the section fit (never a refusal the centroid-only solver would not make)
                    try:
                        checks = verify_fit(geom, model, locked, rivals, slices, Ss, blob_sets, opts)
                        best = locked
                    except ImprecisePose:
                        pass
        if checks is None:
            # verified but not precise enough from the centroids: fit the sections themselves (the accuracy
            # mode), then decide on that
            accurate = centroid_refine(model, geom.tubes, locked, xys, Ss, slices, blob_sets, opts)
            check_trust(accurate, [], model, slices, opts, Ss)
            if poses_distinct(accurate.T_F_from_scanner, best.T_F_from_scanner, model):
                raise NoLock("the accuracy refinement moved the pose by more than 1 mm or 1 degree: the fit is "
                             "not stable", {"n_tubes": accurate.n_matched}) from None
            best = accurate
            checks = verify_fit(geom, model, best, rivals, slices, Ss, blob_sets, opts)
    t2 = time.perf_counter()
    return build_registration(geom, model, geom_sha, best, slices, Ss, blob_sets, xys,
                         [e for _, e in per_slice], checks, filled, skipped, opts, target_F_mm,
                         (t0, t1, t2), pixel_fit=blurred if precision is not None else None)


def build_registration(geom: FiducialGeometry, model: TubeModel, geom_sha: str, best, slices, Ss, blob_sets, xys,
                  ellipses, checks, filled, skipped, opts: SolveOptions, target_F_mm, times,
                  pixel_fit=None) -> Registration:
    """The :class:`Registration` of a verified fit ``best`` (a ``refine._Fit``) on ``slices``: per-slice results,
    the uncertainty (and the ``max_tre_mm`` test), timing from ``times`` (t0 start, t1 detected, t2 posed).
    ``pixel_fit``: the :class:`~chic_register.fit.blurred.BlurredFit` the pose came from, whose covariance is then
    the pose's (the blob centres of wide blobs are biased by merged neighbours)."""
    t0, t1, t2 = times
    T_sf = invert(best.T_F_from_scanner)
    results = []
    for j, (sl, S) in enumerate(zip(slices, Ss)):
        T_F_from_I = best.T_F_from_scanner @ S
        ang = slice_angles(T_F_from_I)
        a = best.assignments[j]
        q, _, _, inside = plane_crossings(model, T_F_from_I)
        k = np.flatnonzero(a >= 0)
        res = best.residuals[j]
        px = sl.pixel_spacing_mm
        results.append(SliceResult(
            source=sl.source, depth_mm=float(ang.depth_mm), tilt_deg=float(ang.tilt_deg),
            azimuth_deg=float(ang.azimuth_deg), twist_deg=float(ang.twist_deg),
            residual_rms_mm=float(math.sqrt(np.mean(res[k] ** 2))),
            residuals_mm={model.ids[i]: float(res[i]) for i in k},
            n_tubes=int(k.size),
            assignment={model.ids[i]: int(a[i]) for i in k},
            blobs_rc=blob_sets[j].centres_rc,
            predicted_rc={model.ids[i]: (float(q[i, 1] / px[0]), float(q[i, 0] / px[1]))
                          for i in np.flatnonzero(inside)},
            ellipse=ellipses[j],
            missing_tubes=checks[j].missing if checks else (),
            filled_pixels=filled[sl.source] if sl.source in filled else 0,
        ))
    t3 = time.perf_counter()
    unc = None
    if opts.uncertainty or opts.verify or math.isfinite(opts.max_tre_mm):
        target = target_point(geom, target_F_mm)
        if pixel_fit is not None:
            unc = pixel_fit_uncertainty(pixel_fit, slices, blob_sets, target)
        else:
            unc = registration_uncertainty(model, best, xys, Ss, slices, blob_sets, target,
                                           "centroid" if not opts.centroid_model else "template (centroid covariance)")
            if opts.verify:
                check_noise_precision(unc, model, opts)
        if unc.predicted_tre_mm > opts.max_tre_mm:
            raise NoLock(f"imprecise: predicted TRE {unc.predicted_tre_mm:.3f} mm at "
                         f"({', '.join(f'{v:g}' for v in unc.target_F_mm)}) exceeds {opts.max_tre_mm:g} mm",
                         {"code": "imprecise", "predicted_tre_mm": round(unc.predicted_tre_mm, 4),
                          "max_tre_mm": opts.max_tre_mm})
    t4 = time.perf_counter()
    timing = {"detect": (t1 - t0) * 1e3, "pose": (t2 - t1) * 1e3, "uncertainty": (t4 - t3) * 1e3,
              "total": (t4 - t0) * 1e3}
    return Registration("ok", T_sf, tuple(results), timing, geom.name, geom_sha, tuple(skipped),
                        unc if opts.uncertainty or math.isfinite(opts.max_tre_mm) else None)


def _only_slices(model: TubeModel, fit, keep: list[int], xys, Ss):
    """``fit`` (at the same pose) on its slices ``keep`` only (``xys``, ``Ss``: theirs): assignments and residuals
    recomputed."""
    assign = [fit.assignments[i] for i in keep]
    out = refine(model, xys, Ss, fit.T_F_from_scanner, gates_mm=(), final_iters=0, assign0=assign)
    meas = None if fit.measurements is None else [fit.measurements[i] for i in keep]
    return dataclasses.replace(out, T_F_from_scanner=fit.T_F_from_scanner, measurements=meas)


def _without_outlier_sections(geom, model: TubeModel, fit, rivals, slices, Ss, blob_sets, opts):
    """``(checks, fit)`` of the section fit ``fit`` refitted without its outlier sections
    (:func:`~chic_register.fit.accuracy.drop_section_outliers`) when that pose verifies at
    :data:`~chic_register.fit.checks.OUTLIER_PRECISION_SIGMAS` and lies within 1 mm and 1 deg of ``fit``
    (:func:`~chic_register.verify.trust.poses_distinct`); else ``(None, fit)``."""
    dropped = drop_section_outliers(model, fit, Ss, opts)
    if dropped is fit or poses_distinct(dropped.T_F_from_scanner, fit.T_F_from_scanner, model):
        return None, fit
    try:
        return verify_fit(geom, model, dropped, rivals, slices, Ss, blob_sets, opts,
                          precision_sigmas=OUTLIER_PRECISION_SIGMAS), dropped
    except NoLock:
        return None, fit


#: Largest pixel magnitude the detector takes (its smoothing is in single precision).
MAX_PIXEL_MAGNITUDE = SAFE_MAGNITUDE


def _check_pixel_range(slices) -> list[float]:
    """Raise :class:`NoLock` for a slice whose pixels (lost ones already filled) reach beyond
    :data:`MAX_PIXEL_MAGNITUDE`: no MR image holds such values (a rescale slope or a conversion gone wrong).
    Returns each slice's smallest pixel (NaN when not computed: an empty or integer image)."""
    lows = []
    for sl in slices:
        img = np.asarray(sl.pixels)
        if img.size == 0 or img.dtype.kind != "f":
            lows.append(math.nan)
            continue
        lo, hi = float(np.minimum.reduce(img, axis=None)), float(np.maximum.reduce(img, axis=None))
        lows.append(lo)
        peak = max(abs(lo), abs(hi))
        if peak > MAX_PIXEL_MAGNITUDE and math.isfinite(lo) and math.isfinite(hi):
            raise NoLock(f"{sl.source}: pixel values reach {peak:.3g}, beyond the {MAX_PIXEL_MAGNITUDE:.3g} the detector "
                         "takes (single precision): rescale the image (a rescale slope or a unit conversion gone wrong?)",
                         {"pixel_peak": peak})
    return lows


def _worth_flattening(blobs: Blobs, model: TubeModel, pixels: np.ndarray) -> bool:
    """A slice whose detection may have lost tubes to their surroundings: something bright, but not a blank image.

    "Bright" is Otsu's split beyond four noise sigmas, as the detector measures the noise, or as the differences
    of neighbouring pixels do (:func:`chic_register.detect.noise.difference_sigma`): the detector's background mixes a
    dark and a bright region when a fiducial lies in a water bath (the median is the water, the tubes sit in dark
    plastic), and its noise then reads ten times too large. (A NaN estimate compares false.)"""
    if not (math.isfinite(blobs.threshold) and blobs.noise_sigma > 0 and len(blobs) < 3 * len(model.ids)):
        return False
    split = blobs.threshold - blobs.background
    return split > 4 * blobs.noise_sigma or split > 4 * difference_sigma(pixels)
