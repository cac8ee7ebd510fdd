"""Channel arithmetic without a CAD kernel: extended centrelines, openings, fill ports and fluid volumes.

Every channel is made from a tube object of :mod:`chic_register.model.geometry`;
these helpers answer questions about those objects that the CAD model, the
report and the output checks share.
"""

from __future__ import annotations

import numpy as np

from chic_register.model.geometry import FiducialGeometry
from chic_register.model.tubes import Tube


def extended_tube(tube: Tube, ext_mm: float) -> Tube:
    """The same centreline continued by ``ext_mm`` (arc length) past both ends: ``tube.extended``.

    Sweeping the extended tube and cutting it with the body gives channels
    whose openings are exactly the tube's sections by the end-face planes.
    """
    return tube.extended(ext_mm)


def channel_openings_xy(geometry: FiducialGeometry, z_mm: float) -> dict[str, np.ndarray]:
    """Centre ``(x, y)`` (mm, shape (2,)) of every channel's opening in the end face at ``z_mm``.

    A helix's opening at the top is at angle ``theta0 + pitch * length``.
    """
    return {t.id: t.point_at_z(z_mm)[0, :2] for t in geometry.tubes}


def distinct_points(points, tol_mm: float = 1e-6) -> list[np.ndarray]:
    """``points`` with (near) duplicates dropped, first occurrence kept."""
    out: list[np.ndarray] = []
    for p in points:
        if all(np.linalg.norm(p - q) > tol_mm for q in out):
            out.append(np.asarray(p))
    return out


def fill_ports_xy(geometry: FiducialGeometry) -> list[np.ndarray]:
    """Centres (x, y) of the top cap's fill ports: one over each distinct channel opening in the top face.

    Channels that end at the same point (a Z-frame diagonal at its corner rod) share a port.
    """
    return distinct_points(channel_openings_xy(geometry, geometry.body.length).values())


def channel_volume_mm3(tube: Tube, z_lo_mm: float, z_hi_mm: float) -> float:
    """Fluid volume of one channel between two heights (mm^3): pi a^2 times the centreline length.

    Exact for a straight channel cut by parallel planes (Cavalieri), and for a
    helix to within its curvature (radius of curvature >> channel radius):
    ``tube.fluid_volume_mm3``. Overlaps with other channels are not subtracted
    (see :func:`blank_volume_mm3`).
    """
    return tube.fluid_volume_mm3(z_lo_mm, z_hi_mm)


def blank_volume_mm3(geometry: FiducialGeometry) -> float:
    """Volume of the body before the channels are cut (mm^3): an annulus, or a square frame."""
    b = geometry.body
    return (b.outline_area_mm2 - b.bore_area_mm2) * b.length
