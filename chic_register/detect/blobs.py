"""Tube cross-section detection: bright blobs in a slice, with sub-pixel centres.

As in the paper: denoise, threshold, morphology, connected components and an
area filter. Every blob that could be a tube is kept as a candidate (anatomy
and the tool in the bore included): the solver, which knows the geometry,
picks the subset that fits. Centres are intensity-weighted centroids of the
background-subtracted *original* image over each blob's dilated footprint, so
partial-volume edges count and smoothing does not bias them. Blobs that are
two touching tubes (helix close to a straight tube near the body's ends) are
also offered split in two along their intensity peaks.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import cc3d
import numpy as np

from chic_register.detect.filters import (
    SAFE_MAGNITUDE,
    dilate,
    gaussian_smooth,
    maximum_filter,
)
from chic_register.detect.watershed import watershed_ift
from chic_register.model.slices import Slice
from chic_register.util.quantiles import sorted_span

#: :func:`median` of this many values or more: from a bracket of the middle values (see ``quantiles.sorted_span``).
MEDIAN_SPAN_MIN = 2048


@dataclass(frozen=True, eq=False)
class Blobs:
    """Candidate tube cross-sections of one image (N blobs).

    ``centres_rc`` (N, 2): sub-pixel (row, col) centres; ``area_px`` (N,):
    pixels above threshold; ``mean_intensity`` (N,): mean of the original
    image over the blob; ``axis_ratio`` (N,): minor/major axis of the blob's
    second moments (1 = round); ``contrast`` (N,): (mean - background) /
    noise sigma; ``background`` and ``noise_sigma``: image level and noise
    estimate; ``threshold``: the level used on the smoothed image;
    ``footprints`` (N,): per blob ``(row0, col0, mask)``, the pixels (a bool
    mask placed at row0, col0) whose intensity made its centre, so that a
    model can predict that centre the same way (see ``solve``);
    ``width_mm``: the typical width of the tube blobs measured in this image
    (the median minor axis of the candidate components; NaN when fewer than 3).
    """

    centres_rc: np.ndarray
    area_px: np.ndarray
    mean_intensity: np.ndarray
    axis_ratio: np.ndarray
    contrast: np.ndarray
    background: float
    noise_sigma: float
    threshold: float
    footprints: tuple = ()
    width_mm: float = float("nan")

    def __len__(self) -> int:
        return int(self.centres_rc.shape[0])

    @classmethod
    def empty(cls, background=0.0, noise_sigma=0.0, threshold=float("nan")) -> "Blobs":
        z = np.zeros(0)
        return cls(np.zeros((0, 2)), z, z, z, z, float(background), float(noise_sigma), float(threshold))


def otsu_threshold(image: np.ndarray, bins: int = 256) -> float:
    """Otsu's threshold of an image (any shape), from a ``bins``-bin histogram."""
    x = image.ravel()
    lo, hi = float(np.minimum.reduce(x)), float(np.maximum.reduce(x))
    if hi <= lo:
        return lo
    t = x - lo  # (x - lo) * (bins / (hi - lo)), in place
    t *= bins / (hi - lo)
    q = t.astype(np.intp)
    # np.bincount(np.minimum(q, bins - 1)): the top value's bin (bins) folded into the last, without a pass over q
    hist = np.bincount(q, minlength=bins + 1)
    if hist.size == bins + 1:
        hist[bins - 1] += hist[bins]
        hist = hist[:bins].astype(float)
    else:  # (rounding past the top bin: not seen, but then exactly as it says)
        hist = np.bincount(np.minimum(q, bins - 1), minlength=bins).astype(float)
    steps = _OTSU_STEPS.get(bins)
    if steps is None:
        steps = _OTSU_STEPS[bins] = np.arange(bins) + 0.5
    centres = lo + steps * (hi - lo) / bins
    w0 = np.add.accumulate(hist)  # (np.cumsum, less its wrapper)
    w1 = w0[-1] - w0
    m0 = np.add.accumulate(hist * centres)
    mu0 = m0 / np.maximum(w0, 1e-12)
    mu1 = (m0[-1] - m0) / np.maximum(w1, 1e-12)
    between = w0 * w1 * (mu0 - mu1) ** 2
    k = int(between[:-1].argmax())
    return float(lo + (k + 1) * (hi - lo) / bins)


_OTSU_STEPS: dict = {}  # bins -> the bin centres' offsets, np.arange(bins) + 0.5


