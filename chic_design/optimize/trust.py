"""Will the solver trust a candidate's poses? Its refusal test predicted from the Cramér-Rao bound.

``chic_register.pipeline.register.register`` refuses a pose whose own predicted error,
:data:`~chic_register.fit.checks.PRECISION_SIGMAS` (3) times the 1-sigma of
:func:`~chic_register.verify.pixels.pose_precision` (worst direction of the
rotation, and of the frame centre ``(0, 0, L/2)``'s displacement), exceeds
``SolveOptions.trust_rot_deg`` or ``trust_tre_mm``. A design whose slices the
solver refuses at the required poses is useless, however good its bound, so
the optimiser predicts that estimate: the bound's worst-direction SDs at the
same two places (:func:`solver_sds`) times :data:`SOLVER_OVER_CRLB`, the
measured ratio of the solver's estimate to the bound.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from chic_register.fit.checks import PRECISION_SIGMAS
from chic_register.model.pose_params import deg_mm_scale, target_jacobian
from chic_register.options import SolveOptions

#: The solver's own 1-sigma estimate over the bound's worst-direction SD (benchmarks/calibrate_trust.py --draws 6
#: --seed 0: 182 locks of neuro at 0.5 mm / 2 mm and needle-guide-p01 at 0.3 mm / 1.5 mm, SNR 20, 1 and 3 slices,
#: tilt 0 and 15-20 deg): rotation median 1.27 (90th percentile 1.56, 95th 1.70, range 0.67-2.19), frame centre
#: median 1.23. It is above 1 because the solver fits section positions, not every pixel (an efficiency below 1), and takes the
#: residual scatter at its 90 % chi-square upper bound (x1.3-1.4 for 6-10 tubes); it varies from slice to slice
#: because that scatter is estimated from a dozen residuals. The median is the prediction: a design at the limit
#: has about half of its slices at the worst required pose refused; one well inside it, few.
SOLVER_OVER_CRLB = 1.27


@dataclass(frozen=True)
class TrustLimits:
    """The solver's default refusal test: ``sigmas`` times its 1-sigma error within these limits."""

    tre_mm: float
    rot_deg: float
    sigmas: float


def solver_limits() -> TrustLimits:
    """The limits as ``chic_register`` sets them today (``SolveOptions`` defaults, ``PRECISION_SIGMAS``)."""
    default = {f.name: f.default for f in fields(SolveOptions)}
    return TrustLimits(float(default["trust_tre_mm"]), float(default["trust_rot_deg"]), float(PRECISION_SIGMAS))


def solver_sds(cov_deg_mm, length_mm: float) -> tuple[float, float]:
    """Worst-direction 1-sigma of the frame centre's displacement (mm) and of the rotation (deg) of a pose
    covariance in :data:`chic_register.precision.crlb.PARAMETER_ORDER` (what ``pose_precision`` reports, from the bound)."""
    s = deg_mm_scale()
    C = np.asarray(cov_deg_mm, dtype=float) / np.outer(s, s)  # rad, mm
    J = target_jacobian((0.0, 0.0, 0.5 * float(length_mm)))
    tre = math.sqrt(max(float(np.linalg.eigvalsh(J @ C @ J.T).max()), 0.0))
    rot = math.degrees(math.sqrt(max(float(np.linalg.eigvalsh(C[:3, :3]).max()), 0.0)))
    return tre, rot


def predicted_solver_error(cov_deg_mm, length_mm: float, limits: TrustLimits) -> tuple[float, float]:
    """The solver's predicted ``limits.sigmas``-sigma (TRE at the centre mm, rotation deg) from a bound's covariance."""
    tre, rot = solver_sds(cov_deg_mm, length_mm)
    k = limits.sigmas * SOLVER_OVER_CRLB
    return k * tre, k * rot


def trust_reason(prec: dict, limits: TrustLimits) -> str | None:
    """One line when the worst required pose's predicted solver error breaks the limits, else None."""
    tre, rot = prec["solver_tre_mm"], prec["solver_rot_deg"]
    if tre <= limits.tre_mm and rot <= limits.rot_deg:
        return None
    z, t, a = prec["solver_worst_pose"]
    worst = (f"rotation {rot:.2f} deg > {limits.rot_deg:g} (x{rot / limits.rot_deg:.1f})" if rot > limits.rot_deg
             else f"rotation {rot:.2f} deg")
    worst += (f", centre TRE {tre:.2f} mm > {limits.tre_mm:g} (x{tre / limits.tre_mm:.1f})" if tre > limits.tre_mm
              else f", centre TRE {tre:.2f} mm")
    return (f"the solver would refuse it: predicted {limits.sigmas:g}-sigma error {worst} at depth {z:g} mm, "
            f"tilt {t:g} deg (CRLB x {SOLVER_OVER_CRLB:g})")


def trust_excess(prec: dict, limits: TrustLimits) -> float:
    """By how much (relative, 0 = within) the worse of the two predicted errors exceeds its limit."""
    return max(0.0, prec["solver_tre_mm"] / limits.tre_mm - 1.0, prec["solver_rot_deg"] / limits.rot_deg - 1.0)
