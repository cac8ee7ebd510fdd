"""What a registration returns: the pose, one result per slice used, the slices left out and why.

:func:`build_registration` assembles a :class:`Registration` from a verified
fit, with the pose's uncertainty (and the ``max_tre_mm`` refusal).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from chic_register.detect.detected import DetectedSlice
from chic_register.errors import NoLock
from chic_register.fit.checks import check_noise_precision
from chic_register.fit.refine import Fit
from chic_register.guess.ellipse import Ellipse
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.pose import invert, slice_angles
from chic_register.model.tube_model import TubeModel, plane_crossings
from chic_register.options import SolveOptions
from chic_register.precision.uncertainty import (
    pixel_fit_uncertainty,
    position_covariance,
    registration_uncertainty,
    target_point,
)
from chic_register.verify.pixels import section_model_error_mm


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
    scale: object = field(repr=False, default=None)  # chic_register.pipeline.scaling.ImageScale

    def to_dict(self) -> dict:
        """JSON-ready object, docs/interfaces.md section 4 plus extra keys (``covariance``, ``noise``,
        ``target_F_mm``, ``predicted_tre_mm``: :meth:`~chic_register.precision.uncertainty.PoseUncertainty.to_dict`)."""
        return {
            "status": self.status,
            "T_scanner_from_fiducial": [[float(v) for v in row] for row in self.T_scanner_from_fiducial],
            "slices": [s.to_dict() for s in self.slices],
            "n_slices_used": len(self.slices),
            "skipped_slices": [s.to_dict() for s in self.skipped],
            "timing_ms": {k: round(v, 3) for k, v in self.timing_ms.items()},
            "geometry": {"name": self.geometry_name, "sha256": self.geometry_sha256},
            **({"scale": self.scale.to_dict()} if self.scale is not None else {}),
            **(self.uncertainty.to_dict() if self.uncertainty is not None else {}),
        }


def build_registration(geom: FiducialGeometry, model: TubeModel, geom_sha: str, best: Fit, seen: list[DetectedSlice],
                       ellipses, checks, filled, skipped, opts: SolveOptions, target_F_mm, times,
                       pixel_fit=None, scale=None, uncertainty=None) -> Registration:
    """The :class:`Registration` of a verified fit ``best`` on the slices ``seen``: per-slice results, the
    uncertainty (and the ``max_tre_mm`` test), timing from ``times`` (t0 start, t1 detected, t2 posed).
    ``ellipses``: per slice, its first guess's ellipse or None; ``checks``: per slice, the verification's
    :class:`~chic_register.verify.pixels.SliceCheck` (None unverified); ``filled``: {source: lost pixels filled};
    ``scale``: the :class:`~chic_register.pipeline.scaling.ImageScale` (when fitted with the pose, its effect on
    the pose widens the covariance before the precision tests).
    ``pixel_fit``: the :class:`~chic_register.fit.blurred.BlurredFit` the pose came from, whose covariance is then
    the pose's (the blob centres of wide blobs are biased by merged neighbours). ``uncertainty``: the pose's
    :class:`~chic_register.precision.uncertainty.PoseUncertainty` when the caller measured it (the every-slice
    path, from the scatter its residuals show); it is then held to the same tests."""
    t0, t1, t2 = times
    T_sf = invert(best.T_F_from_scanner)
    results = []
    for j, d in enumerate(seen):
        sl, S = d.slice, d.T_scanner_from_image
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
            blobs_rc=d.blobs.centres_rc,
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
            unc = pixel_fit_uncertainty(pixel_fit, seen, target)
            m = section_model_error_mm(checks) if checks else 0.0
            if m > 0:  # where the sections really lie, beyond the pixels' noise (a real scan: 0.1-0.5 mm)
                unc = unc.widened(position_covariance(model, best, seen, m), "sections' model error")
        else:
            unc = uncertainty if uncertainty is not None else registration_uncertainty(
                model, best, seen, target, "centroid" if not opts.centroid_model else "template (centroid covariance)")
            if scale is not None and scale.widens:
                unc = unc.widened(scale.pose_covariance, "image scale" if scale.fitted else "a-priori scale")
            if opts.verify:
                check_noise_precision(unc, model, opts,
                                      scale_prior=scale is not None and scale.widens and not scale.fitted)
        if unc.predicted_tre_mm > opts.max_tre_mm:
            raise NoLock(f"imprecise: predicted TRE {unc.predicted_tre_mm:.3f} mm at "
                         f"({', '.join(f'{v:g}' for v in unc.target_F_mm)}) exceeds {opts.max_tre_mm:g} mm",
                         {"code": "imprecise", "predicted_tre_mm": round(unc.predicted_tre_mm, 4),
                          "max_tre_mm": opts.max_tre_mm})
    t4 = time.perf_counter()
    timing = {"detect": (t1 - t0) * 1e3, "pose": (t2 - t1) * 1e3, "uncertainty": (t4 - t3) * 1e3,
              "total": (t4 - t0) * 1e3}
    return Registration("ok", T_sf, tuple(results), timing, geom.name, geom_sha, tuple(skipped),
                        unc if opts.uncertainty or math.isfinite(opts.max_tre_mm) else None, scale)
