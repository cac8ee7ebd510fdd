"""Which channels touch, and over which heights: the one answer the report and the feasibility use.

Two channels touch at height z when their sections by the plane z overlap; the
z-range of that overlap is the z-extent of the two solids' intersection (where
the fluid connects and the images merge). The section of a channel by a plane
z = const is the ellipse of the cylinder around its tangent line there: centre
``tube.point_at_z(z)``, semi-axis ``r`` across the tube and ``r / cos(tilt)``
along the tube's horizontal direction (exact for a straight channel; for a helix
to within its curvature). Overlap is tested exactly up to the boundary sampling
(:data:`BOUNDARY_POINTS` per ellipse, a sagitta of < 0.001 mm for these sizes):
a boundary point of one ellipse inside the other, or one centre inside the other.
Pairs whose bounding circles ``r / cos(tilt)`` stay apart are skipped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from chic_design.feasibility.runs import true_runs
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.tubes import Tube

BOUNDARY_POINTS = 256


@dataclass(frozen=True)
class Contact:
    """Channels ``a`` and ``b`` touch over the heights ``z_ranges_mm`` ((z0, z1), ...), sampled."""

    a: str
    b: str
    z_ranges_mm: tuple[tuple[float, float], ...]

    @property
    def z_lo(self) -> float:
        return self.z_ranges_mm[0][0]

    @property
    def z_hi(self) -> float:
        return self.z_ranges_mm[-1][1]


def z_sections(tube: Tube, z_mm: np.ndarray):
    """Ellipse of the channel's section by each plane z: centres (N, 2), unit major axes (N, 2), semi-axes (N,), r."""
    z = np.atleast_1d(np.asarray(z_mm, dtype=float))
    centre = tube.point_at_z(z)[:, :2]
    t = tube.tangents_at_z(z)
    r = tube.diameter / 2
    txy = np.hypot(t[:, 0], t[:, 1])
    u = np.where(txy[:, None] > 1e-12, t[:, :2] / np.maximum(txy, 1e-12)[:, None], [1.0, 0.0])
    return centre, u, r / np.abs(t[:, 2]), r


def _inside(p, centre, u, a, b) -> np.ndarray:
    """Whether points p (N, K, 2) lie in the ellipses (centre (N, 2), major axis u (N, 2), semi-axes a (N,), b)."""
    d = p - centre[:, None, :]
    along = np.einsum("nki,ni->nk", d, u)
    across = d[..., 0] * -u[:, None, 1] + d[..., 1] * u[:, None, 0]
    return (along / a[:, None]) ** 2 + (across / b) ** 2 <= 1.0


def _boundary(centre, u, a, b) -> np.ndarray:
    phi = np.linspace(0.0, 2 * np.pi, BOUNDARY_POINTS, endpoint=False)
    v = np.stack([-u[:, 1], u[:, 0]], axis=1)
    return (centre[:, None, :] + (a[:, None] * np.cos(phi))[..., None] * u[:, None, :]
            + (b * np.sin(phi))[None, :, None] * v[:, None, :])


def sections_overlap(tube_a: Tube, tube_b: Tube, z_mm) -> np.ndarray:
    """Whether the two channels' sections by the planes ``z_mm`` overlap; shape (N,) bool."""
    z = np.atleast_1d(np.asarray(z_mm, dtype=float))
    ca, ua, aa, ba = z_sections(tube_a, z)
    cb, ub, ab, bb = z_sections(tube_b, z)
    out = np.linalg.norm(ca - cb, axis=1) <= aa + ab  # bounding circles: a necessary condition
    k = np.flatnonzero(out)
    if k.size:
        ea, eb = (ca[k], ua[k], aa[k], ba), (cb[k], ub[k], ab[k], bb)
        hit = (_inside(_boundary(*ea), *eb).any(axis=1) | _inside(_boundary(*eb), *ea).any(axis=1)
               | _inside(ca[k][:, None], *eb)[:, 0] | _inside(cb[k][:, None], *ea)[:, 0])
        out[k] = hit
    return out


def channel_contacts(geometry: FiducialGeometry, step_mm: float = 0.05) -> tuple[Contact, ...]:
    """Every pair of channels that touches inside the body, with its z-ranges (``step_mm`` grid, ends included)."""
    length = geometry.body.length
    z = np.linspace(0.0, length, int(round(length / step_mm)) + 1)
    tubes = geometry.tubes
    out = []
    for i in range(len(tubes)):
        for j in range(i + 1, len(tubes)):
            lo = max(tubes[i].z_range[0], tubes[j].z_range[0], 0.0)
            hi = min(tubes[i].z_range[1], tubes[j].z_range[1], length)
            zz = z[(z >= lo) & (z <= hi)]
            if zz.size == 0:
                continue
            hit = sections_overlap(tubes[i], tubes[j], zz)
            if hit.any():
                out.append(Contact(tubes[i].id, tubes[j].id, true_runs(zz, hit)))
    return tuple(out)


def touching_channels(geometry: FiducialGeometry, step_mm: float = 0.05) -> list[tuple[str, str, float, float]]:
    """Pairs of channels that touch: ``[(id, id, z_lo, z_hi)]`` (mm, sampled), from :func:`channel_contacts`.

    Such channels are connected where they meet (they fill together) and
    their images merge there. The same answer as the feasibility report's.
    """
    return [(c.a, c.b, c.z_lo, c.z_hi) for c in channel_contacts(geometry, step_mm)]
