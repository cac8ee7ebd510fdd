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

:func:`register` runs the stages in order, each in its own module of this
package: detection (:mod:`~chic_register.pipeline.detection`), each slice's
lock (:mod:`~chic_register.pipeline.locking`), the joint fit of several
slices (:mod:`~chic_register.pipeline.joint`), refinement on the sections'
pixels (:mod:`~chic_register.pipeline.refinement`), verification against
the image (:mod:`~chic_register.pipeline.verification`), the image's scale
fitted with the pose (:mod:`~chic_register.pipeline.scaling`) and the result
with its uncertainty (:mod:`~chic_register.pipeline.results`). A slice travels
through them as a :class:`~chic_register.pipeline.locking.SliceRun`.
"""

from __future__ import annotations

import dataclasses
import time

from chic_register.detect.dropout import fill_slice_dropouts
from chic_register.errors import AmbiguousFit, NoLock
from chic_register.fit.refine import Fit
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.slices import Slice
from chic_register.model.symmetry import EXACT_SHARE, prior_needed
from chic_register.model.tube_model import TubeModel, prepare_geometry
from chic_register.options import SolveOptions
from chic_register.pipeline.detection import check_pixel_range, detect_slices
from chic_register.pipeline.joint import joint_fit, no_slice_locked
from chic_register.pipeline.locking import SliceRun, lock_slices
from chic_register.pipeline.refinement import refine_locked
from chic_register.pipeline.results import Registration, SkippedSlice, build_registration
from chic_register.pipeline.scaling import ImageScale, scale_stage
from chic_register.pipeline.verification import verify_refined


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
    refuse_self_symmetric(geom, opts)
    t0 = time.perf_counter()
    slices, filled = fill_slice_dropouts(slices)
    lows = check_pixel_range(slices)
    model, geom_sha = prepare_geometry(geom)
    seen = detect_slices(slices, lows, model, detect_options)
    t1 = time.perf_counter()
    runs = lock_slices(seen, model, opts, skip_failed, detect_options)
    skipped = [r.skipped for r in runs if r.skipped is not None]
    best, runs = _joint(model, runs, opts, skip_failed, skipped)
    refined = refine_locked(model, geom, best, [r.seen for r in runs], opts)
    verified = verify_refined(geom, model, refined, runs, opts, skip_failed, skipped)
    seen = [r.seen for r in verified.runs]
    pixel_fit = refined.blurred if refined.precision is not None else None
    if pixel_fit is not None:
        best, scale = verified.best, ImageScale.of_pixel_fit(pixel_fit)
    else:
        best, scale = scale_stage(model, verified.best, seen, opts)
    t2 = time.perf_counter()
    return build_registration(geom, model, geom_sha, best, seen, [r.ellipse for r in verified.runs],
                              verified.checks, filled, skipped, opts, target_F_mm, (t0, t1, t2),
                              pixel_fit=pixel_fit, scale=scale)


def refuse_self_symmetric(geom: FiducialGeometry, opts: SolveOptions) -> None:
    """A frame that maps onto itself (z001) needs a prior: no image can choose; say so before any work."""
    if opts.prior is not None:
        return
    # only a symmetry within the channels' own print tolerance: a near-twin a pixel or so away (the needle guide's
    # half turn, 0.63 mm) is for the pixels and the rival poses to decide, as every other ambiguity
    why = prior_needed(geom, EXACT_SHARE * min(t.diameter for t in geom.tubes))
    if why:
        raise AmbiguousFit(why, {"needs_prior": True})


def _joint(model: TubeModel, runs: list[SliceRun], opts: SolveOptions, skip_failed: bool,
           skipped: list[SkippedSlice]) -> tuple[Fit, list[SliceRun]]:
    """The pose of the slices that locked, fitted jointly when there are several, and those slices (one that
    disagrees with the rest is left out when ``skip_failed``, and appended to ``skipped``)."""
    used = [r for r in runs if r.fit is not None]
    if not used:
        raise NoLock(no_slice_locked(skipped), {"n_skipped": len(skipped)})
    if len(used) == 1:
        return used[0].fit, used
    starts = [f.T_F_from_scanner for r in used if r.undecided for f in [r.fit, *r.rivals]]
    best, dropped = joint_fit(model, [r.seen for r in used], [r.fit for r in used], opts, skip_failed, starts)
    skipped += [SkippedSlice(used[j].seen.source, why, rms) for j, why, rms in dropped]
    gone = {j for j, _, _ in dropped}
    return best, [r for j, r in enumerate(used) if j not in gone]
