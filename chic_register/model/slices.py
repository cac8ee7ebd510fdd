"""A 2-D image slice with its place in the scanner (docs/interfaces.md section 3).

Every reader returns :class:`Slice` objects and the solver only ever sees
these, whatever the file format was.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, eq=False)
class Slice:
    """Pixels plus geometry.

    ``pixels`` has shape (rows, cols). ``origin_mm`` is the scanner position
    of the centre of pixel (row 0, col 0); ``col_dir`` is the unit direction
    of increasing column index, ``row_dir`` of increasing row index (DICOM's
    ImageOrientationPatient order); ``pixel_spacing_mm`` is (row spacing,
    col spacing), i.e. the distance between rows, then between columns, as
    DICOM's PixelSpacing. The scanner frame is LPS for DICOM and volumes, and
    the image frame itself for plain arrays.
    """

    pixels: np.ndarray
    pixel_spacing_mm: tuple[float, float]
    origin_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    col_dir: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    row_dir: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    slice_thickness_mm: float = 0.0
    source: str = "<array>"
    #: (rows, cols) bool, or None: pixels that carry no measurement (lost to dropout: filled by the solver, or zeros
    #: it leaves; a caller may mark more), which the section fit leaves out (:mod:`chic_register.detect.dropout`)
    lost: np.ndarray | None = None
    #: "MR" (a magnitude image: Rician noise, never below zero), "CT" (Hounsfield units: signed, Gaussian noise)
    #: or "auto" (the detection stage decides from the pixels: :func:`chic_register.detect.ct.looks_hounsfield`)
    modality: str = "auto"
    #: True when ``pixels`` are the detection image made from the file's (a CT slice's white top-hat), not the file's
    detection_image: bool = False
    #: the pixels' noise sigma when measured before ``pixels`` were made (a CT slice's, on its Hounsfield values:
    #: its top-hat's own background reads lower than the noise on the rods), else None
    pixel_noise_sigma: float | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.pixels.shape

    @property
    def normal(self) -> np.ndarray:
        a, b = np.asarray(self.col_dir), np.asarray(self.row_dir)
        if a.shape == b.shape == (3,) and a.dtype == b.dtype == np.float64:
            # np.cross's own products and differences on floats (its array wrapper costs ~20 us a call)
            (a0, a1, a2), (b0, b1, b2) = a.tolist(), b.tolist()
            n = np.array([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0])
        else:
            n = np.cross(self.col_dir, self.row_dir)
        return n / np.linalg.norm(n)

    def T_scanner_from_image(self) -> np.ndarray:
        """4x4 transform from the image frame to the scanner frame.

        Image frame: origin at the centre of pixel (0, 0), x along ``col_dir``
        (mm), y along ``row_dir`` (mm), z = x × y.
        """
        T = np.eye(4)
        T[:3, 0] = self.col_dir
        T[:3, 1] = self.row_dir
        T[:3, 2] = self.normal
        T[:3, 3] = self.origin_mm
        return T

    def pixel_to_image_mm(self, rows, cols) -> np.ndarray:
        """(row, col) pixel coordinates (sub-pixel allowed) to image-frame (x, y) mm; shape (N, 2)."""
        rows = np.atleast_1d(np.asarray(rows, dtype=float))
        cols = np.atleast_1d(np.asarray(cols, dtype=float))
        return np.stack([cols * self.pixel_spacing_mm[1], rows * self.pixel_spacing_mm[0]], axis=1)

    def image_mm_to_pixel(self, xy_mm) -> np.ndarray:
        """Image-frame (x, y) mm to (row, col) pixel coordinates; shape (N, 2)."""
        xy = np.atleast_2d(np.asarray(xy_mm, dtype=float))
        return np.stack([xy[:, 1] / self.pixel_spacing_mm[0], xy[:, 0] / self.pixel_spacing_mm[1]], axis=1)

    def pixel_to_scanner(self, rows, cols) -> np.ndarray:
        """(row, col) pixel coordinates to scanner-frame points (mm); shape (N, 3)."""
        xy = self.pixel_to_image_mm(rows, cols)
        return self.origin_mm + xy[:, :1] * self.col_dir + xy[:, 1:] * self.row_dir