def median(values) -> float:
    """The median of an array's finite or infinite values (NaN not checked), as ``np.median`` but from a partition.

    ``np.median`` (and ``np.percentile``) import ``numpy.ma`` on first use,
    about 60 ms on the start-up path of a one-shot solve. Large arrays (a
    background sample) take the middle values from :func:`~chic_register.util.quantiles.sorted_span`.
    """
    a = np.asarray(values)
    if a.dtype != np.float64 and a.dtype != np.float32:  # (float32 orders as its float64 values: no copy needed)
        a = a.astype(float)
    a = a.ravel()
    n = a.size
    if n == 0:
        return math.nan
    h = n // 2
    if n >= MEDIAN_SPAN_MIN:
        mid = sorted_span(a, h - 1 + n % 2, h)
        if mid is not None:
            return float(mid[0]) if n % 2 else 0.5 * (float(mid[0]) + float(mid[1]))
    p = a.copy()  # (np.partition's own steps, less its wrappers)
    if n % 2:
        p.partition(h)
        return float(p[h])
    p.partition((h - 1, h))
    return 0.5 * (float(p[h - 1]) + float(p[h]))


def _mean_std(values: np.ndarray) -> tuple[float, float]:
    """``(values.mean(), values.std())`` of a 1-D float64 array, by numpy's own sums and steps (the same numbers
    bit for bit) without its wrappers; NaNs when empty."""
    n = values.size
    if n == 0:
        return math.nan, math.nan
    mean = float(np.add.reduce(values) / n)
    dev = values - mean
    return mean, math.sqrt(float(np.add.reduce(dev * dev)) / n)


@dataclass(frozen=True)
class _Components:
    """The labelled pixels of an image, gathered per component (label j + 1 at index j, j < n).

    ``boxes``: per component ``(r0, r1, c0, c1)``, its bounding box widened
    by the footprint's margin (clipped to the image); ``start``: where its
    pixels begin in ``values`` (the image's values at the labelled pixels,
    sorted by label, raster order within one); ``row_counts`` /
    ``col_counts``: its pixels per row / column of its box (floats, the
    boxes one after the other from ``row_at`` / ``col_at``), and
    ``row_sums`` / ``col_sums``: the sums of its pixels' rows / columns in
    its box (exact integers, as floats). These are a mask's own row and
    column sums and moments, found for every component in a few passes over
    its pixels instead of several calls per component.
    """

    boxes: list
    start: list
    values: np.ndarray
    row_counts: np.ndarray
    row_at: list
    col_counts: np.ndarray
    col_at: list
    row_sums: list
    col_sums: list


def _components(img: np.ndarray, lab: np.ndarray, rows: np.ndarray, cols: np.ndarray, area: np.ndarray,
                margin: int):
    """:class:`_Components` of the labels 1..n (each present, ``area`` (n,) pixels), from ``lab``, ``rows``,
    ``cols``: the label, row and column of every labelled pixel in raster order; boxes widened by ``margin`` pixels."""
    H, W = img.shape
    n = area.size
    order = lab.argsort(kind="stable")  # stable: rows stay ascending within a label (methods: less overhead)
    lab, rr, cc = lab[order], rows[order], cols[order]
    ends = area.cumsum()
    starts = ends - area  # label j + 1 from starts[j]
    ends -= 1
    r0, r1 = np.maximum(rr[starts] - margin, 0), np.minimum(rr[ends] + 1 + margin, H)
    c0 = np.maximum(np.minimum.reduceat(cc, starts) - margin, 0)
    c1 = np.minimum(np.maximum.reduceat(cc, starts) + 1 + margin, W)
    j = lab.astype(np.intp) - 1
    lr, lc = rr - r0[j], cc - c0[j]  # rows and columns in the box
    h, w = r1 - r0, c1 - c0
    row_at, col_at = h.cumsum() - h, w.cumsum() - w
    row_counts = np.bincount(row_at[j] + lr, minlength=int(h.sum())).astype(float)
    col_counts = np.bincount(col_at[j] + lc, minlength=int(w.sum())).astype(float)
    return _Components(list(zip(r0.tolist(), r1.tolist(), c0.tolist(), c1.tolist())), starts.tolist(), img[rr, cc],
                       row_counts, row_at.tolist(), col_counts, col_at.tolist(),
                       np.bincount(j, weights=lr, minlength=n).tolist(), np.bincount(j, weights=lc, minlength=n).tolist())


