"""Pixels lost to dropout: zeros scattered through a noisy magnitude image (and NaN or infinite pixels), filled
from their neighbours.

A magnitude MR image has no exact zeros where there is signal or noise: its
values are Rician, positive almost surely. Scattered exact zeros inside a
noisy image are lost samples (a corrupted transfer, a reconstruction dropout,
a k-space spike's ringing clipped to zero), not the fluid's or the
background's level. Left in, they break a tube's section into fragments
whose shape no pose explains, and every fit that sums pixels is biased low.
So each is filled with the median of the valid pixels around it before the
solver looks at the image.

Only zeros amid signal are filled: where the valid pixels around are well
above the background (a lost pixel in the background changes nothing the
solver measures, and a background clipped at zero, as some reconstructions
do, has zeros that are the noise itself). Left alone too: an image mostly
zero (a noise-free render, or a volume masked outside the anatomy: its zeros
are a region, not scattered pixels), and zeros in a neighbourhood with too
few valid pixels to fill from (the inside of a masked region).

Bright specks (hot pixels) are filled the same way when the image is strewn
with them, or when one lies far beyond the image's bright level: a single
corrupt value at 100x the fluid's would otherwise set the detector's
threshold for the whole slice.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from chic_register.detect.blobs import median
from chic_register.util.quantiles import nan_median_rows

#: Largest share of exact zeros for which the image still counts as noisy: a noise-free render or a masked slice
#: is mostly zero (the fiducial's sections cover a few per cent of a slice), a noisy image with dropouts is not.
MAX_ZERO_SHARE = 0.5
#: Side (pixels) of the neighbourhood a lost pixel is filled from: wide enough to hold valid pixels at 40 %
#: dropout, narrow against a 3 mm tube's section (6 px across at 0.5 mm).
WINDOW_PX = 3
#: A lost pixel is filled only when this share of its neighbourhood is valid (else it is a masked region).
MIN_VALID_SHARE = 0.4
#: A lost pixel is filled only when its neighbours' median is this many noise sigmas above the background (the
#: median and MAD-sigma of the non-zero pixels, most of which are background).
SIGNAL_SIGMAS = 4.0
#: Zeros are lost samples only if they are about as common next to signal as in the whole image (this share of it
#: or more): dropouts fall anywhere, while a background clipped at zero has its zeros away from the signal.
SCATTER_SHARE = 0.5
#: A bright speck exceeds the median of its neighbours by this share of its height above the background ...
SPECK_ALONE = 0.9
#: ... and by this many noise sigmas (the median absolute deviation of the image)
SPECK_SIGMAS = 5.0
#: Specks are filled only when at least this share of the pixels are specks (an image strewn with impulse noise;
#: a few isolated bright pixels in a normal image are left as they are, and a slice whose bright pixels are fewer,
#: as a plain slice's tube sections are, costs one comparison).
MIN_SPECK_SHARE = 0.01
#: Fewer exact zeros than this share are not worth a pass (integer images may round a few background pixels to 0).
MIN_ZERO_SHARE = 0.002
#: A speck this many times farther from the background than the image's bright level (:data:`EXTREME_RANK`) is
#: filled even alone: one corrupt pixel at 100x the fluid's level would otherwise set the detector's threshold
#: for the whole image (a speck below 30x the fluid is harmless: the detector's own area and contrast tests).
EXTREME_FACTOR = 10.0
#: The image's bright level: the height of the this-many-th brightest pixel of a sixteenth of the image (the
#: fluid's level when the fiducial's sections cover a few per cent of the slice; the noise's top when they do not,
#: and then a section still shares its level with its neighbours, so is not a speck).
EXTREME_RANK = 8
#: At most this share of the pixels may be extreme specks (more is an object or an image scaled in parts, not
#: corrupt pixels).
MAX_EXTREME_SHARE = 0.001


def _neighbourhoods(img: np.ndarray, fill) -> np.ndarray:
    """(rows, cols, WINDOW_PX, WINDOW_PX) view of every pixel's neighbourhood, the border padded with ``fill``."""
    h = WINDOW_PX // 2
    return sliding_window_view(np.pad(img, h, constant_values=fill), (WINDOW_PX, WINDOW_PX))


