"""The registration's scale stage: the verified pose fitted again together with the image's scale.

Where the data show a scale (the F test of :func:`~chic_register.fit.scale.fit_scale` below
:data:`~chic_register.fit.checks.STRETCH_P`), the pose fitted with it is the answer: a rigid pose would have taken
part of the scale as a tilt. A scale beyond ``max_scale_error`` in the image plane (``max_slice_scale_error`` across
the slices) by more than its noise explains (:data:`SCALE_LIMIT_SIGMAS`) is refused as a wrong pixel (slice) spacing;
one whose fit moves the pose beyond the trust limits is refused as not separable from the pose. One slice measures its scale but cannot fit it: the registration says how
far an unmeasured scale would move the pose, and holds a scale of ``SolveOptions.scale_sd`` (a calibrated geometry
file's own, by default) in the pose's covariance.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from chic_register.detect.detected import DetectedSlice
from chic_register.errors import NoLock
from chic_register.fit.checks import STRETCH_P, TO_TWIST, worst_errors
from chic_register.fit.refine import Fit
from chic_register.fit.scale import ScaleFit, fit_scale, scaled_fit
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.tube_model import TubeModel, poses_distinct
from chic_register.options import SolveOptions

#: A scale is refused as a wrong spacing when it lies beyond its axis' limit by more than this many of its own
#: standard deviations (one-sided 1 %): few or thin-sliced volumes measure the slice direction's scale to 1-3 %, and
#: an estimate that only its noise puts past the limit is a scanner's, fitted with the pose. A wrong spacing (10-50 %
#: across the slices, several per cent in the plane) still lies far beyond.
SCALE_LIMIT_SIGMAS = 2.326


@dataclass(frozen=True)
class ImageScale:
    """The image's scale as the registration found it: per axis of ``axes`` (x: the columns, y: the rows, z: the
    slice spacing) its relative value and standard deviation, the F test's ``p`` (NaN: from a pixel fit's own
    test), whether the pose was fitted with it, and what it adds to the pose's covariance (6, 6, F's parameters).

    For one slice (the scale measured, not fitted): ``pose_sd_per_pct``, the
    pose's standard deviation ``(rotation deg, mm at the frame centre)`` that
    an unmeasured scale of 1 % SD per axis would add (:attr:`~chic_register.fit.scale.ScaleFit.unfitted_covariance`),
    and ``prior_sd``, the scale SD the registration was told (``SolveOptions.scale_sd``), whose share
    ``pose_covariance`` then holds."""

    axes: tuple[str, ...]
    scale: np.ndarray
    scale_sd: np.ndarray
    p: float
    fitted: bool
    pose_covariance: np.ndarray
    pose_sd_per_pct: tuple[float, float] | None = None
    prior_sd: float = 0.0

    @classmethod
    def of(cls, sf: ScaleFit, fitted: bool) -> ImageScale:
        return cls(sf.axes, sf.scale, sf.scale_sd, sf.p, fitted, sf.pose_covariance)

    @classmethod
    def of_pixel_fit(cls, blurred) -> ImageScale:
        """The stretch a :class:`~chic_register.fit.blurred.BlurredFit` measured (its pose is fitted at the spacing
        as given; a significant stretch beyond 2 % is refused there)."""
        return cls(("x", "y"), np.array(blurred.stretch), np.array(blurred.stretch_sd), math.nan, False,
                   np.zeros((6, 6)))

    def to_dict(self) -> dict:
        return {"axes": list(self.axes), "scale": [round(float(v), 6) for v in self.scale],
                "sd": [round(float(v), 6) for v in self.scale_sd],
                **({"p": float(self.p)} if math.isfinite(self.p) else {}), "fitted": self.fitted,
                **({"pose_sd_per_pct": {"rot_deg": round(self.pose_sd_per_pct[0], 4),
                                        "tre_mm": round(self.pose_sd_per_pct[1], 4)}}
                   if self.pose_sd_per_pct is not None else {}),
                **({"prior_sd": self.prior_sd} if self.prior_sd > 0 else {})}

    @property
    def widens(self) -> bool:
        """Whether :attr:`pose_covariance` belongs in the pose's covariance (a fitted scale, or a prior one)."""
        return self.fitted or self.prior_sd > 0


def scale_limit(axis: str, opts: SolveOptions) -> float:
    """The largest scale fitted along ``axis`` (x, y: the image plane; z: across the slices) rather than refused."""
    return opts.max_slice_scale_error if axis == "z" else opts.max_scale_error


