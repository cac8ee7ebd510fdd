"""Blobs wider than the channels: a Gaussian point spread for the verification's model images.

Real MRI blobs are often wider than the tube drawn (point spread, partial
volume, fluid spreading in a printed channel). The verification
(:mod:`chic_register.verify_pose`) draws sections sharp; when they fail its
shape test, :func:`fit_psf` finds the Gaussian blur that best explains the
matched sections and the tests are repeated on the blurred model. Numpy
only: scipy stays off the solve path's imports.
"""

from __future__ import annotations

import math

import numpy as np


def gaussian_blur(img: np.ndarray, sigma_px: float) -> np.ndarray:
    """``img`` (H, W) blurred by an isotropic Gaussian of ``sigma_px``, zero outside (separable: two small
    matrix products, as the windows are a few dozen pixels)."""
    if sigma_px <= 0:
        return img

    def matrix(n):
        x = np.arange(n, dtype=float)
        K = np.exp(-0.5 * ((x[:, None] - x[None, :]) / sigma_px) ** 2)
        return K / (sigma_px * math.sqrt(2 * math.pi))

    return matrix(img.shape[0]) @ img @ matrix(img.shape[1]).T


def blurred_windows(wins, canvas, sigma_px: float):
    """The verification's tube windows (own and neighbours' renders) and its model image blurred by ``sigma_px``
    (``canvas`` None: the windows only)."""
    out = [type(w)(w.k, w.r0, w.c0, gaussian_blur(w.own, sigma_px), gaussian_blur(w.others, sigma_px)) for w in wins]
    return out, None if canvas is None else gaussian_blur(canvas, sigma_px)


def fit_psf(wins, matched, sigmas_px, misfit) -> float | None:
    """The sigma (pixels) of ``sigmas_px`` whose blur leaves the least summed ``misfit(window)`` over the windows
    of the ``matched`` tubes (``misfit`` returns inf for a window it cannot fit); None if none fits."""
    best, best_total = None, math.inf
    for sigma in sigmas_px:
        blurred, _ = blurred_windows(wins, None, sigma)
        total = sum(misfit(w) for w in blurred if w.k in matched)
        if total < best_total:
            best, best_total = sigma, total
    return best
