"""A pixel's exact share of the inside of a section's edge, for the section model (:mod:`chic_register.fit.section`).

:func:`box_edge` is the share of a square pixel on the inside of a straight
edge and its slope; :func:`chord_m2` the second moment of the pixel's chord
along the edge, which corrects that share for the edge's curvature.
"""

from __future__ import annotations

import numpy as np


def box_edge(delta: np.ndarray, A: np.ndarray, B: np.ndarray):
    """Share of a pixel inside a straight edge at signed distance ``delta`` from its centre, and its derivative.

    ``A``, ``B``: the pixel's two sides projected on the edge normal. The
    share is the distribution function of ``n . p`` for ``p`` uniform over
    the pixel: the convolution of two boxes of widths ``A`` and ``B`` (a
    trapezoid), so linear in the middle and quadratic in the corners:
    ``(R(d + hi) - R(d + lo) - R(d - lo) + R(d - hi)) / (2 A B)`` with
    ``R(x) = max(x, 0)^2``, ``hi = (A + B) / 2``, ``lo = |A - B| / 2``.
    """
    A = np.maximum(A, 1e-4 * (A + B) + 1e-9)  # (a side along the edge: the limit, a linear ramp)
    B = np.maximum(B, 1e-4 * (A + B) + 1e-9)
    hi, lo = 0.5 * (A + B), 0.5 * np.abs(A - B)
    p1, p2 = np.maximum(delta + hi, 0), np.maximum(delta + lo, 0)
    p3, p4 = np.maximum(delta - lo, 0), np.maximum(delta - hi, 0)
    inv = 1.0 / (A * B)
    share = (p1 * p1 - p2 * p2 - p3 * p3 + p4 * p4) * (0.5 * inv)
    slope = (p1 - p2 - p3 + p4) * inv
    return np.minimum(share, 1.0), slope


def chord_m2(delta, nx, ny, cs: float, rs: float):
    """Mean of tau^2 over the chord ``n . p = delta`` of the pixel ``|x| <= cs/2, |y| <= rs/2``; tau along the edge.

    On the chord ``p = delta n + tau (-ny, nx)`` each pair of pixel sides
    bounds tau to an interval (centre, half-width); over their intersection
    ``[t1, t2]`` the mean of tau^2 is ``(t1^2 + t1 t2 + t2^2) / 3``.
    """
    big = 1e6
    sy, sx = np.abs(ny) > 1e-6, np.abs(nx) > 1e-6
    inv_y = 1.0 / np.where(sy, ny, 1.0)
    inv_x = 1.0 / np.where(sx, nx, 1.0)
    ca, wa = np.where(sy, delta * nx * inv_y, 0.0), np.where(sy, 0.5 * cs * np.abs(inv_y), big)
    cb, wb = np.where(sx, -delta * ny * inv_x, 0.0), np.where(sx, 0.5 * rs * np.abs(inv_x), big)
    lo = np.maximum(ca - wa, cb - wb)
    hi = np.maximum(np.minimum(ca + wa, cb + wb), lo)
    return (lo * lo + lo * hi + hi * hi) * (1.0 / 3.0)


#: Abramowitz & Stegun 7.1.26's coefficients: erf to 1.5e-7 (numpy has no erf, and scipy.special is not loaded on
#: a one-shot solve's path).
_AS = (0.254829592, -0.284496736, 1.421413741, -1.453152027, 1.061405429)


def normal_cdf(x: np.ndarray) -> np.ndarray:
    """Phi(x), the standard normal distribution function, to 1e-7 (Abramowitz & Stegun 7.1.26 on erf)."""
    z = np.abs(x) * 0.7071067811865476
    t = 1.0 / (1.0 + 0.3275911 * z)
    a1, a2, a3, a4, a5 = _AS
    erf = 1.0 - ((((a5 * t + a4) * t + a3) * t + a2) * t + a1) * t * np.exp(-z * z)
    return 0.5 * (1.0 + np.copysign(erf, x))


def blurred_box_edge(delta: np.ndarray, A: np.ndarray, B: np.ndarray, sigma: float, spread: bool = False):
    """:func:`box_edge` blurred across the edge by a Gaussian point spread of ``sigma`` (the unit of ``delta``).

    The share is ``E[trapezoid(delta + Z)]``, ``Z ~ N(0, sigma^2)``, in closed
    form: ``R(x) = max(x, 0)^2`` becomes ``(x^2 + s^2) Phi(x / s) + x s phi(x / s)``.
    Returns ``(share, slope)``, and with ``spread`` also its derivative in the
    blur's variance ``v = sigma^2`` (by the heat equation, half the second
    derivative in ``delta``: ``Phi`` in place of ``R``, over ``2 A B``; at
    ``sigma = 0`` the box of the pixels the edge crosses).
    """
    if not sigma > 0 and not spread:
        return box_edge(delta, A, B)
    share0 = box_edge(delta, A, B) if not sigma > 0 else None
    A = np.maximum(A, 1e-4 * (A + B) + 1e-9)
    B = np.maximum(B, 1e-4 * (A + B) + 1e-9)
    hi, lo = 0.5 * (A + B), 0.5 * np.abs(A - B)
    inv = 1.0 / (A * B)
    terms = ((1.0, hi), (-1.0, lo), (-1.0, -lo), (1.0, -hi))
    if share0 is not None:
        steps = sum(sign * np.where(delta + off > 0, 1.0, np.where(delta + off < 0, 0.0, 0.5)) for sign, off in terms)
        return share0[0], share0[1], steps * (0.5 * inv)
    reach = hi + 8.0 * sigma  # beyond it the share is 0 or 1 to 1e-15 (and the squares would lose every digit)
    delta = np.clip(delta, -reach, reach)
    s2 = sigma * sigma
    inv_s = 1.0 / sigma
    share = np.zeros(np.broadcast(delta, A).shape)
    slope = np.zeros_like(share)
    steps = np.zeros_like(share)
    for sign, off in terms:
        x = delta + off
        u = x * inv_s
        cdf = normal_cdf(u)
        pdf = 0.3989422804014327 * np.exp(-0.5 * u * u)
        share += sign * ((x * x + s2) * cdf + x * sigma * pdf)
        slope += sign * (x * cdf + sigma * pdf)
        steps += sign * cdf
    share = np.clip(share * (0.5 * inv), 0.0, 1.0)
    return (share, slope * inv, steps * (0.5 * inv)) if spread else (share, slope * inv)