def _box_count(mask: np.ndarray) -> np.ndarray:
    """(rows, cols) int: the True pixels of every pixel's ``WINDOW_PX`` neighbourhood, the border padded False
    (the sum over :func:`_neighbourhoods`, in separable passes: a reduction over a strided view costs ten times
    more)."""
    h, n = WINDOW_PX // 2, WINDOW_PX
    p = np.pad(mask.astype(np.int32), h)
    rows = sum(p[i:p.shape[0] - n + 1 + i] for i in range(n))
    return sum(rows[:, j:rows.shape[1] - n + 1 + j] for j in range(n))


def fill_dropouts(pixels: np.ndarray) -> tuple[np.ndarray, int]:
    """``(pixels, n_filled)``: each lost pixel (not a finite number, a bright speck, or an exact zero amid signal,
    see the module's doc) replaced by the median of the valid pixels of its ``WINDOW_PX`` neighbourhood; the input itself when there
    are none."""
    return lost_pixels(pixels)[:2]


def lost_pixels(pixels: np.ndarray) -> tuple[np.ndarray, int, np.ndarray | None]:
    """:func:`fill_dropouts`, and the (rows, cols) bool mask of the lost pixels (None when there are none): the
    filled ones, and every exact zero of an image whose zeros are lost samples (those in the background too, which
    are not filled: a fit over a section's surroundings must leave them out as well)."""
    img = np.asarray(pixels)
    # the range, once: a NaN or an infinity anywhere shows in it, and an image of positive (or negative) pixels only
    # has no exact zero, before the specks are filled or after (a speck takes the median of its neighbours)
    lo = hi = math.nan
    if img.size and img.dtype.kind in "fiu":
        lo, hi = float(np.minimum.reduce(img, axis=None)), float(np.maximum.reduce(img, axis=None))
    pixels, n_bad = _fill_non_finite(pixels, lo, hi)
    pixels, n_specks = _fill_specks(pixels, nonzero=not n_bad and (lo > 0 or hi < 0),
                                    lo_hi=None if n_bad else (lo, hi))
    if not n_bad and (lo > 0 or hi < 0):
        return pixels, n_specks, _changed(img, pixels) if n_specks else None
    filled, n_zero, zeros = _fill_zeros(pixels)
    n = n_bad + n_specks + n_zero
    lost = _changed(img, filled) if n else None
    if zeros is not None:
        lost = zeros if lost is None else lost | zeros
    return filled, n, lost