def scale_stage(model: TubeModel, fit: Fit, seen: list[DetectedSlice], opts: SolveOptions) -> tuple[Fit, ImageScale | None]:
    """``(pose, scale)``: ``fit`` or, where the data show a scale, the pose fitted with it; :class:`NoLock` for a
    scale beyond ``opts.max_scale_error`` or one the pose cannot be told apart from."""
    if not opts.fit_scale:
        return fit, None
    sf = fit_scale(model, fit, seen)
    if sf is None:
        return fit, None
    if len(seen) < 2:  # one slice alone reads a stretch as a tilt: measured, not fitted; its effect on the pose told
        return fit, _one_slice_scale(model, sf, opts)
    if not sf.p < STRETCH_P:
        return fit, ImageScale.of(sf, False)
    limits = np.array([scale_limit(a, opts) for a in sf.axes])
    beyond = (np.abs(sf.scale) - limits) / np.maximum(np.asarray(sf.scale_sd, float), 1e-12)
    worst = int(np.argmax(beyond))
    if beyond[worst] > SCALE_LIMIT_SIGMAS:
        spacing, cause = (("slice spacing", "the gradients' non-linearity across the slices")
                          if sf.axes[worst] == "z" else ("pixel spacing", "a scanner's calibration or a print"))
        raise NoLock(f"the image's scale along {sf.axes[worst]} is {100 * sf.scale[worst]:+.2f} % "
                     f"(+-{100 * sf.scale_sd[worst]:.2f}), beyond the {100 * limits[worst]:g} % {cause} explains: "
                     f"check the {spacing} (--max-scale-error sets the limits)", {"scale": sf.to_dict()})
    if poses_distinct(sf.T_F_from_scanner, fit.T_F_from_scanner, model, opts.trust_tre_mm, opts.trust_rot_deg):
        raise NoLock("the image's scale cannot be told apart from the pose: fitted with it, the pose moves beyond "
                     f"the trust limits ({opts.trust_tre_mm:g} mm, {opts.trust_rot_deg:g} deg)", {"scale": sf.to_dict()})
    return scaled_fit(model, fit, seen, sf), ImageScale.of(sf, True)


def _one_slice_scale(model: TubeModel, sf: ScaleFit, opts: SolveOptions) -> ImageScale:
    """One slice's :class:`ImageScale`: measured, with the pose's sensitivity to an unmeasured scale and, for
    ``opts.scale_sd`` > 0, that prior's share of the pose's covariance."""
    out = ImageScale.of(sf, False)
    per_pct = sf.unfitted_covariance * 0.01 ** 2
    tre, rot = worst_errors(per_pct * np.outer(TO_TWIST, TO_TWIST), np.array([0.0, 0.0, 0.5 * model.length_mm]))
    sd = opts.scale_sd or 0.0
    cov = sf.unfitted_covariance * sd ** 2 if sd > 0 else out.pose_covariance
    return dataclasses.replace(out, pose_covariance=cov, pose_sd_per_pct=(rot, tre), prior_sd=float(sd))


def with_calibrated_scale(opts: SolveOptions, geom: FiducialGeometry) -> SolveOptions:
    """``opts`` with ``scale_sd`` resolved: as given, else the geometry file's calibration's
    (:func:`calibrated_scale_sd`)."""
    return opts if opts.scale_sd is not None else dataclasses.replace(opts, scale_sd=calibrated_scale_sd(geom))


def calibrated_scale_sd(geom: FiducialGeometry) -> float:
    """The in-plane scale SD left after a geometry file's calibration (``source.calibration``,
    :mod:`chic_register.studies.scale_calibration`), 0 for an uncalibrated file: the calibration factor's own SD
    and, in quadrature, how far the calibration scan's columns and rows stood from the one factor it recorded (a
    scanner's gradients differ per axis; the file can hold only their mean)."""
    record = (geom.source or {}).get("calibration")
    if not isinstance(record, dict):
        return 0.0
    sd, factor = record.get("factor_sd"), record.get("factor")
    if not (isinstance(sd, (int, float)) and math.isfinite(sd) and sd > 0):
        return 0.0
    spread = 0.0
    seen = (record.get("image_scale") or {}).get("scale") if isinstance(record.get("image_scale"), dict) else None
    if isinstance(factor, (int, float)) and factor > 0 and isinstance(seen, list) and len(seen) >= 2 and all(
            isinstance(v, (int, float)) and math.isfinite(v) for v in seen[:2]):
        mean = 1.0 / float(factor) - 1.0  # the factor registers a scale correction of this size
        spread = max(abs(float(v) - mean) for v in seen[:2])
    return math.hypot(float(sd), spread)
