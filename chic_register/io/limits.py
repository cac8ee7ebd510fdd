"""What the image readers accept: physical ranges and sizes, checked before pixels are decoded.

Every refusal is an :class:`~chic_register.errors.ImageReadError` naming the file and the fault in one line.
"""

from __future__ import annotations

import math

import numpy as np

from chic_register.errors import ImageReadError

#: Physical range of a pixel spacing (mm): 10 um (microscopy-grade MRI) to 50 mm.
MIN_SPACING_MM = 0.01
MAX_SPACING_MM = 50.0
#: Largest slice read (pixels over all frames): 4096 x 4096 (128 MiB as float64; solving one took 0.5 GiB).
MAX_PIXELS = 4096 * 4096
#: Largest slice thickness taken from a file (mm); beyond it the value is refused.
MAX_THICKNESS_MM = 100.0

#: Luminance weights of R, G, B (ITU-R 601): colour images become grey.
LUMA = np.array([0.299, 0.587, 0.114])

def short_reason(exc: BaseException) -> str:
    """The first line of an exception's message, short enough for a one-line refusal."""
    text = str(exc).strip()
    first = text.splitlines()[0] if text else type(exc).__name__
    first = first.split(" - ")[0]
    return first if len(first) <= 120 else first[:117] + "..."


def spacing_fault(pixel_spacing) -> str | None:
    """Why ``pixel_spacing`` (row, col) mm is not a physical pixel spacing, or None when it is."""
    try:
        rs, cs = (float(v) for v in pixel_spacing)
    except (TypeError, ValueError):
        return f"pixel spacing must be two numbers (row, col), got {pixel_spacing!r}"
    if not all(math.isfinite(v) and MIN_SPACING_MM <= v <= MAX_SPACING_MM for v in (rs, cs)):
        return (f"pixel spacing must be two positive numbers in {MIN_SPACING_MM:g}..{MAX_SPACING_MM:g} mm, "
                f"got ({rs:g}, {cs:g})")
    return None


def check_spacing(path, pixel_spacing, kind: str) -> tuple[float, float]:
    """``pixel_spacing`` (row, col) mm of a plain ``kind`` image read from ``path``, or :class:`ImageReadError`."""
    if pixel_spacing is None:
        raise ImageReadError(
            path, f"a {kind} image has no geometry: give the pixel spacing (--pixel-spacing ROW COL, mm)"
        )
    fault = spacing_fault(pixel_spacing)
    if fault:
        raise ImageReadError(path, fault)
    rs, cs = (float(v) for v in pixel_spacing)
    return rs, cs


def check_size(path, shape, kind: str) -> None:
    """Refuse an image too large to be a slice before its pixels are decoded (memory bound)."""
    n = 1
    for v in shape:
        n *= max(int(v), 0)
    if n > MAX_PIXELS:
        raise ImageReadError(path, f"{kind} of shape {tuple(int(v) for v in shape)} is too large for a slice "
                                   f"(at most {MAX_PIXELS} pixels)")


#: Largest volume read (voxels): 512 x 512 x 256, 256 MiB as float32, read and copied once.
MAX_VOXELS = 2**26


def check_voxels(path, size, components: int) -> None:
    """Refuse a volume too large to read (from its header, before any voxel is decoded)."""
    n = components
    for v in size:
        n *= int(v)
    if n > MAX_VOXELS:
        raise ImageReadError(path, f"volume of size {tuple(int(v) for v in size)} is too large "
                                   f"(at most {MAX_VOXELS} voxels)")


def last_line(exc: Exception) -> str:
    """The last non-empty line of an exception's message (ITK puts the reason there)."""
    lines = [ln.strip() for ln in str(exc).strip().splitlines() if ln.strip()]
    return lines[-1] if lines else type(exc).__name__