def float_range(n: int) -> np.ndarray:
    """``np.arange(n, dtype=float)``, as a view of one cached array (the moments' row and column indices)."""
    global _INDEX
    if n > _INDEX.size:
        _INDEX = np.arange(max(n, 2 * _INDEX.size), dtype=float)
    return _INDEX[:n]


_INDEX = np.arange(256, dtype=float)


def _moments(w: np.ndarray):
    """Centroid (row, col) of weights ``w`` (h, w), the minor/major axis ratio of their spread and its variance
    across (px^2); None when the weights do not sum to a positive total."""
    c = _centroid(w, with_sums=True)
    if c is None:
        return None
    mr, mc, wr, wc, total = c
    return (mr, mc) + _spread(w, wr, wc, total, mr, mc)


def _centroid(w: np.ndarray, with_sums: bool = False):
    """Centroid ``(row, col)`` of weights ``w`` (h, w) (then its row sums, column sums and total when
    ``with_sums``); None when the weights do not sum to a positive total.

    From the row and column sums (two passes over ``w``, then vectors of
    length h and w): these windows are small, so call overhead dominates
    (hence the ufuncs' own reductions, without ``sum``'s wrapper, and ``dot``).
    """
    wr, wc = np.add.reduce(w, 1), np.add.reduce(w, 0)
    total = float(np.add.reduce(wr))
    if not total > 0:
        return None
    # (ndarray.dot is matmul's BLAS call, less its ufunc machinery: the same bits)
    mr, mc = float(wr.dot(float_range(w.shape[0]))) / total, float(wc.dot(float_range(w.shape[1]))) / total
    return (mr, mc, wr, wc, total) if with_sums else (mr, mc)


def _spread(w: np.ndarray, wr: np.ndarray, wc: np.ndarray, total: float, mr: float, mc: float):
    """``(minor/major axis ratio, variance across)`` of weights ``w`` (h, w) with row and column sums ``wr``,
    ``wc``, sum ``total`` and centroid ``(mr, mc)``."""
    dr, dc = float_range(w.shape[0]) - mr, float_range(w.shape[1]) - mc
    srr, scc, src = float(wr.dot(dr * dr)) / total, float(wc.dot(dc * dc)) / total, float(dr.dot(w).dot(dc)) / total
    half_tr, det = (srr + scc) / 2, srr * scc - src * src
    root = math.sqrt(max(half_tr * half_tr - det, 0.0))
    big, small = half_tr + root, max(half_tr - root, 0.0)
    return (math.sqrt(small / big) if big > 0 else 1.0), small




def detect_blobs(
    pixels: np.ndarray,
    pixel_spacing_mm=(1.0, 1.0),
    tube_diameter_mm=3.0,
    *,
    smooth_sigma_px: float | None = None,
    min_area_factor: float = 0.3,
    max_area_factor: float = 12.0,
    min_contrast: float = 3.0,
    dilate_px: int | None = None,
    split_touching: bool = True,
    size_from_image: bool = True,
    flatten_background: bool = False,
    noise_threshold_sigmas: float | None = None,
) -> Blobs:
    """Candidate tube cross-sections in ``pixels`` (rows, cols).

    ``tube_diameter_mm`` (one value, or every tube's from the geometry file)
    and ``pixel_spacing_mm`` (row, col) set the expected blob area ``A0``;
    components with an area outside ``[min_area_factor, max_area_factor] *
    A0`` or a contrast below ``min_contrast`` noise sigmas are dropped. Blank
    images give no blobs. With ``size_from_image`` the blobs' width is
    measured in the image first (``Blobs.width_mm``: blur, partial volume,
    thick slices and fluid around a printed channel widen them, 0.7 to 2.5
    times the nominal diameter is usual) and, when it differs from the
    nominal diameter by more than a quarter, the detection is redone at the
    measured size: smoothing, area window and the test for two touching
    tubes all follow what the image shows, so a wide blob is one blob.
    ``flatten_background`` first subtracts the image's morphological opening
    at three blob widths (a white top-hat): tissue and other structures wider
    than a tube, and slow intensity changes (coil sensitivity), are removed,
    so tubes touching them or lying in a dim part of the image stay separate
    blobs (centres are then weighted by the flattened image). The solver
    retries a slice this way when it does not lock as it is.
    ``noise_threshold_sigmas``: the level is at most this many robust noise
    sigmas of the smoothed image above its median: on a flat background (a CT
    slice's top-hat) one very bright object (metal) would draw Otsu's level
    above the tubes.
    """
    diam = np.atleast_1d(np.asarray(tube_diameter_mm, dtype=float))
    d_lo, d_mid, d_hi = float(diam.min()), median(diam), float(diam.max())
    kw = dict(smooth_sigma_px=smooth_sigma_px, min_contrast=min_contrast, dilate_px=dilate_px,
              split_touching=split_touching, noise_threshold_sigmas=noise_threshold_sigmas)
    if flatten_background:
        pixels = _flatten(pixels, pixel_spacing_mm, d_mid, smooth_sigma_px, min_area_factor, max_area_factor,
                          min_contrast)
        kw["threshold_fraction"] = 0.45
    blobs = _detect(pixels, pixel_spacing_mm, d_mid, min_area_factor * (d_lo / d_mid) ** 2,
                    max_area_factor * (d_hi / d_mid) ** 2, **kw)
    width = blobs.width_mm
    if size_from_image and math.isfinite(width) and not 0.8 <= width / d_mid <= 1.25:
        f = width / d_mid
        # wider blobs: the area window grows at the top only (a tube half hidden in tissue stays small)
        again = _detect(pixels, pixel_spacing_mm, d_mid * f, min_area_factor * (d_lo / d_mid) ** 2 / max(f, 1.0) ** 2,
                        max_area_factor * (d_hi / d_mid) ** 2, **kw)
        return dataclasses.replace(again, width_mm=width)
    return blobs


