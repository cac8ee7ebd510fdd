"""Is a slice a magnitude image? Signed images (a real part, phase-sensitive or subtracted) are refused.

The solver models what a magnitude MR image shows: fluid bright, plastic and
air dark, the background's noise Rician and so never below zero. The real
part of a complex image whose phase drifts across the field is that image
times the cosine of the phase: sections are shaded, dimmed or turned
negative where the cosine is, and their shading pulls every fitted position
the same way (a pose 0.5-0.9 deg off whose residuals look like noise, in the
unlisted-damage hunt). Its telltale is in the background: a magnitude
image's noise averages above zero everywhere, a signed image's averages
below zero where the phase has turned and above it elsewhere. An offset
subtracted from the noise of a magnitude image (a display or scaling
offset) shifts every background block alike, so it is not mistaken for
one; but an offset larger than the noise under dim tissue (below the tubes'
level) leaves air blocks below zero and tissue blocks above it, and such an
image is refused too (its reason says to remove the offset): a refusal,
never a wrong pose. Blocks with less spread than the noise (a mask, padding)
are no noise samples and are not counted.
"""

from __future__ import annotations

import math

import numpy as np

from chic_register.detect.noise import clear_blocks
from chic_register.errors import NoLock

#: Side (pixels) of the background blocks whose means are compared: 64 noise samples, a standard error of the mean
#: of about a tenth of the noise, and dozens of blocks in the smallest slice the solver takes ...
BLOCK_PX = 8
#: ... clear of every blob's footprint grown by this many pixels (as the noise estimates' blocks).
GUARD_PX = 3
#: A block's mean is of one sign when it lies this many of its standard errors from zero (a 3e-7 tail each) ...
SIGN_SIGMAS = 5.0
#: ... and this share of the image's noise from it (a mask's edge, half noise and half a constant, does not) ...
SIGN_DEPTH = 0.5
#: ... and the image is signed when at least this many background blocks are of each sign ...
MIN_SIGNED_BLOCKS = 3
#: ... and this share of them (a phase that turns within the field turns a large part of it).
MIN_SIGNED_SHARE = 0.05


def signed_blocks(pixels: np.ndarray, footprints, noise_sigma: float = 0.0) -> tuple[int, int]:
    """``(negative, positive)``: how many :data:`BLOCK_PX`-square blocks of ``pixels`` (rows, cols) clear of the
    blobs (``footprints``, the detector's: :func:`~chic_register.detect.noise.clear_blocks`) and with a spread of at
    least half ``noise_sigma`` (noise samples, not a mask) have a mean significantly below zero, and how many
    significantly above (:data:`SIGN_SIGMAS` standard errors of the block's mean and :data:`SIGN_DEPTH` noise
    sigmas)."""
    img = np.asarray(pixels, dtype=float)
    b = BLOCK_PX
    h, w = img.shape[0] // b, img.shape[1] // b
    if h * w == 0:
        return 0, 0
    clear = clear_blocks(img, footprints, GUARD_PX, b)  # (h, w)
    blocks = img[:h * b, :w * b].reshape(h, b, w, b).swapaxes(1, 2)[clear].reshape(-1, b * b)
    if blocks.shape[0] == 0:
        return 0, 0
    mean = blocks.mean(axis=1)
    spread = blocks.std(axis=1, ddof=1)
    noisy = spread > max(0.5 * noise_sigma, 0.0)
    mean = mean[noisy]
    far = np.maximum(SIGN_SIGMAS * spread[noisy] / b, SIGN_DEPTH * noise_sigma)
    return int(np.count_nonzero(mean < -far)), int(np.count_nonzero(mean > far))


def refuse_signed(pixels: np.ndarray, blobs, source: str, lowest: float = math.nan) -> None:
    """:class:`NoLock` when ``pixels`` are signed, not magnitudes (see the module's doc); free for an image with no
    negative pixel. ``blobs``: the detector's :class:`~chic_register.detect.blobs.Blobs` of the image (footprints,
    noise); ``lowest``: the smallest pixel, when known (NaN: found here)."""
    img = np.asarray(pixels)
    if img.size == 0 or img.dtype.kind == "u":
        return
    lo = lowest if not math.isnan(lowest) else float(np.minimum.reduce(img, axis=None))
    if not lo < 0 or not math.isfinite(lo):  # (a NaN or -inf pixel: refused elsewhere; blocks holding one are not
        return                                # counted)
    negative, positive = signed_blocks(img, blobs.footprints, blobs.noise_sigma)
    if min(negative, positive) >= max(MIN_SIGNED_BLOCKS, MIN_SIGNED_SHARE * (negative + positive)):
        raise NoLock(f"{source}: the image is signed, not a magnitude image: its background averages below zero in "
                     f"{negative} blocks of {BLOCK_PX} px and above zero in {positive} (the real part of a complex "
                     f"image, a phase-sensitive or a subtracted one, or an offset subtracted?); register the magnitude image, "
                     f"without an offset",
                     {"negative_blocks": negative, "positive_blocks": positive})
