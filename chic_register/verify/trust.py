"""Trust checks: when a fit is a pose to report, and the units its thresholds are counted in.

:func:`check_trust` raises :class:`~chic_register.errors.NoLock` for a fit
whose residuals, matched tubes, depth or rivals leave doubt;
:func:`resolution_mm` is the unit of a slice's thresholds (what its image
can resolve); :func:`poses_distinct` and :func:`near_prior` compare poses.
"""

from __future__ import annotations

import math

import numpy as np

from chic_register.detect.blobs import pixel_mm
from chic_register.errors import AmbiguousFit, NoLock
from chic_register.fit.refine import Fit
from chic_register.model.pose import slice_depth_mm
from chic_register.model.slices import Slice
from chic_register.model.tube_model import TubeModel, poses_distinct
from chic_register.options import SolveOptions


def depth_tube_name(model: TubeModel) -> str:
    """What the tubes that tell the depth are, by their shape: 'helical', 'diagonal' or 'depth-coding' (both)."""
    kinds = {"helical" if model.is_helix[k] else "diagonal" for k in np.flatnonzero(model.depth_coding)}
    return kinds.pop() if len(kinds) == 1 else "depth-coding"


def check_trust(fit: Fit, others: list[Fit], model: TubeModel, slices: list[Slice], opts: SolveOptions,
                 Ss: list | None = None, res_mm: list | None = None):
    """Raise :class:`NoLock` unless ``fit`` is a trustworthy pose.

    ``Ss``: the slices' T_scanner_from_image; ``res_mm``: the unit of each
    slice's thresholds (:func:`resolution_mm`; default its pixel).
    """
    n_depth = 0
    px_unit = res_mm if res_mm is not None else [pixel_mm(sl) for sl in slices]
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
                + (")" if px == pixel_mm(sl) else f", counting the image's resolution of {px:.2f} mm as a pixel)"),
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
        name = depth_tube_name(model)
        raise NoLock(f"only {fit.n_matched} tubes matched ({n_depth} {name}); need at least "
                     f"{opts.min_tubes} with {need_depth} {name}", {"n_tubes": fit.n_matched})
    for other in others:
        if (other.n_matched >= fit.n_matched and other.n_matched >= opts.min_tubes
                and other.rms_mm <= opts.ambiguity_ratio * max(fit.rms_mm, 1e-3)
                and other.rms_mm <= opts.max_rms_px * min(px_unit)
                and poses_distinct(fit.T_F_from_scanner, other.T_F_from_scanner, model)):
            hint = "" if opts.prior is not None else "; an approximate orientation (prior, --prior) picks one"
            raise AmbiguousFit(f"ambiguous fit: two distinct poses match {fit.n_matched} and {other.n_matched} "
                         f"tubes with RMS {fit.rms_mm:.3f} and {other.rms_mm:.3f} mm{hint}",
                         {"n_tubes": fit.n_matched})
