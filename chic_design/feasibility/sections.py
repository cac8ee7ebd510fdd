"""Heights where the body's channels are clear of each other: where a cross-section shows every channel apart.

The build's output checks cut ``body.stl`` at :func:`section_heights`; the
printability rules refuse a design without one (``no_clear_section``).
"""

from __future__ import annotations

import numpy as np

from chic_register.model.geometry import FiducialGeometry
from chic_register.model.tubes import Tube

#: Two channels' sections (and a channel and the walls) must be this far apart at a check height.
SECTION_MARGIN_MM = 0.3


def tube_slope_cos(tube: Tube, z_mm) -> np.ndarray:
    """cos of the angle between the tube's centreline and +z at heights ``z_mm``; shape (N,)."""
    return np.abs(tube.tangents_at_z(z_mm)[:, 2])


def _section_circles(geometry: FiducialGeometry, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centres (N, T, 2) and bounding radii a / cos(tilt) (N, T) of every channel's section."""
    centres = np.stack([t.point_at_z(z)[:, :2] for t in geometry.tubes], axis=1)
    half = np.stack([t.diameter / 2 / tube_slope_cos(t, z) for t in geometry.tubes], axis=1)
    return centres, half


def pair_gaps_mm(geometry: FiducialGeometry, z_mm) -> dict[tuple[str, str], np.ndarray]:
    """Gap between the section circles of every pair of channels at ``z_mm``: ``{(id, id): (N,)}``."""
    z = np.atleast_1d(np.asarray(z_mm, dtype=float))
    centres, half = _section_circles(geometry, z)
    ids = geometry.ids
    return {
        (ids[i], ids[j]): np.linalg.norm(centres[:, i] - centres[:, j], axis=1) - half[:, i] - half[:, j]
        for i in range(len(ids)) for j in range(i + 1, len(ids))
    }


def section_clearance_mm(geometry: FiducialGeometry, z_mm) -> np.ndarray:
    """Smallest gap between channel sections (and between a section and the walls) at ``z_mm``.

    Each channel's section by the plane z is bounded by a circle of radius
    ``a / cos(tilt)`` (the half major axis of its ellipse) around ``point_at_z``;
    the gap is measured between those circles. Shape (N,) for N heights.
    Negative: two channels touch there.
    """
    z = np.atleast_1d(np.asarray(z_mm, dtype=float))
    body = geometry.body
    centres, half = _section_circles(geometry, z)
    flat = centres.reshape(-1, 2)
    wall = np.minimum(body.outside_gap_mm(flat), body.bore_gap_mm(flat)).reshape(half.shape) - half
    gap = wall.min(axis=1)
    for d in pair_gaps_mm(geometry, z).values():
        gap = np.minimum(gap, d)
    return gap


def section_heights(geometry: FiducialGeometry, n: int = 5, margin_mm: float = SECTION_MARGIN_MM) -> np.ndarray:
    """``n`` heights (mm, increasing, shape (<= n,)) spread over the body where channels are apart.

    Candidates are a 0.25 mm grid strictly inside the body; those with
    :func:`section_clearance_mm` >= ``margin_mm`` are kept and ``n`` of them
    picked nearest to evenly spaced targets. Empty if the channels touch everywhere.
    """
    length = geometry.body.length
    z = np.linspace(0, length, max(int(round(length / 0.25)), 8) + 1)[1:-1]
    good = z[section_clearance_mm(geometry, z) >= margin_mm]
    if good.size == 0:
        return good
    targets = np.linspace(good[0], good[-1], n) if good.size > n else good
    picked = sorted({float(good[np.argmin(np.abs(good - t))]) for t in targets})
    return np.array(picked)
