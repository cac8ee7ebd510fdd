"""What real scanners do to an image that the simulator's perfect one does not: scale, distortion, shading, tissue.

:class:`ScannerEffects` names them; :func:`apply_scanner_effects` draws them
into a simulated slice's pixels (:func:`chic_register.studies.distortion.apparent_pose`
is then the pose the image shows: a scanner that shows the frame 0.5 % larger
shows it at another pose, and no image can tell).

- ``scale`` (2,): the image larger than the world by this share along its
  columns (x) and rows (y), about the scanner's isocentre (a gradient
  calibration error);
- ``nonlinearity_mm``: the gradients' non-linearity, a smooth displacement
  growing with the cube of the distance from the isocentre, this many mm at
  100 mm (a few mm is typical at the edge of a clinical field of view);
- ``shading``: a receive coil's smooth gain across the field, peak to peak;
- ``anatomy``: this many tissue-like bright regions (smooth ellipses 5-30 mm
  wide, at 30-100 % of the fluid's signal), placed anywhere in the image;
- ``isocentre_mm`` (3,): the scanner point about which the scale and the
  non-linearity grow (the scanner's origin unless the image has no placement).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from chic_register.model.slices import Slice

#: The distance from the isocentre (mm) at which ``nonlinearity_mm`` is the displacement.
NONLINEARITY_RADIUS_MM = 100.0


@dataclass(frozen=True)
class ScannerEffects:
    """The effects of :mod:`chic_register.imaging.scanner`, all off by default."""

    scale: tuple[float, float] = (0.0, 0.0)
    nonlinearity_mm: float = 0.0
    shading: float = 0.0
    anatomy: int = 0
    isocentre_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def displacement_mm(self, points: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(N, 3): where a scanner point (N, 3) is shown, less where it is (in-plane axes ``u``, ``v``: the image's
        columns and rows, whose scale this is)."""
        p = np.asarray(points, float) - np.asarray(self.isocentre_mm, float)
        d = (self.scale[0] * (p @ u))[:, None] * u + (self.scale[1] * (p @ v))[:, None] * v
        if self.nonlinearity_mm:
            r2 = np.sum(p * p, axis=1, keepdims=True) / NONLINEARITY_RADIUS_MM**2
            d = d + self.nonlinearity_mm * (p / NONLINEARITY_RADIUS_MM) * r2
        return d


def apply_scanner_effects(sl: Slice, effects: ScannerEffects, rng=None, signal: float = 1.0,
                          no_tissue=None) -> np.ndarray:
    """The pixels (rows, cols) of ``sl`` as a scanner with ``effects`` shows them: each pixel shows what lies where
    the displacement puts it (first order: the world point ``q - d(q)`` of the pixel's point ``q``), shaded, with
    tissue added at ``signal`` (the fluid's level) except where ``no_tissue`` (rows, cols) bool is set: the
    fiducial's own body (:func:`body_footprint`), where there is plastic, fluid or the tool and no tissue."""
    from scipy import ndimage  # deferred: loads scipy only for a simulation with scanner effects

    rng = np.random.default_rng(rng)
    img = np.asarray(sl.pixels, float)
    rows, cols = img.shape
    rs, cs = sl.pixel_spacing_mm
    u, v = np.asarray(sl.col_dir, float), np.asarray(sl.row_dir, float)
    rr, cc = np.mgrid[0:rows, 0:cols]
    q = np.asarray(sl.origin_mm, float) + (cc.ravel() * cs)[:, None] * u + (rr.ravel() * rs)[:, None] * v
    p = q - effects.displacement_mm(q, u, v)
    rel = p - np.asarray(sl.origin_mm, float)
    out = ndimage.map_coordinates(img, [(rel @ v / rs).reshape(rows, cols), (rel @ u / cs).reshape(rows, cols)],
                                  order=1, mode="nearest")
    if effects.anatomy:
        tissue = _tissue(rows, cols, (rs, cs), effects.anatomy, signal, rng)
        if no_tissue is not None:
            tissue = np.where(no_tissue, 0.0, tissue)
        out = out + tissue
    if effects.shading:
        yy, xx = np.mgrid[-1:1:complex(0, rows), -1:1:complex(0, cols)]
        a, b = rng.uniform(-1, 1, 2)
        gain = 1.0 + 0.5 * effects.shading * (a * xx + b * yy) / max(abs(a) + abs(b), 1e-9)
        out = out * gain
    return out


def _tissue(rows: int, cols: int, spacing, n: int, signal: float, rng) -> np.ndarray:
    """``n`` smooth bright ellipses 5-30 mm across at 30-100 % of ``signal``."""
    from scipy import ndimage  # deferred: as in apply_scanner_effects

    rs, cs = spacing
    yy, xx = np.mgrid[0:rows, 0:cols]
    out = np.zeros((rows, cols))
    for _ in range(int(n)):
        r0, c0 = rng.uniform(0, rows), rng.uniform(0, cols)
        a, b = rng.uniform(2.5, 15.0, 2)  # semi-axes, mm
        th = rng.uniform(0, np.pi)
        dy, dx = (yy - r0) * rs, (xx - c0) * cs
        x1, y1 = dx * np.cos(th) + dy * np.sin(th), -dx * np.sin(th) + dy * np.cos(th)
        out = np.maximum(out, rng.uniform(0.3, 1.0) * signal * ((x1 / a) ** 2 + (y1 / b) ** 2 <= 1.0))
    return ndimage.gaussian_filter(out, 1.5)


#: The room (mm) kept between tissue and the fiducial's outer surface: the body as the distorted image shows it.
BODY_MARGIN_MM = 0.5


def body_footprint(sl: Slice, T_scanner_from_fiducial: np.ndarray, outer_radius_mm: float,
                   length_mm: float) -> np.ndarray:
    """(rows, cols) bool: the pixels of ``sl`` inside the fiducial's body (within ``outer_radius_mm`` of its axis,
    z 0..``length_mm`` in F, both grown by :data:`BODY_MARGIN_MM`) at ``T_scanner_from_fiducial``."""
    rows, cols = np.asarray(sl.pixels).shape
    rr, cc = np.mgrid[0:rows, 0:cols]
    q = sl.pixel_to_scanner(rr.ravel(), cc.ravel())
    T = np.asarray(T_scanner_from_fiducial, float)
    f = (q - T[:3, 3]) @ T[:3, :3]  # F coordinates of each pixel's point
    m = BODY_MARGIN_MM
    inside = (np.hypot(f[:, 0], f[:, 1]) <= outer_radius_mm + m) & (f[:, 2] >= -m) & (f[:, 2] <= length_mm + m)
    return inside.reshape(rows, cols)


def image_centre_mm(sl: Slice) -> np.ndarray:
    """(3,): the scanner point at the centre of ``sl``'s pixels, where a field of view sets the isocentre."""
    rows, cols = np.asarray(sl.pixels).shape
    return sl.pixel_to_scanner((rows - 1) / 2.0, (cols - 1) / 2.0)[0]
