"""Whether the matched blobs are wider than the channels: the trigger of the blurred pixel fit.

Every solve asks it (:func:`blobs_wide`); only the slices that answer yes
need :mod:`chic_register.fit.blurred`, which a one-shot solve then does not
import.
"""

from __future__ import annotations

import math

import numpy as np

from chic_register.detect.blobs import float_range, median
from chic_register.detect.detected import DetectedSlice
from chic_register.model.tube_model import TubeModel

#: Blobs this many times wider than the channels (median over the slices' measured widths) take the blurred fit
#: (:func:`blob_width_ratio` reads 0.99-1.05 for sharp sections, 1.14-1.36 for blobs 1.5x, 1.2-1.7 for 2x).
WIDE_RATIO = 1.15


def blob_width_ratio(model: TubeModel, seen: list[DetectedSlice], assignments) -> float:
    """Median over the matched blobs of their width across (4 x the minor standard deviation of the intensity
    above the background over the blob's footprint, less a pixel's own spread) over their tube's diameter.

    A sharp section reads about 1 (a disc's minor sigma is a quarter of its
    diameter), a blob blurred to twice the channel's width about 1.6-2 (the
    footprint cuts the tails). Intensity-weighted, not thresholded, so a
    brighter object elsewhere in the image does not shrink it.
    """
    slices = [d.slice for d in seen]
    blob_sets = [d.blobs for d in seen]
    ratios = []
    for sl, b, a in zip(slices, blob_sets, assignments):
        img = np.asarray(sl.pixels, float)
        rs, cs = (float(v) for v in sl.pixel_spacing_mm)
        bg = b.background
        for k in np.flatnonzero(a >= 0).tolist():
            i = int(a[k])
            if i >= len(b.footprints):
                continue
            r0, c0, mask = b.footprints[i]
            h, wd = mask.shape
            # np.maximum(window - background, 0) * mask, in place; the ufuncs' own reductions (small windows: call
            # overhead dominates)
            w = img[r0:r0 + h, c0:c0 + wd] - bg
            np.maximum(w, 0.0, out=w)
            w *= mask
            total = float(np.add.reduce(w, axis=None))
            if not total > 0:
                continue
            y = float_range(h) * rs
            x = float_range(wd) * cs
            wy, wx = np.add.reduce(w, 1), np.add.reduce(w, 0)  # the marginals give the means and variances
            my, mx = float(wy.dot(y)) / total, float(wx.dot(x)) / total  # (dot: matmul's BLAS call, less overhead)
            dy, dx = y - my, x - mx
            cyy = float(wy.dot(dy * dy)) / total - rs * rs / 12
            cxx = float(wx.dot(dx * dx)) / total - cs * cs / 12
            cxy = float(dy.dot(w).dot(dx)) / total
            minor = 0.5 * (cxx + cyy) - math.sqrt(0.25 * (cxx - cyy) ** 2 + cxy * cxy)
            if minor > 0:
                ratios.append(4.0 * math.sqrt(minor) / float(model.diameter_mm[k]))
    return median(ratios) if len(ratios) >= 3 else float("nan")


def blobs_wide(model: TubeModel, seen: list[DetectedSlice], assignments) -> bool:
    """Whether the blurred fit is for these slices: their matched blobs :data:`WIDE_RATIO` times the channels' width
    or wider (:func:`blob_width_ratio`)."""
    return blob_width_ratio(model, seen, assignments) >= WIDE_RATIO
