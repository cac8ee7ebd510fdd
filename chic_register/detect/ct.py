"""CT slices: Hounsfield units told from magnitude MR, and the image the detector reads in a CT slice.

A CT slice is signed by nature (air at -1000 HU, padding outside the
reconstruction circle at -1024 to -3024) and its noise is Gaussian, not
Rician; contrast-filled rods sit in plastic plates about a thousand HU
above the air around them, and bone and metal streaks are bright too. So a
CT slice is not refused as "signed"; the detector and the section fit read
it as its linear top-hat (:func:`ct_detection_image`): the slice less the
largest of its grey openings by straight lines in every direction, each
:data:`LINE_WIDTHS` rod diameters long. A structure that holds such a line
in some direction survives that opening and is removed: the plates the
rods sit in (however thin), the head, bone edges and metal streaks; a rod's
section, shorter than the line in every direction, stays as a bright
section on a flat, near-zero background with the CT's Gaussian noise
(Soille's supremum of linear openings). The raw Hounsfield values stay in
the file and the overlay.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from chic_register.model.slices import Slice

#: Modalities of :attr:`chic_register.model.slices.Slice.modality`: "auto" decides from the pixels
#: (:func:`looks_hounsfield`).
MODALITIES = ("auto", "MR", "CT")
#: Air in Hounsfield units and the band around it that a calibrated CT's air falls in.
AIR_HU = -1000.0
AIR_BAND_HU = 150.0
#: A slice is in Hounsfield units when at least this share of its pixels lies at or below the air band's top (air
#: and the padding outside the reconstruction circle) and its brightest pixels are far above air.
MIN_AIR_SHARE = 0.05
#: Length of the top-hat's lines, in rod diameters: longer than a rod's section as a CT shows it (blurred to 1.5-2.5
#: diameters, and 1.4 times longer again for a rod at 45 degrees to the slice), short beside the plates.
LINE_WIDTHS = 5.0
#: Directions of the lines (evenly over a half turn): a line within 7.5 degrees of a plate's direction fits in it.
LINE_DIRECTIONS = 12


def looks_hounsfield(pixels: np.ndarray) -> bool:
    """True for a slice in Hounsfield units: a share of air (or darker padding) near -1000 and
    structures above water; a magnitude MR image has no values below zero at all."""
    img = np.asarray(pixels)
    if img.size == 0:
        return False
    lo = float(np.min(img))
    if not (math.isfinite(lo) and lo <= AIR_HU + AIR_BAND_HU):
        return False
    dark = np.count_nonzero(img <= AIR_HU + AIR_BAND_HU) / img.size
    return dark >= MIN_AIR_SHARE and float(np.max(img)) > 0.0


def slice_modality(modality: str, pixels: np.ndarray) -> str:
    """``"MR"`` or ``"CT"``: ``modality`` itself, or for ``"auto"`` what :func:`looks_hounsfield` says."""
    if modality == "auto":
        return "CT" if looks_hounsfield(pixels) else "MR"
    return modality


def line_footprint(length_px: int, angle_rad: float) -> np.ndarray:
    """A straight line of ``length_px`` pixels (odd) through the centre of a square boolean footprint."""
    h = length_px // 2
    t = np.linspace(-h, h, 2 * length_px + 1)
    rows = np.rint(h - t * math.sin(angle_rad)).astype(int)
    cols = np.rint(h + t * math.cos(angle_rad)).astype(int)
    fp = np.zeros((length_px, length_px), bool)
    fp[rows, cols] = True
    return fp


def ct_detection_image(pixels_hu: np.ndarray, pixel_spacing_mm, rod_diameter_mm: float) -> np.ndarray:
    """The linear top-hat of a CT slice (rows, cols), see the module docstring: Hounsfield values less the
    largest of their openings by lines :data:`LINE_WIDTHS` rod diameters long in :data:`LINE_DIRECTIONS`
    directions. Padding below air is set to air first, so the reconstruction circle's edge is no structure."""
    from scipy import ndimage as ndi  # deferred: a CT slice only; keeps a one-shot MR solve from loading scipy.ndimage

    img = np.maximum(np.asarray(pixels_hu, dtype=np.float32), AIR_HU)
    px = min(float(pixel_spacing_mm[0]), float(pixel_spacing_mm[1]))
    length = int(2 * math.ceil(0.5 * LINE_WIDTHS * max(rod_diameter_mm, 2 * px) / px) + 1)
    base = np.full(img.shape, AIR_HU, np.float32)
    for k in range(LINE_DIRECTIONS):
        fp = line_footprint(length, math.pi * k / LINE_DIRECTIONS)
        np.maximum(base, ndi.grey_opening(img, footprint=fp, mode="nearest"), out=base)
    return (img - base).astype(float)


def detection_slice(sl: Slice, rod_diameter_mm: float) -> Slice:
    """``sl`` with its modality decided (:func:`slice_modality`); a CT slice with its pixels replaced by
    :func:`ct_detection_image` (``detection_image`` set), the image the detector and every later stage read."""
    if sl.detection_image:
        return sl
    modality = slice_modality(sl.modality, sl.pixels)
    if modality != "CT":
        return sl if sl.modality == modality else dataclasses.replace(sl, modality=modality)
    return dataclasses.replace(sl, pixels=ct_detection_image(sl.pixels, sl.pixel_spacing_mm, rod_diameter_mm),
                               modality="CT", detection_image=True, pixel_noise_sigma=ct_noise_sigma(sl.pixels))


def ct_noise_sigma(pixels_hu: np.ndarray) -> float | None:
    """The noise sigma (HU) of a CT slice: the median absolute difference of neighbouring pixels along rows,
    over pairs inside the reconstruction circle (both above the padding), as for Gaussian noise; None if
    too few. Edges are a small share of the pairs."""
    img = np.asarray(pixels_hu, dtype=float)
    if img.ndim != 2 or img.shape[1] < 2:
        return None
    inside = img > AIR_HU - AIR_BAND_HU
    both = inside[:, 1:] & inside[:, :-1]
    d = np.abs(np.diff(img, axis=1))[both]
    if d.size < 256:
        return None
    sigma = float(np.median(d)) / (math.sqrt(2.0) * 0.6745)
    return sigma if sigma > 0 else None
