"""Trust checks: when a fit is a pose to report, and the units its thresholds are counted in.

:func:`_check_trust` raises :class:`~chic_register.errors.NoLock` for a fit
whose residuals, matched tubes, depth or rivals leave doubt;
:func:`_resolution_mm` is the unit of a slice's thresholds (what its image
can resolve); :func:`_distinct` and :func:`_near_prior` compare poses.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from chic_register.detect.blobs import Blobs
from chic_register.errors import AmbiguousFit, NoLock
from chic_register.model.pose import slice_depth_mm
from chic_register.fit.refine import _Fit
from chic_register.model.slices import Slice
from chic_register.model.tube_model import TubeModel

if TYPE_CHECKING:
    from chic_register.pipeline.register import SolveOptions


def _pixel_mm(sl: Slice) -> float:
    return float(max(sl.pixel_spacing_mm))


def _to_xy_mm(blobs: Blobs, sl: Slice) -> np.ndarray:
    rc = blobs.centres_rc
    return np.stack([rc[:, 1] * sl.pixel_spacing_mm[1], rc[:, 0] * sl.pixel_spacing_mm[0]], axis=1)


def _resolution_mm(sl: Slice, blobs: Blobs) -> float:
    """The unit of a slice's trust thresholds (mm): what its image can resolve, never less than a pixel.

    A centre is as precise as the blob is sharp: blobs wider than the tube
    (blur, partial volume, fluid around a printed channel; ``blobs.width_mm``
    measured in the image) and thick slices (a tilted tube's section is
    smeared over the thickness) both widen the error, so the unit is the
    largest of the pixel, a 7.5th of the blob width and a 6th of the slice
    thickness (equal to the pixel for 3 mm tubes at 0.5 mm pixels and 2-3 mm slices).
    """
    w = blobs.width_mm if math.isfinite(blobs.width_mm) else 0.0
    return max(_pixel_mm(sl), w / 7.5, float(sl.slice_thickness_mm) / 6.0)


def _distinct(T1: np.ndarray, T2: np.ndarray, model: TubeModel, mm: float = 1.0, deg: float = 1.0) -> bool:
    """Two fiducial poses differ by more than ``mm`` at any tube end or by more than ``deg`` (1 mm, 1 degree)."""
    dR = T1[:3, :3].T @ T2[:3, :3]
    ang = math.degrees(math.acos(min(1.0, max(-1.0, (np.trace(dR) - 1) / 2))))
    if ang > deg:
        return True
    pts = model.probe_points_mm  # tube ends on the axis circle, the axis ends
    d = (pts @ T1[:3, :3].T + T1[:3, 3]) - (pts @ T2[:3, :3].T + T2[:3, 3])
    return float(np.sqrt(np.add.reduce(d * d, axis=1)).max()) > mm  # (np.linalg.norm's formula, less its checks)


def _rotation_deg(R1: np.ndarray, R2: np.ndarray) -> float:
    """Angle (degrees) of the rotation between two 3x3 rotations."""
    return math.degrees(math.acos(min(1.0, max(-1.0, (float(np.trace(R1.T @ R2)) - 1) / 2))))


def _near_prior(T_F_from_scanner: np.ndarray, opts: "SolveOptions") -> bool:
    """True without a prior, else when the pose's rotation lies within ``prior_max_deg`` of the prior's."""
    if opts.prior is None:
        return True
    R_prior = np.asarray(opts.prior, float)[:3, :3]  # R_scanner_from_fiducial
    return _rotation_deg(T_F_from_scanner[:3, :3].T, R_prior) <= opts.prior_max_deg


def _depth_tube_name(model: TubeModel) -> str:
    """What the tubes that tell the depth are, by their shape: 'helical', 'diagonal' or 'depth-coding' (both)."""
    kinds = {"helical" if model.is_helix[k] else "diagonal" for k in np.flatnonzero(model.depth_coding)}
    return kinds.pop() if len(kinds) == 1 else "depth-coding"


def _check_trust(fit: _Fit, others: list[_Fit], model: TubeModel, slices: list[Slice], opts: SolveOptions,
                 Ss: list | None = None, res_mm: list | None = None):
    """Raise :class:`NoLock` unless ``fit`` is a trustworthy pose.

    ``Ss``: the slices' T_scanner_from_image; ``res_mm``: the unit of each
    slice's thresholds (:func:`_resolution_mm`; default its pixel).
    """
    n_depth = 0
    px_unit = res_mm if res_mm is not None else [_pixel_mm(sl) for sl in slices]
    for j, sl in enumerate(slices):
        a = fit.assignments[j]
        px = px_unit[j]
        res = fit.residuals[j][a >= 0]
        n_depth += int(np.count_nonzero((a >= 0) & model.depth_coding))
        # (np.mean's sum and division, less its wrapper)
        if res.size and math.sqrt(float(np.add.reduce(res**2)) / res.size) > opts.max_rms_px * px:
            raise NoLock(
                f"{sl.source}: residual RMS {math.sqrt(float(np.mean(res ** 2))):.3f} mm exceeds "
                f"{opts.max_rms_px:g} px ({opts.max_rms_px * px:.3f} mm"
                + (")" if px == _pixel_mm(sl) else f", counting the image's resolution of {px:.2f} mm as a pixel)"),
                {"residual_rms_mm": round(math.sqrt(float(np.mean(res**2))), 4)})
        if res.size and res.max() > opts.max_residual_px * px:
            raise NoLock(f"{sl.source}: a tube residual of {res.max():.3f} mm exceeds "
                         f"{opts.max_residual_px:g} px", {"max_residual_mm": round(float(res.max()), 4)})
        T_F_from_I = fit.T_F_from_scanner @ (Ss[j] if Ss is not None else sl.T_scanner_from_image())
        depth_mm = slice_depth_mm(T_F_from_I)
        if not (0.0 <= depth_mm <= model.length_mm):
            raise NoLock(f"{sl.source}: the slice crosses the fiducial axis at depth {depth_mm:.1f} mm, "
                         f"outside the body [0, {model.length_mm:g}] mm",
                         {"depth_mm": round(float(depth_mm), 3)})
    need_depth = min(opts.min_depth_tubes, int(model.depth_coding.sum()))
    if fit.n_matched < opts.min_tubes or n_depth < need_depth:
        name = _depth_tube_name(model)
        raise NoLock(f"only {fit.n_matched} tubes matched ({n_depth} {name}); need at least "
                     f"{opts.min_tubes} with {need_depth} {name}", {"n_tubes": fit.n_matched})
    for other in others:
        if (other.n_matched >= fit.n_matched and other.n_matched >= opts.min_tubes
                and other.rms_mm <= opts.ambiguity_ratio * max(fit.rms_mm, 1e-3)
                and other.rms_mm <= opts.max_rms_px * min(px_unit)
                and _distinct(fit.T_F_from_scanner, other.T_F_from_scanner, model)):
            hint = "" if opts.prior is not None else "; an approximate orientation (prior, --prior) picks one"
            raise AmbiguousFit(f"ambiguous fit: two distinct poses match {fit.n_matched} and {other.n_matched} "
                         f"tubes with RMS {fit.rms_mm:.3f} and {other.rms_mm:.3f} mm{hint}",
                         {"n_tubes": fit.n_matched})
