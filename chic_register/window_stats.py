"""Statistics of a tube's verification window (:mod:`chic_register.verify_pose`): where its section lies against
where the pose puts it (:func:`section_shift`), and a section's spread along rows and columns (:func:`_spread`)."""

from __future__ import annotations

import math

import numpy as np


def section_shift(w, y: np.ndarray, coef: np.ndarray, sigma: float) -> tuple[float, float]:
    """``(shift, standard error)`` in pixels: the in-plane shift of a tube's rendered section that best explains the
    residual of its window's fit (``chic_register.verify_pose._fit_window``'s ``coef``), to first order (the section's gradient times its
    gain, with an offset), and the standard error of its length under pixel noise ``sigma``. ``(0, inf)`` when
    degenerate."""
    own = w.own
    res = y - coef[0] - coef[1] * own.ravel()
    if coef.size > 2:
        res -= coef[2] * w.others.ravel()
    g = np.empty((2,) + own.shape)  # central differences, one-sided at the window's edges (np.gradient's, cheaper)
    g[0, 1:-1] = 0.5 * (own[2:] - own[:-2])
    g[0, 0], g[0, -1] = own[1] - own[0], own[-1] - own[-2]
    g[1, :, 1:-1] = 0.5 * (own[:, 2:] - own[:, :-2])
    g[1, :, 0], g[1, :, -1] = own[:, 1] - own[:, 0], own[:, -1] - own[:, -2]
    g = g.reshape(2, -1)
    g -= g.mean(axis=1, keepdims=True)  # the offset's column projected out
    a = float(coef[1])
    (grr, grc), (_, gcc) = (g @ g.T).tolist()
    det = grr * gcc - grc * grc
    if not a * a * det > 0:
        return 0.0, math.inf
    br, bc = (g @ res).tolist()
    dr, dc = -(gcc * br - grc * bc) / (a * det), -(grr * bc - grc * br) / (a * det)  # y ~ a own(x - d): -a grad . d
    n = math.hypot(dr, dc)
    ur, uc = (dr / n, dc / n) if n > 0 else (1.0, 0.0)
    var = (gcc * ur * ur - 2 * grc * ur * uc + grr * uc * uc) / (a * a * det)  # u^T (a^2 G)^-1 u
    return n, sigma * math.sqrt(max(var, 0.0))


def _spread(w: np.ndarray):
    """Weighted variance along rows and columns (pixels^2) of weights ``w`` (h, w); None if empty."""
    total = float(w.sum())
    if not total > 0:
        return None
    r = np.arange(w.shape[0], dtype=float)
    c = np.arange(w.shape[1], dtype=float)
    wr, wc = w.sum(axis=1), w.sum(axis=0)
    mr, mc = wr @ r / total, wc @ c / total
    vr, vc = wr @ (r - mr) ** 2 / total, wc @ (c - mc) ** 2 / total
    if not (vr > 0 and vc > 0):
        return None
    return np.array([vr, vc])