#: The detection level is at least this many noise sigmas of the smoothed image above its median: a noise pixel
#: passes with odds of 3e-7, so a 512 x 512 slice of noise alone gives no candidate.
FLOOR_SIGMAS = 5.0
#: Median absolute difference of two neighbouring pixels of independent Gaussian noise, in its sigma.
_PAIR_MAD = math.sqrt(2.0) * 0.6745


def smoothed_noise_sigma(img: np.ndarray, sigma_px: float) -> float:
    """The pixel noise of ``img`` (rows, cols) after :func:`~chic_register.detect.filters.gaussian_smooth` at
    ``sigma_px``: the raw noise from the differences of neighbouring pixels along rows (every fourth row; an edge
    is a small share of them), times the smoothing's noise gain (the kernel's L2 norm: ``n`` binomial passes per
    axis keep ``C(4n, 2n) / 16^n`` of the noise's sigma)."""
    rows = img[::4]
    if rows.shape[1] < 2:
        return 0.0
    raw = median(np.abs(np.diff(rows, axis=1)).ravel()) / _PAIR_MAD
    n = min(3, max(1, int(round(2 * sigma_px * sigma_px))))
    return float(raw) * math.comb(4 * n, 2 * n) / 16.0 ** n


def _detect(pixels, pixel_spacing_mm, tube_diameter_mm: float, min_area_factor: float, max_area_factor: float, *,
            smooth_sigma_px, min_contrast, dilate_px, split_touching, threshold_fraction: float = 1.0,
            noise_threshold_sigmas: float | None = None) -> Blobs:
    """One detection pass at the blob size of a tube of ``tube_diameter_mm`` (see :func:`detect_blobs`).

    ``threshold_fraction``: the level used, as a fraction of the way from the
    median to Otsu's threshold (below 1 on flattened images, where tubes in
    tissue stand out less than tubes in air).
    """
    img = np.asarray(pixels, dtype=float)
    if img.ndim != 2 or img.size == 0:
        return Blobs.empty()
    lo, hi = float(np.minimum.reduce(img, axis=None)), float(np.maximum.reduce(img, axis=None))
    if not (math.isfinite(lo) and math.isfinite(hi)):  # a NaN or an infinity anywhere shows in min / max
        return Blobs.empty()
    if max(-lo, hi) > SAFE_MAGNITUDE:  # beyond the smoothing's single precision (register says so before this)
        return Blobs.empty()
    if hi - lo <= 1e-12 * max(1.0, abs(hi)):
        return Blobs.empty(background=lo)
    rs, cs = (float(v) for v in pixel_spacing_mm)
    r_px = 0.5 * tube_diameter_mm / math.sqrt(rs * cs)
    a0 = math.pi * r_px * r_px
    sig = smooth_sigma_px if smooth_sigma_px is not None else max(0.5, 0.3 * r_px)
    smooth = gaussian_smooth(img, sig, scale_at_end=lo >= 1.0 / SAFE_MAGNITUDE and hi <= SAFE_MAGNITUDE)  # (exact: see gaussian_smooth)
    sub_smooth = np.ascontiguousarray(smooth[::2, ::2])  # (Otsu's histogram is faster from a contiguous copy)
    thr = otsu_threshold(sub_smooth)
    base = median(smooth[::4, ::4])
    thr = base + threshold_fraction * (thr - base)
    if noise_threshold_sigmas is not None:
        spread = 1.4826 * median(np.abs(sub_smooth - base))  # robust sigma of the (mostly background) image
        if spread > 0:
            thr = min(thr, base + noise_threshold_sigmas * spread)
    # a nearly empty image (a few small tubes on a wide field of noise): Otsu's split falls into the noise and
    # every speck is a candidate; the level is at least FLOOR_SIGMAS of the smoothed image's noise above its median
    # (not on a flattened image, read at a lower level on purpose: tubes in tissue stand out less there; nor where
    # Otsu's level lies below the median: an image mostly of bright water around dark plastic, split well below it)
    if threshold_fraction >= 1.0 and thr > base:
        thr = max(thr, base + FLOOR_SIGMAS * smoothed_noise_sigma(img, sig))
    mask = smooth > thr
    flat = mask.ravel().nonzero()[0]  # the pixels above the threshold (a few per cent of a slice): np.flatnonzero
    # background and noise: the pixels well below the threshold (mean and spread)
    sub_img = img[::2, ::2]
    bg_pixels = sub_img[sub_smooth < base + 0.25 * (thr - base)]
    if bg_pixels.size < 16:
        bg_pixels = sub_img[sub_smooth <= base]
    bg, sigma_n = _mean_std(bg_pixels)
    if flat.size == 0:
        return Blobs.empty(bg, sigma_n, thr)
    k = dilate_px if dilate_px is not None else 1
    H, W = img.shape
    # components (4-connected, numbered in raster order) labelled on the mask's bounding box only, widened by the
    # blobs' margin k: the same labels as on the whole image, at a fraction of the cost; `labels` starts at (R0, C0)
    rows, cols = np.divmod(flat, W)
    m = max(k, 0)
    R0, R1 = max(0, int(rows[0]) - m), min(H, int(rows[-1]) + 1 + m)
    C0, C1 = max(0, int(cols.min()) - m), min(W, int(cols.max()) + 1 + m)
    # (a contiguous mask: cc3d copies a strided one slowly)
    labels, n = cc3d.connected_components(smooth[R0:R1, C0:C1] > thr, connectivity=4, return_N=True)
    lab_px = labels[rows - R0, cols - C0]  # every labelled pixel's label, in raster order
    area = np.bincount(lab_px, minlength=n + 1)[1:]
    comp = _components(img, lab_px, rows, cols, area, k)
    keep = np.flatnonzero((area >= min_area_factor * a0) & (area <= max_area_factor * a0))
    # a component too large for one tube may be several blurred ones run together (wide blobs of close tubes):
    # it is offered split at higher levels, never whole
    merged = set(np.flatnonzero((area > max_area_factor * a0) & (area <= 150 * a0)).tolist()) if split_touching else set()
    grown = dilate(labels != 0) if k == 1 else None  # every component's footprint at once (see below)
    img_bg = img[R0:R1, C0:C1] - bg
    centres, areas, means, ratios, contrasts, feet, widths = [], [], [], [], [], [], []
    for i in sorted(set(keep.tolist()) | merged):
        r0, r1, c0, c1 = comp.boxes[i]
        n_i = int(area[i])
        # its mean: the sum of raw[blob], in the same order
        mean_i = float(np.add.reduce(comp.values[comp.start[i]:comp.start[i] + n_i])) / float(n_i)
        contrast = (mean_i - bg) / sigma_n if sigma_n > 0 else math.inf
        if contrast < min_contrast:
            continue
        lab = labels[r0 - R0:r1 - R0, c0 - C0:c1 - C0]
        blob = lab == i + 1
        raw = img[r0:r1, c0:c1]
        # the blob's axis ratio and spread across, from the row and column counts and sums found for all components at once
        h, w = r1 - r0, c1 - c0
        total = float(n_i)
        ratio, minor_var = _spread(blob.astype(float), comp.row_counts[comp.row_at[i]:comp.row_at[i] + h],
                                   comp.col_counts[comp.col_at[i]:comp.col_at[i] + w], total,
                                   comp.row_sums[i] / total, comp.col_sums[i] / total)
        if i not in merged:
            widths.append(4 * math.sqrt(max(minor_var - 1 / 12, 0.0)))  # a disc's diameter, less a pixel's spread
        parts = [blob]
        if i in merged:
            parts = _split_levels(blob, smooth[r0:r1, c0:c1], thr, min_area_factor * a0, max_area_factor * a0)
            if not parts:
                continue
        elif split_touching and area[i] > 1.4 * a0:
            parts = _split(blob, smooth[r0:r1, c0:c1], r_px) or [blob]
            if len(parts) > 1:
                parts = [blob] + parts
        keep_out, alone = None, False
        if np.count_nonzero(lab) > n_i:  # other components in the box: keep out of the neighbours' own edges
            keep_out = ~dilate((lab != 0) ^ blob)
        elif grown is not None:
            # alone in its box and in the ring just outside it (so no neighbour's pixel reaches the box's edge):
            # its dilation in the box is that of all the components
            q0, q1, p0, p1 = max(R0, r0 - 1), min(R1, r1 + 1), max(C0, c0 - 1), min(C1, c1 + 1)
            alone = np.count_nonzero(labels[q0 - R0:q1 - R0, p0 - C0:p1 - C0]) == n_i
        raw_bg = img_bg[r0 - R0:r1 - R0, c0 - C0:c1 - C0]  # (raw - bg)
        for part in parts:
            if part is blob and alone:
                foot = grown[r0 - R0:r1 - R0, c0 - C0:c1 - C0].copy()
            else:
                foot = dilate(part, k)
            if keep_out is not None:
                foot &= keep_out
            if part is not blob:
                foot &= ~(blob & ~part)  # a split half stays out of the other half
            m = _centroid(raw_bg * foot)  # (its spread is the blob's own, from _spread above)
            if m is None:
                continue
            centres.append((r0 + m[0], c0 + m[1]))
            if part is blob:
                areas.append(float(area[i]))
                means.append(mean_i)
                ratios.append(ratio)
            else:
                areas.append(float(part.sum()))
                means.append(float(raw[part].mean()))
                ratios.append(_moments(part.astype(float))[2])
            contrasts.append(contrast)
            feet.append((r0, c0, foot))
    # the blobs' width: the median minor axis of the single components with a tube's contrast (a tilted or
    # thick-slice section only grows along the tube, so the minor axis is the blob's diameter whatever the cut)
    width_mm = median(widths) * math.sqrt(rs * cs) if len(widths) >= 3 else float("nan")
    if not centres:
        return dataclasses.replace(Blobs.empty(bg, sigma_n, thr), width_mm=width_mm)
    return Blobs(
        centres_rc=np.asarray(centres, float),
        area_px=np.asarray(areas, float),
        mean_intensity=np.asarray(means, float),
        axis_ratio=np.asarray(ratios, float),
        contrast=np.asarray(contrasts, float),
        background=bg,
        noise_sigma=sigma_n,
        threshold=thr,
        footprints=tuple(feet),
        width_mm=width_mm,
    )


