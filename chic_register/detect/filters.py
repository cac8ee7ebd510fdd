"""Small exact image filters on numpy arrays, by array shifts (no scipy call overhead on one core): separable
binomial smoothing, a separable running maximum and a 3 x 3 binary dilation. Used by the blob detector
(:mod:`chic_register.detect.blobs`, which re-exports them) and by the pose checks that dilate masks.
"""

from __future__ import annotations

import numpy as np


def dilate(mask: np.ndarray, iterations: int = 1) -> np.ndarray:
    """3 x 3 (8-connected) binary dilation of a small mask (h, w), by array shifts (no scipy call overhead)."""
    out = mask
    for _ in range(iterations):
        m = out.copy()
        m[1:] |= out[:-1]
        m[:-1] |= out[1:]
        row = m.copy()
        m[:, 1:] |= row[:, :-1]
        m[:, :-1] |= row[:, 1:]
        out = m
    return out


#: Largest pixel magnitude :func:`gaussian_smooth` takes (it works in single precision, to 3.4e38, with headroom for its
#: sums); 2^-100 is the smallest for its ``scale_at_end``.
SAFE_MAGNITUDE = 2.0 ** 100


def gaussian_smooth(img: np.ndarray, sigma_px: float, scale_at_end: bool = False) -> np.ndarray:
    """Separable binomial smoothing (float32), the closest of widths 3 / 5 / 7 to a Gaussian of ``sigma_px``.

    ``n`` passes of [1, 2, 1] / 4 have sigma sqrt(n / 2); array shifts are
    several times faster than ``scipy.ndimage.gaussian_filter`` on one core.
    Edges replicate the border pixel. ``scale_at_end``: the passes' divisions
    by 4 made once at the end, for an image whose pixels all lie in
    [2^-100, 2^100] (the caller's promise): every sum then stays a normal
    float, where a power of two scales exactly, so the result is the same
    to the bit, with a pass over the image less per half-pass.
    """
    n = min(3, max(1, int(round(2 * sigma_px * sigma_px))))
    a = img.astype(np.float32)
    h, w = a.shape
    scale = not (scale_at_end and h >= 2 and w >= 2)
    # two image buffers and one of pair sums, reused by every pass: fresh large arrays cost page faults
    b = np.empty_like(a)
    pair = np.empty(h * w, np.float32)
    for _ in range(n):
        _binomial_rows(a, b, pair, scale)
        _binomial_cols(b, a, pair, scale)
    if not scale:
        a *= 0.25 ** (2 * n)
    return a


def _binomial_rows(x: np.ndarray, y: np.ndarray, pair: np.ndarray, scale: bool = True) -> None:
    """``y`` = one [1, 2, 1] / 4 pass along axis 0 of ``x`` (h, w), edges replicated; ``pair``: scratch (>= h * w);
    without the division by 4 unless ``scale`` (``h`` >= 2 then).

    Sums of neighbouring pairs, then sums of neighbouring pair sums.
    """
    h, w = x.shape
    if h < 2:
        y[...] = x
        return
    p = pair[: (h - 1) * w].reshape(h - 1, w)
    np.add(x[:-1], x[1:], out=p)  # x[i] + x[i+1]
    np.add(p[:-1], p[1:], out=y[1:-1])
    y[0] = p[0] + 2 * x[0]  # replicated x[-1] = x[0]
    y[-1] = p[-1] + 2 * x[-1]
    if scale:
        y *= 0.25


def _binomial_cols(x: np.ndarray, y: np.ndarray, pair: np.ndarray, scale: bool = True) -> None:
    """The same pass along axis 1, on the flattened image (one long contiguous loop, not h short ones).

    Pairs that straddle two rows only land in the first and last columns,
    which are then overwritten with their replicated-edge values.
    """
    h, w = x.shape
    if w < 2:
        y[...] = x
        return
    xf, p = x.reshape(-1), pair[: h * w - 1]
    np.add(xf[:-1], xf[1:], out=p)  # p[i * w + j] = x[i, j] + x[i, j + 1] for j < w - 1
    np.add(p[:-1], p[1:], out=y.reshape(-1)[1:-1])
    y[:, 0] = x[:, 0] * 3 + x[:, 1]
    y[:, -1] = x[:, -2] + x[:, -1] * 3
    if scale:
        y *= 0.25


def maximum_filter(vals: np.ndarray, size: int) -> np.ndarray:
    """Maximum over each ``size`` x ``size`` window (odd ``size``), as ``scipy.ndimage.maximum_filter``.

    The border is padded with -inf; for a maximum that equals scipy's default
    mirror padding, whose values all lie within the window already.
    """
    h = size // 2
    H, W = vals.shape
    padded = np.full((H + 2 * h, W + 2 * h), -np.inf, dtype=vals.dtype)  # (np.pad's result, less its overhead)
    padded[h:h + H, h:h + W] = vals
    # separable: the maximum over the window's rows, then over its columns (on the transposed view; exact)
    return _running_max(_running_max(padded, size).T, size).T


def _running_max(a: np.ndarray, size: int) -> np.ndarray:
    """Maximum of every ``size`` consecutive rows of ``a`` (the first axis shrinks by ``size - 1``).

    By doubling: maxima over 2, 4, ... rows, then two overlapping windows of
    the largest power of two make up ``size`` (a maximum is exact in any
    order): ~log2(size) operations instead of ``size - 1``.
    """
    m, width = a, 1
    while 2 * width <= size:
        m = np.maximum(m[:-width], m[width:])
        width *= 2
    if width == size:
        return m
    n_out = a.shape[0] - size + 1
    return np.maximum(m[:n_out], m[size - width:size - width + n_out])
