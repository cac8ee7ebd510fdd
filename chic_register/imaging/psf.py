"""Blobs wider than the channels: a Gaussian point spread for the verification's model images.

Real MRI blobs are often wider than the tube drawn (point spread, partial
volume, fluid spreading in a printed channel). The verification
(:mod:`chic_register.verify.pixels`) draws sections sharp; when they fail its
shape test, :func:`fit_psf` finds the Gaussian blur that best explains the
matched sections and the tests are repeated on the blurred model. Numpy
only: scipy stays off the solve path's imports.
"""

from __future__ import annotations

import math

import numpy as np


def gaussian_blur(img: np.ndarray, sigma_px) -> np.ndarray:
    """``img`` (H, W) blurred by a Gaussian of ``sigma_px`` (one sigma, or (along rows, along columns): a
    point spread round in millimetres is not in pixels that are not square), zero outside (separable: two
    small matrix products, as the windows are a few dozen pixels)."""
    s_r, s_c = (float(sigma_px), float(sigma_px)) if np.ndim(sigma_px) == 0 else (float(v) for v in sigma_px)
    if s_r <= 0 or s_c <= 0:
        return img

    def matrix(n, sigma):
        x = np.arange(n, dtype=float)
        K = np.exp(-0.5 * ((x[:, None] - x[None, :]) / sigma) ** 2)
        return K / (sigma * math.sqrt(2 * math.pi))

    return matrix(img.shape[0], s_r) @ img @ matrix(img.shape[1], s_c).T


def blurred_windows(wins, canvas, sigma_px):
    """The verification's tube windows (own and neighbours' renders) and its model image blurred by ``sigma_px``
    (``canvas`` None: the windows only)."""
    out = [type(w)(w.k, w.r0, w.c0, gaussian_blur(w.own, sigma_px), gaussian_blur(w.others, sigma_px)) for w in wins]
    return out, None if canvas is None else gaussian_blur(canvas, sigma_px)


def fit_psf(wins, matched, sigmas_px, misfit, refine_steps: int = 6) -> float | None:
    """The sigma (pixels; a number or a (row, column) pair) whose blur leaves the least summed ``misfit(window)``
    over the windows of the ``matched`` tubes (``misfit`` returns inf for a window it cannot fit); None if none
    fits. The best of ``sigmas_px`` (ascending) is refined between its neighbours by ``refine_steps`` of a
    golden-section search: real blobs are any width, and a blur between two grid values leaves a misfit that
    reads as a wrong shape."""
    def total(sigma):
        blurred, _ = blurred_windows(wins, None, sigma)
        return sum(misfit(w) for w in blurred if w.k in matched)

    cands = [np.atleast_1d(np.asarray(s, dtype=float)) for s in sigmas_px]
    scores = [total(s if s.size > 1 else float(s[0])) for s in cands]
    i = int(np.argmin(scores))
    if not math.isfinite(scores[i]):
        return None

    def at(u):  # u in [0, 1] along the bracket around the best
        v = lo + u * (hi - lo)
        return v if v.size > 1 else float(v[0])

    lo, hi = cands[max(i - 1, 0)], cands[min(i + 1, len(cands) - 1)]
    best_u = (np.linalg.norm(cands[i] - lo) / max(np.linalg.norm(hi - lo), 1e-12)) if i > 0 else 0.0
    best, best_total = at(best_u), scores[i]
    g = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = 0.0, 1.0
    c, d = b - g * (b - a), a + g * (b - a)
    fc, fd = total(at(c)), total(at(d))
    for _ in range(max(refine_steps, 0)):
        for u, f in ((c, fc), (d, fd)):
            if f < best_total:
                best, best_total = at(u), f
        if fc <= fd:
            b, d, fd = d, c, fc
            c = b - g * (b - a)
            fc = total(at(c))
        else:
            a, c, fc = c, d, fd
            d = a + g * (b - a)
            fd = total(at(d))
    for u, f in ((c, fc), (d, fd)):
        if f < best_total:
            best, best_total = at(u), f
    return best if np.ndim(best) == 0 else tuple(float(v) for v in best)
