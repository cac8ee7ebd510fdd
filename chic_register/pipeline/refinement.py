"""The registration's refinement stage: the locked pose refitted on what the pixels say of each section.

Sharp sections are fitted one by one (:func:`~chic_register.fit.accuracy.section_refine`); blobs clearly wider
than the channels through a blurred model of all sections at once (:mod:`chic_register.fit.blurred`); the
centroid model on request (``SolveOptions.centroid_model``).
"""

from __future__ import annotations

from dataclasses import dataclass

from chic_register.detect.detected import DetectedSlice
from chic_register.detect.wide_blobs import blobs_wide
from chic_register.errors import NoLock
from chic_register.fit.accuracy import centroid_refine, section_refine
from chic_register.fit.refine import Fit
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.tube_model import TubeModel, poses_distinct
from chic_register.options import SolveOptions
from chic_register.verify.trust import check_trust


@dataclass(frozen=True)
class Refined:
    """The refined pose and what the verification needs to know of how it came about.

    ``best``: the pose to verify; ``locked``: the pose fitted to the blob
    centres, or the section fit's when that moved off it (``moved``);
    ``precision``: the pose's 1-sigma ``(TRE mm, rotation deg)`` when it was
    fitted to the pixels through the blurred model (``blurred``, its
    :class:`~chic_register.fit.blurred.BlurredFit`), else None.
    """

    best: Fit
    locked: Fit
    moved: bool = False
    precision: tuple[float, float] | None = None
    blurred: object | None = None


def refine_locked(model: TubeModel, geom: FiducialGeometry, fit: Fit, seen: list[DetectedSlice],
                  opts: SolveOptions) -> Refined:
    """``fit`` (the lock, on the blob centres) refitted on the sections' pixels, as ``opts`` asks."""
    refined = Refined(fit, fit)
    if opts.blurred_fit and not opts.centroid_model and blobs_wide(model, seen, fit.assignments):
        # the sections are blurred: the sharp section model does not describe them, a blurred one does
        from chic_register.fit.blurred import blurred_stage  # deferred: only wide blobs need it (one-shot start-up)

        best, precision, blurred = blurred_stage(model, fit, seen)
        refined = Refined(best, fit, precision=precision, blurred=blurred)
    elif opts.section_fit and not opts.centroid_model:
        refined = _section_stage(model, fit, seen, opts)
    if opts.centroid_model:
        corrected = centroid_refine(model, geom.tubes, refined.best, seen, opts)
        check_trust(corrected, [], model, [d.slice for d in seen], opts, [d.T_scanner_from_image for d in seen])
        if poses_distinct(corrected.T_F_from_scanner, refined.best.T_F_from_scanner, model):
            raise NoLock("the centroid model moved the pose by more than 1 mm or 1 degree: the fit is not stable",
                         {"n_tubes": corrected.n_matched})
        refined = Refined(corrected, refined.locked, refined.moved)
    return refined


def _section_stage(model: TubeModel, fit: Fit, seen: list[DetectedSlice], opts: SolveOptions) -> Refined:
    """The section fit of ``fit``, held to the trust checks; where it moves the pose by more than 1 mm or 1 deg
    it is a refusal, except for one verified slice, whose section fit's pose is then the one verified."""
    fine = section_refine(model, fit, seen, opts)
    if fine is None:
        return Refined(fit, fit)
    check_trust(fine, [], model, [d.slice for d in seen], opts, [d.T_scanner_from_image for d in seen],
                [d.resolution_mm for d in seen])
    if not poses_distinct(fine.T_F_from_scanner, fit.T_F_from_scanner, model):
        return Refined(fine, fit)
    if not (opts.verify and len(seen) == 1):
        raise NoLock("the section fit moved the pose by more than 1 mm or 1 degree: the fit is not stable",
                     {"n_tubes": fine.n_matched})
    # blob centres pulled by damage (lost pixels, a blob beside a section) can put the blob fit 1-3 deg off where
    # the sections themselves are right: the section fit's pose is verified, never the blob fit's, and held to the
    # stricter precision of a pose refitted without its outlier sections (at 3 sigma, hunt seeds 3 and 5 each
    # locked one such pose 0.59 and 1.49 deg off)
    return Refined(fine, fine, moved=True)
