"""A tube's centre measured over a disc of the blob's width, not over the pixels above the detection level.

The detector's centre is the intensity centroid of a thresholded footprint.
Where a blob's inside is textured (real scans: speckle, an inhomogeneous or
bubbly fill, flow) or faint (a slab's edge), the level cuts it into pieces or
keeps only its brightest part, and that centre wanders by up to a blob radius
with a noise no pixel-noise model predicts. The centroid over a fixed disc,
moved until it sits on its own centroid (mean shift), uses every pixel of
the section whatever its level: it is a linear estimate at its fixed point,
so :func:`~chic_register.precision.uncertainty.centroid_covariance` over the
disc predicts its noise.
"""

from __future__ import annotations

import math

import numpy as np

#: Mean-shift steps at most (a step below :data:`CONVERGED_PX` stops it earlier).
ITERATIONS = 12
CONVERGED_PX = 1e-3


def disc_centroid(pixels: np.ndarray, background: float, start_rc, radius_px: float, others_rc=None,
                  max_shift_px: float | None = None):
    """``(centre_rc, footprint)`` of the background-subtracted intensity centroid over a disc of ``radius_px``
    that sits on its own centroid, started at ``start_rc`` (row, col); None when it has no weight or wanders
    more than ``max_shift_px`` (default: ``radius_px``) from the start.

    ``others_rc`` (M, 2): other sections' centres (row, col): a pixel nearer to one of them than to ``start_rc``
    is theirs and left out of the disc. ``footprint`` is ``(row0, col0, mask)`` of the disc's pixels (the
    detector's convention). Negative weights (noise below the background) are clipped to zero.
    """
    img = np.asarray(pixels)
    H, W = img.shape
    r, c = (float(v) for v in start_rc)
    r_s, c_s = r, c
    limit = radius_px if max_shift_px is None else max_shift_px
    others = np.zeros((0, 2)) if others_rc is None else np.asarray(others_rc, float).reshape(-1, 2)
    R = float(radius_px)
    pad = int(math.ceil(R + limit)) + 1
    r0, r1 = max(0, int(r_s) - pad), min(H, int(r_s) + pad + 2)
    c0, c1 = max(0, int(c_s) - pad), min(W, int(c_s) + pad + 2)
    if r0 >= r1 or c0 >= c1:
        return None
    rr, cc = np.mgrid[r0:r1, c0:c1].astype(float)
    w_all = np.asarray(img[r0:r1, c0:c1], float) - background
    allowed = np.isfinite(w_all)
    if others.size:  # nearer the start than any other section
        d_own = (rr - r_s) ** 2 + (cc - c_s) ** 2
        for o_r, o_c in others:
            allowed &= d_own <= (rr - o_r) ** 2 + (cc - o_c) ** 2
    w_all = np.where(allowed, np.maximum(w_all, 0.0), 0.0)
    mask = None
    for _ in range(ITERATIONS):
        mask = ((rr - r) ** 2 + (cc - c) ** 2 <= R * R) & allowed
        w = w_all * mask
        s = float(w.sum())
        if not s > 0:
            return None
        r_new, c_new = float((w * rr).sum()) / s, float((w * cc).sum()) / s
        step = math.hypot(r_new - r, c_new - c)
        r, c = r_new, c_new
        if math.hypot(r - r_s, c - c_s) > limit:
            return None
        if step < CONVERGED_PX:
            break
    mask = ((rr - r) ** 2 + (cc - c) ** 2 <= R * R) & allowed
    rows, cols = np.nonzero(mask)
    if rows.size == 0:
        return None
    a0, a1, b0, b1 = rows.min(), rows.max() + 1, cols.min(), cols.max() + 1
    return (r, c), (r0 + int(a0), c0 + int(b0), mask[a0:a1, b0:b1].copy())


def disc_contrast(pixels: np.ndarray, background: float, noise_sigma: float, centre_rc, radius_px: float) -> float:
    """The mean of ``pixels`` over a disc of ``radius_px`` about ``centre_rc`` (row, col) above ``background``, in
    noise sigmas of one pixel (NaN without noise or pixels): how plainly a section too faint to detect shows there."""
    if not noise_sigma > 0:
        return math.nan
    img = np.asarray(pixels)
    H, W = img.shape
    r, c = (float(v) for v in centre_rc)
    R = float(radius_px)
    r0, r1 = max(0, int(math.floor(r - R))), min(H, int(math.ceil(r + R)) + 1)
    c0, c1 = max(0, int(math.floor(c - R))), min(W, int(math.ceil(c + R)) + 1)
    if r0 >= r1 or c0 >= c1:
        return math.nan
    rr, cc = np.mgrid[r0:r1, c0:c1]
    inside = (rr - r) ** 2 + (cc - c) ** 2 <= R * R
    values = np.asarray(img[r0:r1, c0:c1], float)[inside]
    values = values[np.isfinite(values)]
    return float((values.mean() - background) / noise_sigma) if values.size else math.nan
