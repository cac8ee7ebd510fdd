"""The registration's lock stage: each slice's own pose, from its blobs alone or tracked from another slice's.

:class:`SliceRun` carries one slice through the registration's stages;
:func:`lock_slices` fills in each slice's own fit (or why it has none).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from chic_register.detect.detected import DetectedSlice
from chic_register.errors import AmbiguousFit, NoLock
from chic_register.fit.lock import lock_slice
from chic_register.fit.refine import Fit, unexplained_tubes
from chic_register.guess.ellipse import Ellipse
from chic_register.model.tube_model import TubeModel
from chic_register.options import SolveOptions
from chic_register.pipeline.detection import second_look, worth_flattening
from chic_register.pipeline.joint import solve_order, track_pose
from chic_register.pipeline.results import SkippedSlice
from chic_register.verify.trust import check_trust


@dataclass(eq=False)
class SliceRun:
    """One slice through a registration: what was detected in it, its own fit, and why it was left out.

    ``fit``: the slice's own pose (its assignment and residuals), None when
    it did not lock; ``rivals``: the other fits of the slice alone that came
    close (for the verification); ``undecided``: alone it fits two distinct
    poses, and the series decides; ``skipped``: why it was left out.
    """

    index: int
    seen: DetectedSlice
    fit: Fit | None = None
    ellipse: Ellipse | None = None
    rivals: list[Fit] = field(default_factory=list)
    undecided: bool = False
    skipped: SkippedSlice | None = None


def lock_slices(seen: list[DetectedSlice], model: TubeModel, opts: SolveOptions, skip_failed: bool,
                detect_options: dict | None = None) -> list[SliceRun]:
    """Every slice's own fit, in :func:`~chic_register.pipeline.joint.solve_order`.

    Without ``skip_failed`` a slice that does not lock is :class:`NoLock`
    for the whole registration; with it (a volume's slices) it is marked
    skipped, and once one slice has locked the next are first tracked from
    its pose.
    """
    runs = [SliceRun(j, d) for j, d in enumerate(seen)]
    anchor = None
    for j in solve_order([d.xy_mm for d in seen], model, skip_failed):
        run = runs[j]
        d = run.seen
        if anchor is not None:
            run.fit = track_pose(model, d.xy_mm, d.T_scanner_from_image, anchor, d.slice, opts, d.resolution_mm)
            if run.fit is not None:
                continue
        try:
            _lock_run(run, model, opts, len(seen), skip_failed, detect_options)
        except NoLock as exc:
            source = d.source
            reason = exc.reason if exc.reason.startswith(f"{source}: ") else f"{source}: {exc.reason}"
            if skip_failed:
                run.skipped = SkippedSlice(source, reason[len(source) + 2:])
                continue
            if len(seen) > 1:
                raise NoLock(reason, exc.detail) from None
            raise
        if skip_failed and anchor is None:
            anchor = run.fit.T_F_from_scanner
    return runs


def _lock_run(run: SliceRun, model: TubeModel, opts: SolveOptions, n_slices: int, skip_failed: bool,
              detect_options: dict | None) -> None:
    """One slice locked on its own blobs (``run.fit``, ``ellipse``, ``rivals``), or :class:`NoLock`."""
    d = run.seen
    try:
        fits, ellipse = lock_slice(model, d.xy_mm, d.T_scanner_from_image, opts, d.resolution_mm, d.blobs.contrast)
        check_trust(fits[0], fits[1:], model, [d.slice], opts, [d.T_scanner_from_image], [d.resolution_mm])
    except AmbiguousFit as exc:
        if n_slices == 1 and opts.verify and not skip_failed:
            # two poses fit the blob centres about as well: the pixels decide (the verification's rival test, to
            # which fits[1:] go), the best held to the rest of the trust checks
            check_trust(fits[0], [], model, [d.slice], opts, [d.T_scanner_from_image], [d.resolution_mm])
        elif n_slices == 1 or skip_failed:
            raise exc
        else:
            run.undecided = True  # the fit and its rivals are all kept: the joint fit tries each
    except NoLock as first:
        if (detect_options or {}).get("flatten_background") or not worth_flattening(d.blobs, model, d.slice.pixels):
            raise first
        fits, ellipse = _second_look(run, model, opts, detect_options, first)
    run.fit, run.ellipse, run.rivals = fits[0], ellipse, fits[1:]


def _second_look(run: SliceRun, model: TubeModel, opts: SolveOptions, detect_options: dict | None,
                 first: NoLock) -> tuple[list[Fit], Ellipse | None]:
    """The slice's fits on its flattened image (``run.seen`` replaced by that detection), held to explaining
    (nearly) every tube; ``first``, the plain image's reason, when they fail."""
    flat = second_look(run.seen, model, detect_options)
    try:
        fits, ellipse = lock_slice(model, flat.xy_mm, flat.T_scanner_from_image, opts, flat.resolution_mm,
                                   flat.blobs.contrast)
        check_trust(fits[0], fits[1:], model, [flat.slice], opts, [flat.T_scanner_from_image], [flat.resolution_mm])
        if unexplained_tubes(fits[0]) > 1:
            raise NoLock("more than one predicted tube unexplained on the flattened image")
    except NoLock as flat_reason:
        if run.seen.xy_mm.shape[0] < opts.min_tubes <= flat.xy_mm.shape[0] or (
                run.seen.xy_mm.shape[0] < flat.xy_mm.shape[0] < opts.min_tubes):
            raise flat_reason from None  # the plain image had too few candidates to say anything
        raise first from None  # the plain image's reason says more
    run.seen = flat
    return fits, ellipse

