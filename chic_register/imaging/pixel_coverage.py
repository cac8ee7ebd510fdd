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
