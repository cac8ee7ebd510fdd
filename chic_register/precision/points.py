"""The position uncertainty of single points under a pose's covariance.

A registered pose ``T_scanner_from_fiducial`` is uncertain by ``exp(delta)``
on its right, ``delta`` of :data:`chic_register.model.pose_params.PARAMETER_ORDER`
(rotation about F's axes through F's origin in deg, then translation in mm;
covariance 6x6). A point held fixed in F (a frame coordinate, a target) then
moves in F's axes by ``r x p + t``; a point held fixed in the scanner moves in
F by the opposite. Either way its 3x3 covariance in F's axes is
``J C J^T`` with ``J = [-[p]x | I]`` (:func:`~chic_register.model.pose_params.target_jacobian`),
the same first-order propagation as the predicted TRE, whose RMS radius
it equals (:func:`~chic_register.model.pose_params.tre_rms_mm`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from chic_register.model.pose_params import deg_mm_scale, target_jacobian

#: The probability the reported sphere radius holds (``radius95_mm``).
RADIUS_LEVEL = 0.95


def point_covariance_F(cov_deg_mm: np.ndarray, point_F_mm) -> np.ndarray:
    """3x3 covariance (mm^2, F's axes) of a point ``point_F_mm`` (3,) under a pose covariance (6x6, deg and mm)."""
    s = deg_mm_scale()
    C = np.asarray(cov_deg_mm, dtype=float) / np.outer(s, s)  # rad, mm
    J = target_jacobian(point_F_mm)
    out = J @ C @ J.T
    return 0.5 * (out + out.T)


def rotate_covariance(cov_mm2: np.ndarray, R: np.ndarray) -> np.ndarray:
    """A 3x3 covariance seen in axes rotated by ``R`` (new from old): ``R C R^T``."""
    R = np.asarray(R, dtype=float)
    out = R @ np.asarray(cov_mm2, dtype=float) @ R.T
    return 0.5 * (out + out.T)


_CHI2_1_99, _CHI2_3_99 = 6.635, 11.345  # chi-square 0.99 quantiles, 1 and 3 degrees of freedom: bracket the root
#: Gauss-Legendre nodes on [-1, 1] of the nested quadrature in :func:`prob_inside_sphere`.
_GL_X, _GL_W = np.polynomial.legendre.leggauss(64)
_REACH_SIGMA = 9.0  # each standard normal integrated over +-9 (the rest weighs < 1e-18)


def _phi(z):
    return np.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi)


def _arc(a: np.ndarray):
    """Nodes ``z = a sin(theta)`` over ``|z| <= min(a, reach)`` and their weights ``phi(z) dz``; ``a`` (...,) ->
    (..., n). The sine substitution smooths the square-root edge of the ellipsoid's section."""
    top = np.arcsin(np.clip(_REACH_SIGMA / np.maximum(a, 1e-300), 0.0, 1.0))
    theta = top[..., None] * _GL_X
    z = a[..., None] * np.sin(theta)
    return z, _phi(z) * a[..., None] * np.cos(theta) * top[..., None] * _GL_W


def prob_inside_sphere(eigvals, radius2: float) -> float:
    """P(sum eigvals_i z_i^2 <= radius2) for three standard normals z: the probability that a Gaussian error of
    those covariance eigenvalues (largest first or in any order) lies within ``sqrt(radius2)`` of the estimate.

    Nested quadrature: the two largest axes numerically (sine substitution), the smallest in closed form (erf).
    """
    from scipy.special import erf  # deferred: only a mapped point's radius needs it (one-shot start-up)

    lam = np.sort(np.asarray(eigvals, dtype=float))[::-1]
    lam = np.maximum(lam, 1e-24 * lam[0])
    y = float(radius2)
    z1, w1 = _arc(np.array(math.sqrt(y / lam[0])))
    rem1 = np.maximum(y - lam[0] * z1 * z1, 0.0)  # (n,)
    z2, w2 = _arc(np.sqrt(rem1 / lam[1]))  # (n, n)
    rem2 = np.maximum(rem1[:, None] - lam[1] * z2 * z2, 0.0)
    inner = erf(np.sqrt(rem2 / (2.0 * lam[2])))
    return float(np.sum(w1 * np.sum(w2 * inner, axis=1)))


def sphere_radius_mm(cov_mm2: np.ndarray, level: float = RADIUS_LEVEL) -> float:
    """Radius (mm) of the sphere about the estimate that holds the true point with probability ``level``,
    for a Gaussian error of covariance ``cov_mm2`` (3x3): 2.796 sigma when the error is isotropic, 1.960 sigma
    when it lies along one axis."""
    lam = np.clip(np.linalg.eigvalsh(np.asarray(cov_mm2, dtype=float)), 0.0, None)
    top = float(lam.max())
    if not top > 0:
        return 0.0
    from scipy.optimize import brentq  # deferred: only a mapped point's radius needs it (one-shot start-up)

    lam = lam / top  # scale-free: solve the case whose largest eigenvalue is 1, then scale back
    # the largest axis alone needs 1.96^2 = 3.84 at 95 %; three isotropic unit axes 7.81 (chi-square(3)): brackets
    lo, hi = 0.5 * _CHI2_1_99, 2.0 * _CHI2_3_99 * float(lam.sum())
    r2 = brentq(lambda y: prob_inside_sphere(lam, y) - level, lo, hi, xtol=1e-12, rtol=1e-12)
    return math.sqrt(r2 * top)


@dataclass(frozen=True, eq=False)
class PointUncertainty:
    """A point's position uncertainty: ``covariance_mm2`` (3x3) in the axes its coordinates are given in."""

    covariance_mm2: np.ndarray

    @property
    def sigma_mm(self) -> np.ndarray:
        """1-sigma along each axis, (3,)."""
        return np.sqrt(np.clip(np.diag(self.covariance_mm2), 0.0, None))

    @property
    def rms_mm(self) -> float:
        """RMS 3-D error: ``sqrt(trace)`` (the predicted TRE of that point)."""
        return float(math.sqrt(max(0.0, float(np.trace(self.covariance_mm2)))))

    @property
    def radius95_mm(self) -> float:
        """Radius of the sphere holding the true point with probability 0.95 (:func:`sphere_radius_mm`)."""
        return sphere_radius_mm(self.covariance_mm2, RADIUS_LEVEL)

    def to_dict(self) -> dict:
        return {"sigma_mm": [round(float(v), 9) for v in self.sigma_mm],
                "rms_mm": round(self.rms_mm, 9),
                "radius95_mm": round(self.radius95_mm, 9),
                "covariance_mm2": [[float(v) for v in row] for row in self.covariance_mm2]}
