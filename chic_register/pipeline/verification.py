"""The registration's verification stage: the refined pose proved against the pixels, or refused.

:func:`verify_refined` runs :func:`~chic_register.verify.pixels.verify_fit`;
a volume's slices that fail their own checks are left out and the rest
verified again. A pose that verifies but is not precise enough is given two
more chances before the refusal stands: refitted without a section the
damage pulled off alone (held to
:data:`~chic_register.fit.checks.OUTLIER_PRECISION_SIGMAS`), and, with
``refine_when_imprecise``, the blob fit judged as it is, then the accuracy
mode's refinement.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from chic_register.detect.detected import DetectedSlice
from chic_register.errors import ImprecisePose, NoLock, SliceRefused
from chic_register.fit.accuracy import centroid_refine, drop_section_outliers, section_refine
from chic_register.fit.checks import OUTLIER_PRECISION_SIGMAS, PRECISION_SIGMAS
from chic_register.fit.refine import Fit, match_gate_mm, refine, unexplained_tubes
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.tube_model import TubeModel, poses_distinct
from chic_register.options import SolveOptions
from chic_register.pipeline.joint import no_slice_locked
from chic_register.pipeline.locking import SliceRun
from chic_register.pipeline.refinement import Refined
from chic_register.pipeline.results import SkippedSlice
from chic_register.verify.pixels import SliceCheck, verify_fit
from chic_register.verify.rivals import BetterRival
from chic_register.verify.trust import check_trust


@dataclass
class Verified:
    """The outcome of :func:`verify_refined`: the pose (``best``), the slices it holds for (``runs``) and their
    checks (None when verification is off); ``locked``: the blob fit's pose on those slices, the fallback of an
    imprecise section fit."""

    best: Fit
    locked: Fit
    runs: list[SliceRun]
    checks: list[SliceCheck] | None = None


def verify_refined(geom: FiducialGeometry, model: TubeModel, refined: Refined, runs: list[SliceRun],
                   opts: SolveOptions, skip_failed: bool, skipped: list[SkippedSlice]) -> Verified:
    """The refined pose verified on ``runs`` (slices left out are appended to ``skipped``), or :class:`NoLock`."""
    out = Verified(refined.best, refined.locked, runs)
    if not opts.verify:
        return out
    try:
        _verify_leaving_out(geom, model, refined, out, opts, skip_failed, skipped)
    except ImprecisePose as exc:
        if opts.centroid_model or refined.precision is not None:
            raise
        _when_imprecise(exc, geom, model, out, opts)
    if out.checks is None:
        _accuracy_refinement(geom, model, out, opts)
    return out


def _verify_leaving_out(geom, model, refined: Refined, out: Verified, opts: SolveOptions, skip_failed: bool,
                        skipped: list[SkippedSlice]) -> None:
    """Verify ``out.best``; slices a volume's verification refuses are left out (``out`` updated as it goes, so a
    later refusal finds the slices that remain) and the rest verified again."""
    sigmas = OUTLIER_PRECISION_SIGMAS if refined.moved else PRECISION_SIGMAS
    swapped = False
    while True:
        seen = [r.seen for r in out.runs]
        try:
            out.checks = verify_fit(geom, model, out.best, [r.rivals for r in out.runs], seen, opts,
                                    precision=refined.precision, name_slice=skip_failed, precision_sigmas=sigmas)
            return
        except BetterRival as exc:  # the pixels prefer a rival the blob centres rated equal: it is verified instead
            if swapped or refined.precision is not None:
                raise
            locked, best = _rival_fits(model, exc.T_F_from_scanner, seen, opts)
            if not _same_blobs(locked, out.best):  # another copy of the pattern (a ghost): a true ambiguity
                raise
            if unexplained_tubes(out.best) or unexplained_tubes(locked):
                # a tube either pose puts in the slice is not there: their model images differ by where each puts
                # it, not only by how they draw the rest, and the comparison cannot choose between them
                raise
            swapped = True
            out.locked, out.best = locked, best
        except SliceRefused as exc:  # a volume: those slices are left out, the rest verified again
            gone = {j for j, _ in exc.refused}
            for j, reason in exc.refused:
                skipped.append(SkippedSlice(seen[j].source, reason.removeprefix(f"{seen[j].source}: ")))
            keep = [i for i in range(len(seen)) if i not in gone]
            if not keep:
                raise NoLock(no_slice_locked(skipped), {"n_skipped": len(skipped)}) from None
            out.runs = [out.runs[i] for i in keep]
            out.best = _only_slices(model, out.best, keep, [r.seen for r in out.runs])
            out.locked = _only_slices(model, out.locked, keep, [r.seen for r in out.runs])
            # (the locked pose is refitted on its own even where it was the pose itself: it stays apart from it)


def _rival_fits(model: TubeModel, T_F_from_scanner, seen: list[DetectedSlice], opts: SolveOptions) -> tuple[Fit, Fit]:
    """``(blob fit, section fit)`` of a rival pose on the slices' blobs (the section fit: the blob fit where the
    sections cannot be fitted, or with the section fit off)."""
    gate = match_gate_mm(model, min(float(max(d.slice.pixel_spacing_mm)) for d in seen))
    locked = refine(model, [d.xy_mm for d in seen], [d.T_scanner_from_image for d in seen], T_F_from_scanner,
                    gates_mm=(gate, 0.6 * gate))
    fine = section_refine(model, locked, seen, opts) if opts.section_fit and not opts.centroid_model else None
    return locked, fine or locked


def _same_blobs(a: Fit, b: Fit) -> bool:
    """Do two fits match the same blobs in every slice (twins the blob centres cannot tell apart)?"""
    return all(set(x[x >= 0].tolist()) == set(y[y >= 0].tolist()) for x, y in zip(a.assignments, b.assignments))


def _when_imprecise(exc: ImprecisePose, geom, model, out: Verified, opts: SolveOptions) -> None:
    """A verified pose not precise enough to trust: without its outlier sections (when it is the section fit's),
    or, with ``refine_when_imprecise``, the blob fit judged as it is; ``exc`` stands otherwise. ``out.checks``
    stays None when only the accuracy refinement is left."""
    rivals, seen, locked = [r.rivals for r in out.runs], [r.seen for r in out.runs], out.locked
    if out.best is not locked:
        # one section pulled off by damage (a blob on it, a stripe, lost pixels) spoils the scatter the precision
        # test sees: the pose refitted without it, held to a stricter precision
        out.checks, out.best = _without_outlier_sections(geom, model, out.best, rivals, seen, opts)
    if out.checks is None and not opts.refine_when_imprecise:
        raise exc
    if out.checks is None and out.best is not locked:
        # the precision test estimates the noise from the residual scatter, unweighted: the section fit's residuals
        # along elongated sections make it pessimistic, so the centroid fit is judged as it is without the section
        # fit (never a refusal the centroid-only solver would not make)
        try:
            out.checks = verify_fit(geom, model, locked, rivals, seen, opts)
            out.best = locked
        except ImprecisePose:
            pass


def _accuracy_refinement(geom, model, out: Verified, opts: SolveOptions) -> None:
    """Verified but not precise enough from the centroids: the sections themselves fitted (the accuracy mode),
    and that pose verified."""
    seen = [r.seen for r in out.runs]
    accurate = centroid_refine(model, geom.tubes, out.locked, seen, opts)
    check_trust(accurate, [], model, [d.slice for d in seen], opts, [d.T_scanner_from_image for d in seen])
    if poses_distinct(accurate.T_F_from_scanner, out.best.T_F_from_scanner, model):
        raise NoLock("the accuracy refinement moved the pose by more than 1 mm or 1 degree: the fit is not stable",
                     {"n_tubes": accurate.n_matched})
    out.best = accurate
    out.checks = verify_fit(geom, model, accurate, [r.rivals for r in out.runs], seen, opts)


def _only_slices(model: TubeModel, fit: Fit, keep: list[int], seen: list[DetectedSlice]) -> Fit:
    """``fit`` (at the same pose) on its slices ``keep`` only (``seen``: theirs): assignments and residuals
    recomputed."""
    assign = [fit.assignments[i] for i in keep]
    out = refine(model, [d.xy_mm for d in seen], [d.T_scanner_from_image for d in seen], fit.T_F_from_scanner,
                 gates_mm=(), final_iters=0, assign0=assign)
    meas = None if fit.measurements is None else [fit.measurements[i] for i in keep]
    return dataclasses.replace(out, T_F_from_scanner=fit.T_F_from_scanner, measurements=meas)


def _without_outlier_sections(geom, model: TubeModel, fit: Fit, rivals, seen: list[DetectedSlice],
                              opts: SolveOptions) -> tuple[list[SliceCheck] | None, Fit]:
    """``(checks, fit)`` of the section fit ``fit`` refitted without its outlier sections
    (:func:`~chic_register.fit.accuracy.drop_section_outliers`) when that pose verifies at
    :data:`~chic_register.fit.checks.OUTLIER_PRECISION_SIGMAS` and lies within 1 mm and 1 deg of ``fit``
    (:func:`~chic_register.model.tube_model.poses_distinct`); else ``(None, fit)``."""
    dropped = drop_section_outliers(model, fit, [d.T_scanner_from_image for d in seen], opts)
    if dropped is fit or poses_distinct(dropped.T_F_from_scanner, fit.T_F_from_scanner, model):
        return None, fit
    try:
        return verify_fit(geom, model, dropped, rivals, seen, opts, precision_sigmas=OUTLIER_PRECISION_SIGMAS), dropped
    except NoLock:
        return None, fit
