"""Ellipses of tube centres: the robust fit behind the paper's closed-form first guess.

A slice through a cylinder of tubes cuts them on an ellipse (semi-minor axis
the cylinder's radius, semi-major that over the cosine of the tilt);
:func:`fit_ellipse_robust` finds it among candidate blob centres with stray
ones, by RANSAC on 5-point conics (Fitzgibbon-Halir-Flusser least squares
for the refit). :mod:`chic_register.guess.hypotheses` turns it into poses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from chic_register.util.lapack import eig_vectors
from chic_register.util.lapack import solve as lapack_solve


@dataclass(frozen=True)
class Ellipse:
    """An ellipse in image mm: centre (2,), semi-axes ``a >= b`` (mm), major-axis angle ``phi`` (rad)."""

    centre: np.ndarray
    a: float
    b: float
    phi: float

    def points(self, n: int = 200) -> np.ndarray:
        """Outline points, shape (n, 2)."""
        t = np.linspace(0, 2 * np.pi, n)
        u, w = self.a * np.cos(t), self.b * np.sin(t)
        c, s = math.cos(self.phi), math.sin(self.phi)
        return self.centre + np.stack([u * c - w * s, u * s + w * c], axis=1)


def _conic_to_ellipse(coef: np.ndarray):
    """Conic coefficients (S, 6) [A, B, C, D, E, F] -> (centre (S,2), a, b, phi, valid)."""
    coef = coef * np.where(coef[:, 0] + coef[:, 2] < 0, -1.0, 1.0)[:, None]  # positive-definite form
    A, B, C, D, E, F = coef.T
    det = 4 * A * C - B * B
    valid = det > 1e-15
    det = np.where(valid, det, 1.0)
    cx = (B * E - 2 * C * D) / det
    cy = (B * D - 2 * A * E) / det
    Fc = A * cx * cx + B * cx * cy + C * cy * cy + D * cx + E * cy + F
    tr = A + C
    disc = np.sqrt(np.maximum((A - C) ** 2 + B * B, 0.0))
    l1, l2 = (tr - disc) / 2, (tr + disc) / 2  # l1 <= l2
    with np.errstate(divide="ignore", invalid="ignore"):
        a2, b2 = -Fc / l1, -Fc / l2
    valid &= (a2 > 0) & (b2 > 0) & np.isfinite(a2) & np.isfinite(b2)
    a = np.sqrt(np.where(valid, a2, 1.0))
    b = np.sqrt(np.where(valid, b2, 1.0))
    # major axis: eigenvector of the smaller eigenvalue l1 of [[A, B/2], [B/2, C]]
    phi = 0.5 * np.arctan2(B, A - C) + np.pi / 2
    return np.stack([cx, cy], axis=1), a, b, phi, valid


def _conic_to_ellipse_1(coef: np.ndarray):
    """One conic (6,) -> ``(centre (2,), a, b, phi)`` or None: :func:`_conic_to_ellipse` in scalar arithmetic."""
    A, B, C, D, E, F = (float(v) for v in coef)
    if A + C < 0:
        A, B, C, D, E, F = -A, -B, -C, -D, -E, -F
    det = 4 * A * C - B * B
    if not det > 1e-15:
        return None
    cx = (B * E - 2 * C * D) / det
    cy = (B * D - 2 * A * E) / det
    Fc = A * cx * cx + B * cx * cy + C * cy * cy + D * cx + E * cy + F
    tr = A + C
    disc = math.sqrt(max((A - C) ** 2 + B * B, 0.0))
    l1, l2 = (tr - disc) / 2, (tr + disc) / 2
    if l1 == 0 or l2 == 0:
        return None
    a2, b2 = -Fc / l1, -Fc / l2
    if not (a2 > 0 and b2 > 0 and math.isfinite(a2) and math.isfinite(b2)):
        return None
    phi = 0.5 * math.atan2(B, A - C) + math.pi / 2
    return np.array([cx, cy]), math.sqrt(a2), math.sqrt(b2), phi


def _sampson(coef: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """First-order geometric distance of points (N, 2) to conics (S, 6) -> (S, N)."""
    x, y = xy[:, 0][None], xy[:, 1][None]
    A, B, C, D, E, F = (coef[:, i : i + 1] for i in range(6))
    val = A * x * x + B * x * y + C * y * y + D * x + E * y + F
    gx = 2 * A * x + B * y + D
    gy = B * x + 2 * C * y + E
    return np.abs(val) / np.maximum(np.hypot(gx, gy), 1e-12)


def _design(xy: np.ndarray) -> np.ndarray:
    """Conic design rows ``[x x, x y, y y, x, y, 1]`` of points (..., 2) -> (..., 6) (np.stack's numbers, fewer
    calls)."""
    D = np.empty(xy.shape[:-1] + (6,))
    np.multiply(xy[..., _SQUARE_A], xy[..., _SQUARE_B], out=D[..., :3])
    D[..., 3:5] = xy
    D[..., 5] = 1.0
    return D


_SQUARE_A, _SQUARE_B = [0, 0, 1], [0, 1, 1]  # x x, x y, y y


def _lsq_conic(xy: np.ndarray) -> np.ndarray:
    """Least-squares ellipse (Fitzgibbon-Halir-Flusser) through points (N >= 5, 2) -> (6,); NaN when the scatter
    matrix is singular (or the eigen-solution fails)."""
    D = _design(xy)
    D1, D2 = D[:, :3], D[:, 3:]
    S1, S2, S3 = D1.T @ D1, D1.T @ D2, D2.T @ D2
    Tm = -lapack_solve(S3, S2.T)
    M = S1 + S2 @ Tm
    M = np.array([M[2] / 2, -M[1], M[0] / 2])
    if not math.isfinite(sum(M.ravel().tolist())):  # S3 singular (np.linalg.solve would raise)
        return np.full(6, np.nan)
    v = eig_vectors(M)
    cond = 4 * v[0] * v[2] - v[1] ** 2
    idx = np.flatnonzero(cond > 0)
    if idx.size == 0:
        return np.full(6, np.nan)
    a1 = v[:, idx[0]]
    return np.concatenate([a1, Tm @ a1])


def fit_ellipse_robust(xy_mm: np.ndarray, radius_mm: float, max_tilt_deg: float = 80.0,
                       tol_mm: float | None = None, rng_seed: int = 0, samples: int = 300):
    """Ellipse of tube centres among candidate points (N, 2), tolerant to outliers.

    The ellipse of a cylinder of radius ``radius_mm`` cut at tilt t has minor
    semi-axis ``radius_mm`` and major ``radius_mm / cos t``; only such
    ellipses are accepted. First all points are tried; if some do not fit,
    RANSAC on 5-point subsets picks the largest consistent set.
    Returns ``(Ellipse, inlier mask (N,))`` or ``None``.
    """
    N = xy_mm.shape[0]
    if N < 5:
        return None
    tol = tol_mm if tol_mm is not None else 0.1 * radius_mm
    mu = np.add.reduce(xy_mm, axis=0) / N  # (xy_mm.mean(axis=0)'s sum and division, less its wrapper)
    scale = radius_mm
    p = (xy_mm - mu) / scale  # well-conditioned units
    max_ratio = 1.0 / math.cos(math.radians(max_tilt_deg))

    def plausible(a, b):
        return (b > 0.75) & (b < 1.25) & (a / b < max_ratio)

    def refit(mask):
        coef = _lsq_conic(p[mask])
        if not np.all(np.isfinite(coef)):
            return None
        e = _conic_to_ellipse_1(coef)
        if e is None or not plausible(e[1], e[2]):
            return None
        dist = _sampson(coef[None], p)[0] * scale
        return coef, e, dist

    best = refit(np.ones(N, bool))
    if best is not None and (best[2] < tol).all():
        inl = np.ones(N, bool)
    else:
        rng = np.random.default_rng(rng_seed)
        idx = np.argsort(rng.random((samples, N)), axis=1)[:, :5]
        D = _design(p[idx])  # (S,5,6)
        _, _, vt = np.linalg.svd(D, full_matrices=True)
        coef = vt[:, -1, :]
        c, a, b, phi, valid = _conic_to_ellipse(coef)
        valid &= plausible(a, b)
        if not valid.any():
            return None
        dist = _sampson(coef, p) * scale
        inliers = (dist < tol) & valid[:, None]
        count = inliers.sum(axis=1)
        err = np.where(inliers, dist, 0).sum(axis=1)
        order = np.lexsort((err, -count))
        inl = inliers[order[0]]
        best = None
        for _ in range(3):
            if inl.sum() < 5:
                return None
            best = refit(inl)
            if best is None:
                return None
            new = best[2] < tol
            if np.array_equal(new, inl):
                break
            inl = new
        if best is None or inl.sum() < 5:
            return None
    _, (c, a, b, phi), _ = best
    return Ellipse(c * scale + mu, float(a * scale), float(b * scale), float(phi)), inl
