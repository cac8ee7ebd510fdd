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

import numpy as np

from chic_register.detect.dropout import fill_slice_dropouts
from chic_register.errors import AmbiguousFit, NoLock
from chic_register.fit.refine import Fit
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.pose import invert, near_prior
from chic_register.model.slices import Slice
from chic_register.model.symmetry import EXACT_SHARE, candidate_rotations, mismatches, prior_needed
from chic_register.model.tube_model import TubeModel, plane_crossings, prepare_geometry
from chic_register.options import SolveOptions
from chic_register.pipeline.detection import check_pixel_range, detect_slices
from chic_register.pipeline.joint import joint_fit, no_slice_locked
from chic_register.pipeline.locking import SliceRun, lock_slices
from chic_register.pipeline.refinement import refine_locked
from chic_register.pipeline.results import Registration, SkippedSlice, build_registration
from chic_register.pipeline.scaling import ImageScale, scale_stage, with_calibrated_scale
from chic_register.pipeline.verification import verify_refined
from chic_register.verify.rivals import check_rivals


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
    opts = with_calibrated_scale(opts, geom)
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
    refuse_seen_symmetric(geom, model, verified.best, [r.seen for r in verified.runs], verified.checks, opts,
                          refined.precision is None and opts.section_fit and not opts.centroid_model)
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


#: Mirror planes through the body centre a frame may be symmetric in: x, y, the two diagonals, and z (end for end).
MIRRORS = (("mirror x -> -x", np.diag([-1.0, 1.0, 1.0])), ("mirror y -> -y", np.diag([1.0, -1.0, 1.0])),
           ("mirror across x = y", np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])),
           ("mirror across x = -y", np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])),
           ("mirror z end for end", np.diag([1.0, 1.0, -1.0])))


def seen_symmetric_twins(geom: FiducialGeometry, model: TubeModel, fit: Fit, Ss, opts: SolveOptions) -> list:
    """Twin poses (``T_F_from_scanner``) the tubes the pose explains allow: a frame whose symmetry only its missing
    tubes break (a BRW frame without its one posterior diagonal, mirror-symmetric then) shows the pose and such a
    twin alike, and the missing tube, predicted elsewhere by each, cannot choose; the pixels must (the rival
    test). A rotation's twin is the frame turned about its centre; a mirror's, for one slice (``Ss``: the slices'
    ``T_scanner_from_image``), the frame mirrored and the slice seen from its other side. Only a pose that
    misses a tube it puts in the slices has any, and only twins within the prior that put no more tubes in the
    slices than the pose does (a twin that predicts tubes the image does not show explains it worse)."""
    seen = np.zeros(len(geom.tubes), bool)
    for a in fit.assignments:
        seen |= np.asarray(a) >= 0
    missed = sum(int(np.sum(np.asarray(ins) & (np.asarray(a) < 0))) for ins, a in zip(fit.inside, fit.assignments))
    if missed == 0 or seen.all() or seen.sum() < 3:
        return []
    predicted = sum(int(np.sum(ins)) for ins in fit.inside)
    sub = dataclasses.replace(geom, tubes=tuple(t for t, s in zip(geom.tubes, seen) if s), tool=None,
                              frame_coordinates=None)
    tol = EXACT_SHARE * min(t.diameter for t in geom.tubes)
    centre = np.array([0.0, 0.0, 0.5 * geom.body.length])
    T_sF = invert(fit.T_F_from_scanner)
    candidates = list(candidate_rotations(geom.body.length)) + (list(MIRRORS) if len(Ss) == 1 else [])
    twins = []
    for (what, M), (mismatch, _) in zip(candidates, mismatches(sub, np.stack([M for _, M in candidates]))):
        if mismatch > tol:
            continue
        twin = T_sF @ rigid_any(M, centre - M @ centre)
        if np.linalg.det(M) < 0:  # the slice seen from its other side: the plane's own reflection in the scanner
            S = np.asarray(Ss[0], float)
            n, o = S[:3, 2], S[:3, 3]
            H = np.eye(4)
            H[:3, :3] -= 2.0 * np.outer(n, n)
            H[:3, 3] = 2.0 * np.dot(n, o) * n
            twin = H @ twin
        twin_F_from_s = invert(twin)
        twin_predicted = sum(int(np.sum(plane_crossings(model, twin_F_from_s @ S, margin_mm=1e-9)[3])) for S in Ss)
        if twin_predicted <= predicted and near_prior(twin_F_from_s, opts):
            twins.append(twin_F_from_s)
    return twins


def refuse_seen_symmetric(geom: FiducialGeometry, model: TubeModel, fit: Fit, seen, checks, opts: SolveOptions,
                          section_pose: bool) -> None:
    """:class:`NoLock` ("ambiguous") when a twin of :func:`seen_symmetric_twins` explains the pixels nearly as
    well as the pose (the rival test of :func:`~chic_register.verify.rivals.check_rivals`); unverified, any twin
    refuses."""
    twins = seen_symmetric_twins(geom, model, fit, [d.T_scanner_from_image for d in seen], opts)
    if not twins:
        return
    if checks is None:
        raise AmbiguousFit("ambiguous fit: the tubes seen map onto themselves, and only the tubes not seen would "
                           "tell the pose from its twin; verify the pose against the pixels, or give --prior")
    check_rivals(geom, model, fit, twins, checks, seen, opts, section_pose)


def rigid_any(M: np.ndarray, t) -> np.ndarray:
    """The 4x4 of any 3x3 ``M`` (a rotation or a mirror) and translation ``t``."""
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = M, t
    return T


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