def _changed(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """(rows, cols) bool: the pixels a fill changed (a NaN counts as changed)."""
    return ~(np.asarray(before) == np.asarray(after))


def _fill_non_finite(pixels: np.ndarray, lo: float, hi: float) -> tuple[np.ndarray, int]:
    """NaN or infinite pixels (a processing step's holes) filled from their finite neighbours, or with the median of
    the finite pixels where they have none. ``lo``, ``hi``: the pixels' range (NaN or an infinity anywhere shows in
    one of them; NaN too for an empty image)."""
    img = np.asarray(pixels)
    if img.dtype.kind != "f":  # (np.issubdtype(dtype, np.floating), less its overhead)
        return pixels, 0
    if math.isfinite(lo) and math.isfinite(hi):
        return pixels, 0
    finite = np.isfinite(img)
    bad = ~finite
    n = int(bad.sum())
    if n == img.size:
        return pixels, 0
    out = img.astype(float)
    hoods = _neighbourhoods(np.where(bad, np.nan, out), np.nan)[bad].reshape(n, -1)
    has = np.isfinite(hoods).any(axis=1)
    fill = np.full(n, median(out[~bad]))
    if has.any():
        fill[has] = nan_median_rows(hoods[has])
    out[bad] = fill
    return out, n


def _fill_specks(pixels: np.ndarray, nonzero: bool = False, lo_hi=None) -> tuple[np.ndarray, int]:
    """Bright specks (hot pixels, impulse noise) replaced by the median of their neighbours, when the image is strewn
    with them (:data:`MIN_SPECK_SHARE`) or one stands far beyond the image's bright level (:data:`EXTREME_FACTOR`);
    ``nonzero``: the caller knows that no pixel is 0; ``lo_hi``: the pixels' (finite) range when known.

    A speck stands alone: it exceeds the median of its eight neighbours by
    nearly its whole height above the background (:data:`SPECK_ALONE`) and by
    :data:`SPECK_SIGMAS` noise sigmas. A tube's section, even at 3 pixels
    across, shares its level with half its neighbours at least.
    """
    img = np.asarray(pixels, float)
    if img.ndim != 2 or min(img.shape) < 3:
        return pixels, 0
    grid = img[::4, ::4]  # the background and noise level from a sixteenth of the pixels: cheap and ample
    # (zeros: a clipped or masked background, not the noise's spread)
    sample = grid.ravel() if nonzero else grid[grid != 0]
    mostly_zero = sample.size < 16  # (a noise-free render, a masked slice: only a lone extreme pixel is filled)
    if mostly_zero:
        sample = grid.ravel()
    background = median(sample)  # (np.median's value, without its overhead: finite pixels here)
    if not math.isfinite(background):  # (an image of NaNs or infinities: nothing to fill from)
        return pixels, 0
    spread = np.abs(sample - background)
    sigma = max(1.4826 * median(spread), 1e-12)
    img, n_extreme = _fill_extreme_specks(img, spread, background, sigma, lo_hi)
    if n_extreme:
        pixels = img
    if mostly_zero:
        return pixels, n_extreme
    level = SPECK_SIGMAS * sigma
    # too few bright pixels to hold that many specks (a plain slice: its tube sections): counted first on a
    # superset, the pixels above background + level less a slack far beyond the subtraction's rounding, then
    # exactly (img - background > level) on those only, before the whole image is worked on
    maybe = img > (background + level) - 1e-9 * (abs(background) + level)
    need = MIN_SPECK_SHARE * img.size
    if np.count_nonzero(maybe) < need or np.count_nonzero(img[maybe] - background > level) < need:
        return pixels, n_extreme
    height = img - background
    # a quick look (pixels above every one of their eight neighbours by far), then the rule itself
    padded = np.pad(img, 1, constant_values=-np.inf)
    h, w = img.shape
    top = np.full(img.shape, -np.inf)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr or dc:
                np.maximum(top, padded[1 + dr:1 + dr + h, 1 + dc:1 + dc + w], out=top)
    alone = (img - top > SPECK_ALONE * height) & (img - top > SPECK_SIGMAS * sigma)
    if alone.sum() < 0.5 * MIN_SPECK_SHARE * img.size:
        return pixels, n_extreme
    # then the rule itself, on the bright pixels only: far above the median of their neighbours
    bright = np.flatnonzero(height > SPECK_SIGMAS * sigma)
    rows, cols = np.unravel_index(bright, img.shape)
    hoods = _neighbourhoods(img, np.nan)[rows, cols].reshape(bright.size, -1)
    nb = nan_median_rows(np.delete(hoods, hoods.shape[1] // 2, axis=1))
    value = img[rows, cols]
    speck = (value - nb > SPECK_ALONE * height[rows, cols]) & (value - nb > SPECK_SIGMAS * sigma)
    n = int(speck.sum())
    if n < MIN_SPECK_SHARE * img.size:
        return pixels, n_extreme
    out = img.copy()
    out[rows[speck], cols[speck]] = nb[speck]
    return out, n + n_extreme


def _fill_extreme_specks(img: np.ndarray, spread: np.ndarray, background: float, sigma: float, lo_hi=None):
    """``(img, n)``: lone pixels :data:`EXTREME_FACTOR` times farther from ``background`` than the bright level of a
    sample of the image (``spread``: its distances from ``background``; either way: a corrupt value may be hugely
    negative too) set to the median of their neighbours.
    Most images have none, which one partial sort of the sample and the image's range show."""
    lo, hi = lo_hi if lo_hi is not None else (float(np.minimum.reduce(img, axis=None)),
                                               float(np.maximum.reduce(img, axis=None)))
    k = min(EXTREME_RANK, spread.size)
    bright = max(float(np.partition(spread, spread.size - k)[spread.size - k]), SPECK_SIGMAS * sigma)
    reach = EXTREME_FACTOR * bright
    if hi - background <= reach and background - lo <= reach:
        return img, 0
    far = np.flatnonzero(np.abs(img - background) > reach)
    if far.size == 0 or far.size > MAX_EXTREME_SHARE * img.size:  # (none: an image of NaNs, whose range is NaN)
        return img, 0
    rows, cols = np.unravel_index(far, img.shape)
    hoods = np.delete(_neighbourhoods(img, np.nan)[rows, cols].reshape(far.size, -1), WINDOW_PX ** 2 // 2, axis=1)
    nb = nan_median_rows(hoods)
    # alone: EXTREME_FACTOR times farther from the background than every one of its neighbours (a section's pixel
    # has a neighbour at its own level, even amid lost pixels)
    dev = np.abs(img[rows, cols] - background)
    speck = dev > EXTREME_FACTOR * np.nanmax(np.abs(hoods - background), axis=1)
    if not speck.any():
        return img, 0
    out = img.copy()
    out[rows[speck], cols[speck]] = nb[speck]
    return out, int(speck.sum())


def _fill_zeros(pixels: np.ndarray) -> tuple[np.ndarray, int, np.ndarray | None]:
    """Exact zeros amid the signal of a noisy image filled (see the module's doc); ``(pixels, n_filled, zeros)``,
    ``zeros`` the mask of every exact zero when they are lost samples, else None."""
    img = np.asarray(pixels)
    zero = img == 0
    share = np.count_nonzero(zero) / zero.size if zero.size else 0.0  # (zero.mean(), in one pass)
    if not (MIN_ZERO_SHARE <= share <= MAX_ZERO_SHARE) or not np.all(np.isfinite(img)):
        return pixels, 0, None
    img = img.astype(float)
    valid = img[~zero]
    background = median(valid)
    level = background + SIGNAL_SIGMAS * 1.4826 * median(np.abs(valid - background))
    # lost samples fall anywhere, signal or not; zeros that are clipped noise avoid the signal
    near_signal = _box_count(img > level) > 0
    if not near_signal.any() or zero[near_signal].mean() < SCATTER_SHARE * share:
        return pixels, 0, None
    valid_share = _box_count(~zero) / float(WINDOW_PX * WINDOW_PX)
    candidates = zero & (valid_share >= MIN_VALID_SHARE)
    if not candidates.any():
        return pixels, 0, zero
    hoods = _neighbourhoods(np.where(zero, np.nan, img), np.nan)[candidates]  # (n, W, W)
    fill = nan_median_rows(hoods.reshape(len(hoods), -1))
    lost = fill > level
    if not lost.any():
        return pixels, 0, zero
    out = img.copy()
    rows, cols = np.nonzero(candidates)
    out[rows[lost], cols[lost]] = fill[lost]
    return out, int(lost.sum()), zero


def fill_slice_dropouts(slices: list) -> tuple[list, dict]:
    """The slices with their lost pixels filled and marked (``Slice.lost``, :func:`lost_pixels`), and
    ``{source: n filled}``."""
    out, filled = [], {}
    for sl in slices:
        given = None
        if sl.lost is not None:  # a mask the caller gave: kept beside the one found here
            given = np.asarray(sl.lost, dtype=bool)
            if given.shape != np.shape(sl.pixels):
                raise ValueError(f"{sl.source}: Slice.lost has shape {given.shape}; the pixels have shape "
                                 f"{np.shape(sl.pixels)}")
        pixels, n, lost = lost_pixels(sl.pixels)
        if given is not None:
            lost = given if lost is None else lost | given
        if n or lost is not sl.lost:
            sl = dataclasses.replace(sl, pixels=pixels, lost=lost)
        if n:
            filled[sl.source] = filled.get(sl.source, 0) + n
        out.append(sl)
    return out, filled
