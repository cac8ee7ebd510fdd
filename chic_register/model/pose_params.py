"""The parameters of a pose error, shared by the bound (:mod:`chic_register.precision.crlb`) and the solver's uncertainty.

A small perturbation ``delta = (rx, ry, rz, tx, ty, tz)`` of the fiducial:
a rotation ``r`` about F's axes through F's origin, then a translation
``t`` along them; a point ``p`` of F moves by ``r x p + t``. Covariances
are reported in :data:`PARAMETER_ORDER` (degrees, mm). This module holds
only that convention and the target error it implies, so that a one-shot
``solve`` reports its uncertainty without importing the bound's renderer.
"""

from __future__ import annotations

import math

import numpy as np

#: Order and units of the pose covariance (rotations about F's axes through its origin; translations along them).
PARAMETER_ORDER = ("rx_deg", "ry_deg", "rz_deg", "tx_mm", "ty_mm", "tz_mm")
PARAMETER_FRAME = "F (fiducial): rotation r (deg) about F's x, y, z axes through F's origin, then translation t (mm) along them; a point p of F moves by r x p + t"


def deg_mm_scale() -> np.ndarray:
    """Factors (6,) from (rad, mm) to the reported (deg, mm)."""
    return np.array([math.degrees(1.0)] * 3 + [1.0] * 3)


def target_jacobian(target_F_mm) -> np.ndarray:
    """d(target position in F)/d(delta) for delta in (rad, mm): ``[-[p]x | I]`` (3x6)."""
    p = np.asarray(target_F_mm, dtype=float)
    skew = np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])
    return np.hstack([-skew, np.eye(3)])


def tre_rms_mm(cov_deg_mm: np.ndarray, target_F_mm) -> float:
    """RMS 3-D error of a point of F under the pose covariance (6x6, order :data:`PARAMETER_ORDER`)."""
    s = deg_mm_scale()
    J = target_jacobian(target_F_mm)
    C = np.asarray(cov_deg_mm) / np.outer(s, s)  # back to rad, mm
    return float(math.sqrt(max(0.0, np.trace(J @ C @ J.T))))


def default_target(geom) -> tuple[float, float, float]:
    """The TRE point of a geometry: its tool tip if it has one, else the centre of the body on its axis."""
    tool = getattr(geom, "tool", None)
    if tool is not None:
        return tuple(float(v) for v in tool.tip_mm)
    return (0.0, 0.0, 0.5 * float(geom.body.length))
