"""A slice as every stage after detection sees it: the image, where it lies, and the blobs found in it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from chic_register.detect.blobs import Blobs, centres_xy_mm, resolution_mm
from chic_register.model.slices import Slice


@dataclass(frozen=True, eq=False)
class DetectedSlice:
    """One slice with its detected blobs.

    ``T_scanner_from_image`` (4, 4): the slice's image frame (mm) in the
    scanner's; ``xy_mm`` (N, 2): the blob centres in image mm (x along the
    columns, y along the rows); ``resolution_mm``: the unit of the slice's
    trust thresholds (:func:`~chic_register.detect.blobs.resolution_mm`).
    """

    slice: Slice
    blobs: Blobs
    T_scanner_from_image: np.ndarray
    xy_mm: np.ndarray
    resolution_mm: float

    @classmethod
    def of(cls, sl: Slice, blobs: Blobs, T_scanner_from_image: np.ndarray | None = None) -> DetectedSlice:
        """``sl`` with ``blobs``; its frame computed unless given."""
        S = sl.T_scanner_from_image() if T_scanner_from_image is None else T_scanner_from_image
        return cls(sl, blobs, S, centres_xy_mm(blobs, sl), resolution_mm(sl, blobs))

    @property
    def source(self) -> str:
        return self.slice.source
