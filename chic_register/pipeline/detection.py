"""The registration's detection stage: lost pixels filled, pixel values checked, blobs found, signed images refused.

:func:`detect_slices` gives every slice as a
:class:`~chic_register.detect.detected.DetectedSlice`; :func:`second_look`
detects one again on the flattened image, for a slice whose tubes may have
been lost to their surroundings (:func:`worth_flattening`).
"""

from __future__ import annotations

import math

import numpy as np

from chic_register.detect.blobs import Blobs, detect_blobs, median
from chic_register.detect.ct import detection_slice
from chic_register.detect.detected import DetectedSlice
from chic_register.detect.filters import SAFE_MAGNITUDE
from chic_register.detect.magnitude import refuse_signed
from chic_register.detect.noise import difference_sigma
from chic_register.errors import NoLock
from chic_register.model.slices import Slice
from chic_register.model.tube_model import TubeModel


def detect_slices(slices: list[Slice], lows: list[float], model: TubeModel,
                  detect_options: dict | None = None) -> list[DetectedSlice]:
    """Each slice's blobs (:func:`~chic_register.detect.blobs.detect_blobs` with ``detect_options``); a signed
    image is refused (``lows``: each slice's smallest pixel, from :func:`check_pixel_range`)."""
    seen = []
    for sl, lo in zip(slices, lows):
        sl = as_detected_image(sl, model)
        b = detect_blobs(sl.pixels, sl.pixel_spacing_mm, model.diameter_mm, **_modality_options(sl, detect_options))
        if sl.modality == "MR":
            refuse_signed(sl.pixels, b, sl.source, lo)
        seen.append(DetectedSlice.of(sl, b))
    return seen


def as_detected_image(sl: Slice, model: TubeModel) -> Slice:
    """``sl`` as the detector reads it (:func:`~chic_register.detect.ct.detection_slice` at the tubes' median
    diameter): a CT slice as its linear top-hat."""
    return detection_slice(sl, median(np.atleast_1d(model.diameter_mm)))


#: A CT slice's detection level, at most this many noise sigmas above its top-hat's median
#: (:func:`~chic_register.detect.blobs.detect_blobs`' ``noise_threshold_sigmas``): metal or bone far brighter than
#: the rods would otherwise draw Otsu's level above them.
CT_THRESHOLD_SIGMAS = 25.0


def _modality_options(sl: Slice, detect_options: dict | None) -> dict:
    """The detector's options for ``sl``: ``detect_options``, and a CT slice's noise-bound level."""
    out = dict(detect_options or {})
    if sl.modality == "CT":
        out.setdefault("noise_threshold_sigmas", CT_THRESHOLD_SIGMAS)
    return out


def second_look(d: DetectedSlice, model: TubeModel, detect_options: dict | None = None) -> DetectedSlice:
    """``d`` detected again on its flattened image (tissue touching the tubes, a dim side of the image)."""
    b = detect_blobs(d.slice.pixels, d.slice.pixel_spacing_mm, model.diameter_mm, flatten_background=True,
                     **_modality_options(d.slice, detect_options))
    return DetectedSlice.of(d.slice, b, d.T_scanner_from_image)


#: Largest pixel magnitude the detector takes (its smoothing is in single precision).
MAX_PIXEL_MAGNITUDE = SAFE_MAGNITUDE


def check_pixel_range(slices: list[Slice]) -> list[float]:
    """Raise :class:`NoLock` for a slice whose pixels (lost ones already filled) reach beyond
    :data:`MAX_PIXEL_MAGNITUDE`: no MR image holds such values (a rescale slope or a conversion gone wrong).
    Returns each slice's smallest pixel (NaN when not computed: an empty or integer image)."""
    lows = []
    for sl in slices:
        img = np.asarray(sl.pixels)
        if img.size == 0 or img.dtype.kind != "f":
            lows.append(math.nan)
            continue
        lo, hi = float(np.minimum.reduce(img, axis=None)), float(np.maximum.reduce(img, axis=None))
        lows.append(lo)
        peak = max(abs(lo), abs(hi))
        if peak > MAX_PIXEL_MAGNITUDE and math.isfinite(lo) and math.isfinite(hi):
            raise NoLock(f"{sl.source}: pixel values reach {peak:.3g}, beyond the {MAX_PIXEL_MAGNITUDE:.3g} the detector "
                         "takes (single precision): rescale the image (a rescale slope or a unit conversion gone wrong?)",
                         {"pixel_peak": peak})
    return lows


def worth_flattening(blobs: Blobs, model: TubeModel, pixels: np.ndarray) -> bool:
    """A slice whose detection may have lost tubes to their surroundings: something bright, but not a blank image.

    "Bright" is Otsu's split beyond four noise sigmas, as the detector measures the noise, or as the differences
    of neighbouring pixels do (:func:`chic_register.detect.noise.difference_sigma`): the detector's background mixes a
    dark and a bright region when a fiducial lies in a water bath (the median is the water, the tubes sit in dark
    plastic), and its noise then reads ten times too large. (A NaN estimate compares false.)"""
    if not (math.isfinite(blobs.threshold) and blobs.noise_sigma > 0 and len(blobs) < 3 * len(model.ids)):
        return False
    split = blobs.threshold - blobs.background
    return split > 4 * blobs.noise_sigma or split > 4 * difference_sigma(pixels)