def _flatten(pixels, pixel_spacing_mm, d_mm: float, smooth_sigma_px, min_area_factor, max_area_factor,
             min_contrast) -> np.ndarray:
    """``pixels`` less their grey opening by a square three blob widths wide (the blob width as the image shows it)."""
    from scipy import ndimage as ndi  # rare paths: kept off a plain solve's start-up
    img = np.asarray(pixels, dtype=float)
    if img.ndim != 2 or img.size == 0 or not np.all(np.isfinite(img)):
        return img
    first = _detect(img, pixel_spacing_mm, d_mm, min_area_factor, max_area_factor, smooth_sigma_px=smooth_sigma_px,
                    min_contrast=min_contrast, dilate_px=None, split_touching=False)
    width = max(d_mm, first.width_mm) if math.isfinite(first.width_mm) else 2.0 * d_mm
    px = math.sqrt(float(pixel_spacing_mm[0]) * float(pixel_spacing_mm[1]))
    size = int(2 * math.ceil(1.5 * width / px) + 1)
    base = ndi.grey_opening(gaussian_smooth(img, 1.0), size=(size, size), mode="nearest")
    return np.maximum(img - base, 0.0)


def _split_levels(blob: np.ndarray, smooth: np.ndarray, threshold: float, min_area_px: float, max_area_px: float):
    """A component of several run-together blobs, cut into one region per blob; [] if it does not come apart.

    Raised levels (30, 50, 70 % of the way from the threshold to the peak)
    are tried in turn; at the first where the component breaks into two or
    more seeds, each of its pixels goes to the seed reached along the path of
    gentlest steps through the smoothed image (:func:`~chic_register.detect.watershed.watershed_ift`),
    the pixels around the component competing as background seeds: a region
    is the part of the component its seed reaches before the background does,
    often little more than the seed's own plateau. The split is kept when
    every region is at most ``max_area_px`` (regions under ``min_area_px``
    are dropped).
    """
    peak = float(smooth[blob].max())
    for frac in (0.3, 0.5, 0.7):
        above = np.ascontiguousarray(blob & (smooth > threshold + frac * (peak - threshold)))
        seeds, n = cc3d.connected_components(above, connectivity=4, return_N=True)
        if n < 2:
            continue
        size = np.bincount(seeds.ravel(), minlength=n + 1)
        size[0] = 0
        good = np.flatnonzero(size >= max(2, 0.1 * min_area_px))
        if good.size < 2:
            continue
        markers = np.where(np.isin(seeds, good), seeds, 0).astype(np.int32)
        markers[~blob] = -1
        depth = np.clip((peak - smooth) / max(peak - threshold, 1e-12) * 1000, 0, 65535).astype(np.uint16)
        ws = watershed_ift(depth, markers, blob, max_area_px)
        if ws is None:  # a region outgrew max_area_px
            continue
        regions = [(ws == g) & blob for g in good]
        sizes = [int(r.sum()) for r in regions]
        if max(sizes) > max_area_px:
            continue
        return [r for r, a in zip(regions, sizes) if a >= min_area_px]
    return []


