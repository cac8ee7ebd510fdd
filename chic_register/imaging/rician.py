"""The mean of a Rician magnitude: what a magnitude image shows, on average, of a signal in noise.

A magnitude pixel of signal ``nu`` in complex Gaussian noise of scale
``sigma`` has the mean ``sigma g(nu / sigma)`` with

    g(u) = sqrt(pi / 2) [(1 + u^2 / 2) I0e(u^2 / 4) + (u^2 / 2) I1e(u^2 / 4)]

(``I0e``, ``I1e``: exponentially scaled Bessel functions): ``g(0) = 1.2533``
(the background's floor) and ``g(u) = u + 1 / (2 u) + ...`` for large ``u``.
So the mean is not ``b + a nu``: a section's faint edge pixels read brighter
than a linear model of the fluid fraction says, and where that lifts one side
of a section more than the other (the pixel grid's phase) a fit of the linear
model moves the section by a bias proportional to ``sigma``
(:mod:`chic_register.fit.section` fits this mean instead).

Tabulated once with numpy alone (the Bessel functions by their integral over
``[0, pi]``, spectrally accurate; ~3 ms); above ``u = 12`` the asymptotic series.
:func:`rician_model` turns a section model into the image's mean at a gain,
:func:`inner_gain` estimates that gain, :func:`rayleigh_sigma` tells a
magnitude image (and its noise scale) from its background.
"""

from __future__ import annotations

import functools
import math

import numpy as np

#: Pixels this deep inside a section model (fluid fraction) give the tube's gain (:func:`inner_gain`).
INNER_LEVEL = 0.95
_U_MAX = 12.0
_STEP = 0.02


@functools.lru_cache(maxsize=1)
def rician_table():
    """``(u, g, g')`` of :func:`rician_mean` on ``u = 0, _STEP, ..., _U_MAX``."""
    u = np.arange(0.0, _U_MAX + 0.5 * _STEP, _STEP)
    x = 0.25 * u * u
    # the trapezoid rule on a smooth periodic integrand converges geometrically: 61 nodes agree with 241 (and with
    # scipy.special.i0e / i1e) to 2e-15 up to u = 12, in 0.2 ms instead of 3 ms (once per process: a one-shot solve)
    th = np.linspace(0.0, math.pi, 61)
    e = np.exp(x[:, None] * (np.cos(th)[None] - 1.0))  # I_n(x) e^-x = (1 / pi) int_0^pi e^{x (cos t - 1)} cos(n t)
    wts = np.full(th.size, 1.0)
    wts[[0, -1]] = 0.5
    wts *= (th[1] - th[0]) / math.pi
    i0e = e @ wts
    i1e = (e * np.cos(th)[None]) @ wts
    g = math.sqrt(math.pi / 2) * ((1 + 2 * x) * i0e + 2 * x * i1e)
    return u, g, np.gradient(g, _STEP, edge_order=2)


def rician_mean(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(g(u), g'(u))``: the mean magnitude over sigma at signal over sigma ``u >= 0``, and its slope."""
    u = np.abs(np.asarray(u, dtype=float))
    u_tab, g_tab, d_tab = rician_table()
    uc = np.minimum(u, _U_MAX)
    w = np.maximum(u, _U_MAX)  # above the table: g(U) + (u - U) + 1 / (2 u) - 1 / (2 U), to 1 / (8 U^3)
    g = np.interp(uc, u_tab, g_tab) + (u - uc) + 0.5 / w - 0.5 / _U_MAX
    d = np.interp(uc, u_tab, d_tab) + 0.5 / _U_MAX**2 - 0.5 / (w * w)
    return g, d


def rician_signal(mean: np.ndarray) -> np.ndarray:
    """The inverse of :func:`rician_mean`'s ``g``: signal over sigma from mean magnitude over sigma (0 below the
    floor ``g(0)``)."""
    m = np.asarray(mean, dtype=float)
    u_tab, g_tab, _ = rician_table()
    u = np.interp(m, g_tab, u_tab, left=0.0)
    far = m > g_tab[-1]
    if far.any():
        v = m[far]
        u[far] = v - 0.5 / v  # (to 1 / v^3)
    return u


#: The Rayleigh distribution (a Rician magnitude without signal): mean / sigma and standard deviation / sigma.
RAYLEIGH_MEAN = math.sqrt(math.pi / 2)
RAYLEIGH_SD = math.sqrt(2 - math.pi / 2)


def rayleigh_sigma(background: float, background_sd: float, tolerance: float = 0.08) -> float:
    """The Rician noise scale of a magnitude image from its background's mean and SD; 0 if it is not Rayleigh.

    A magnitude image's empty background is Rayleigh: its mean is 1.913
    times its SD. A background with another ratio (a filtered or offset
    image, the paper's uniform noise, tissue) gets 0: no Rician model.
    """
    if not (background_sd > 0 and math.isfinite(background)):
        return 0.0
    ratio = background / background_sd
    if abs(ratio / (RAYLEIGH_MEAN / RAYLEIGH_SD) - 1.0) > tolerance:
        return 0.0
    return background_sd / RAYLEIGH_SD


def rician_model(S, Sx, Sy, gain, other, sigma: float):
    """A section model ``S`` (P,) and its derivatives as a Rician magnitude image shows them on average.

    At the fluid gain ``gain`` and the neighbours' signal ``other`` (None: none)
    (:func:`~chic_register.imaging.rician.rician_mean`, ``R(v) = sigma g(v / sigma)``):
    ``M = (R(gain S + other) - R(other)) / gain`` (``gain`` > 0) and its derivatives
    ``R'(gain S + other) (Sx, Sy)``, and ``lift = R(other) - R(0)``, to be taken
    from the pixels. ``y - lift = b + gain M`` then holds on average with
    ``b = R(0)``, as ``y = b + a S`` does without noise: the linear fit of
    :func:`chic_register.fit.section._linear_fit` applies unchanged, and at the true section its fit is
    unbiased at any noise level.
    """
    inv = 1.0 / sigma
    if other is None:  # no neighbour: R(0), the floor, and no lift
        g, slope = rician_mean((gain * S) * inv)
        return (g - RAYLEIGH_MEAN) * (sigma / gain), slope * Sx, slope * Sy, np.zeros(S.size)
    g, slope = rician_mean((gain * S + other) * inv)
    g0, _ = rician_mean(other * inv)
    return (g - g0) * (sigma / gain), slope * Sx, slope * Sy, (g0 - RAYLEIGH_MEAN) * sigma


def inner_gain(S, y, own, K: int, sigma: float) -> np.ndarray:
    """Each tube's fluid gain (K,) from the mean of its window's inner pixels (model at least
    :data:`INNER_LEVEL`), through the inverse Rician mean, over the model's mean there; 0 for a tube
    with fewer than 3 such pixels."""
    inner = S >= INNER_LEVEL
    n = np.bincount(own[inner], minlength=K)
    total = np.bincount(own[inner], weights=y[inner], minlength=K)
    level = np.bincount(own[inner], weights=S[inner], minlength=K)  # (the model's mean there, about 1)
    mean = total / np.maximum(n, 1)
    return np.where(n >= 3, sigma * rician_signal(mean / sigma) * n / np.maximum(level, 1e-12), 0.0)
