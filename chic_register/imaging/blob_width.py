"""Blobs as wide as real images show them: a tube's blob drawn ``factor`` x its nominal width.

Real MRI blobs of a fiducial's tubes are 0.7-2.5x the tube's nominal diameter
(point spread, partial volume in 2-3 mm slices, fluid spreading in a printed
channel). :func:`render_tubes_widened` draws them so for the simulator
(:func:`chic_register.imaging.simulate.simulate_slice`, ``--blob-width``) and for
volumes (:func:`chic_register.imaging.simulate.simulate_volume`); see :class:`BlobWidth`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from chic_register.imaging.render import render_tubes

#: Allowed blob-width factors: real blobs are 0.7-2.5x the nominal diameter.
BLOB_WIDTH_RANGE = (0.2, 5.0)


def _disc_profile(c_mm, radius_mm: float, sigma_mm: float):
    """A disc of ``radius_mm`` blurred by an isotropic Gaussian of ``sigma_mm``, at ``c_mm`` from its centre.

    The share of a 2-D normal distribution centred at distance c that falls
    inside the disc: a non-central chi-square CDF.
    """
    from scipy.stats import ncx2  # deferred: loads scipy only when used (one-shot start-up)

    return ncx2.cdf((radius_mm / sigma_mm) ** 2, 2, (np.asarray(c_mm, dtype=float) / sigma_mm) ** 2)


def _blurred_disc_fwhm_mm(radius_mm: float, sigma_mm: float) -> float:
    """Full width at half maximum (mm) of a disc blurred by a Gaussian of ``sigma_mm``."""
    from scipy.optimize import brentq  # deferred: loads scipy only when used (one-shot start-up)

    half = 0.5 * float(_disc_profile(0.0, radius_mm, sigma_mm))
    return 2.0 * brentq(lambda c: float(_disc_profile(c, radius_mm, sigma_mm)) - half, 0.0, radius_mm + 10 * sigma_mm)


@dataclass(frozen=True)
class BlobWidth:
    """How a tube of ``diameter_mm`` is drawn so its blob is ``factor`` x its nominal width.

    factor <= 1: a narrower tube (``render_diameter_mm``), no blur. factor > 1:
    the tube at its own diameter, blurred by an isotropic in-plane Gaussian of
    ``sigma_mm`` chosen so the blob's full width at half maximum (tube across
    the slice, thin slice) is ``factor x diameter``, and scaled by ``gain`` so
    its peak is the fluid's signal again: real images show wide blobs (point
    spread, partial volume, fluid spread in a printed channel) at full
    brightness, and the noise is set relative to that signal.
    """

    diameter_mm: float
    factor: float
    render_diameter_mm: float
    sigma_mm: float = 0.0
    gain: float = 1.0

    @classmethod
    @lru_cache(maxsize=64)  # a root search per call: a volume asks the same per plane
    def for_tube(cls, diameter_mm: float, factor: float) -> "BlobWidth":
        lo, hi = BLOB_WIDTH_RANGE
        if not (lo <= factor <= hi):
            raise ValueError(f"blob width factor must be {lo:g}..{hi:g}, got {factor:g}")
        if factor <= 1.0:
            return cls(diameter_mm, factor, factor * diameter_mm)
        from scipy.optimize import brentq  # deferred: loads scipy only when used (one-shot start-up)

        r = diameter_mm / 2
        target = factor * diameter_mm
        # FWHM(sigma) dips below the diameter for sigma ~ r / 2 and rises after it: search above r / 3
        lo_s, hi_s = r / 3, r
        while _blurred_disc_fwhm_mm(r, hi_s) < target:
            hi_s *= 2
        sigma = brentq(lambda sg: _blurred_disc_fwhm_mm(r, sg) - target, lo_s, hi_s, xtol=1e-6 * r)
        return cls(diameter_mm, factor, diameter_mm, sigma, 1.0 / float(_disc_profile(0.0, r, sigma)))


def render_tubes_widened(tubes, T_F_from_S: np.ndarray, shape, pixel_spacing_mm, slice_thickness_mm: float = 0.0,
                         center_px=None, supersample: int = 4, thickness_samples: int = 5,
                         blob_width: float = 1.0) -> np.ndarray:
    """:func:`render_tubes` with every blob ``blob_width`` x its nominal width (see :class:`BlobWidth`).

    Tubes of one diameter are rendered and blurred together; groups are
    max-composited. ``blob_width = 1`` is :func:`render_tubes` exactly.
    """
    if blob_width == 1.0:
        return render_tubes(tubes, T_F_from_S, shape, pixel_spacing_mm, slice_thickness_mm, center_px,
                            supersample, thickness_samples)

    from scipy.ndimage import gaussian_filter  # deferred: loads scipy only when used (one-shot start-up)

    rs, cs = (float(v) for v in pixel_spacing_mm)
    out = None
    for d in sorted({t.diameter for t in tubes}):
        bw = BlobWidth.for_tube(d, float(blob_width))
        group = [replace(t, diameter=bw.render_diameter_mm) for t in tubes if t.diameter == d]
        img = render_tubes(group, T_F_from_S, shape, pixel_spacing_mm, slice_thickness_mm, center_px,
                           supersample, thickness_samples)
        if bw.sigma_mm > 0:
            img = bw.gain * gaussian_filter(img, (bw.sigma_mm / rs, bw.sigma_mm / cs), mode="constant", truncate=4.0)
        out = img if out is None else np.maximum(out, img)
    return out if out is not None else np.zeros(tuple(int(v) for v in shape))