def _split(blob: np.ndarray, smooth: np.ndarray, r_px: float):
    """Split a blob at its two strongest intensity peaks (>= one tube radius apart); None if single-peaked."""
    vals = np.where(blob, smooth, -np.inf)
    size = max(3, int(2 * round(0.8 * r_px) + 1))
    peaks = (vals == maximum_filter(vals, size)) & blob
    pr, pc = peaks.nonzero()
    if pr.size < 2:
        return None
    order = np.argsort(-smooth[pr, pc])
    pr, pc = pr[order], pc[order]
    first = (pr[0], pc[0])
    dist = np.hypot(pr - first[0], pc - first[1])
    far = np.flatnonzero(dist >= 1.2 * r_px)
    if far.size == 0:
        return None
    second = (pr[far[0]], pc[far[0]])
    rr, cc = np.nonzero(blob)
    d1 = np.hypot(rr - first[0], cc - first[1])
    d2 = np.hypot(rr - second[0], cc - second[1])
    a = np.zeros_like(blob)
    b = np.zeros_like(blob)
    a[rr[d1 <= d2], cc[d1 <= d2]] = True
    b[rr[d1 > d2], cc[d1 > d2]] = True
    return [a, b]


def pixel_mm(sl: Slice) -> float:
    return float(max(sl.pixel_spacing_mm))


def centres_xy_mm(blobs: Blobs, sl: Slice) -> np.ndarray:
    rc = blobs.centres_rc
    return np.stack([rc[:, 1] * sl.pixel_spacing_mm[1], rc[:, 0] * sl.pixel_spacing_mm[0]], axis=1)


def resolution_mm(sl: Slice, blobs: Blobs) -> float:
    """The unit of a slice's trust thresholds (mm): what its image can resolve, never less than a pixel.

    A centre is as precise as the blob is sharp: blobs wider than the tube
    (blur, partial volume, fluid around a printed channel; ``blobs.width_mm``
    measured in the image) and thick slices (a tilted tube's section is
    smeared over the thickness) both widen the error, so the unit is the
    largest of the pixel, a 7.5th of the blob width and a 6th of the slice
    thickness (equal to the pixel for 3 mm tubes at 0.5 mm pixels and 2-3 mm slices).
    """
    w = blobs.width_mm if math.isfinite(blobs.width_mm) else 0.0
    return max(pixel_mm(sl), w / 7.5, float(sl.slice_thickness_mm) / 6.0)
