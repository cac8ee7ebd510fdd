"""Unambiguity: symmetries of the tilt-0 marker pattern and helices that leave their quadrant.

Item 5 of :mod:`chic_design.feasibility.engine`. All blobs look alike, so a rotation
about the axis or a reflection that maps the markers onto themselves (within
:func:`symmetry_tolerance`) makes twist or depth ambiguous; a helix whose angle
crosses the angle of a straight tube no longer gives depth uniquely.
"""

from __future__ import annotations

import math

import numpy as np

from chic_design.feasibility.records import Finding, Symmetry
from chic_design.feasibility.runs import true_runs
from chic_register.model.centreline_crossings import plane_crossings
from chic_register.model.geometry import FiducialGeometry


def _wrap180(a):
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


def helix_quadrant_crossings(geom: FiducialGeometry, step_mm: float = 0.05) -> tuple[Finding, ...]:
    """Helices whose angle crosses the angle of a straight tube within their common z extent."""
    out = []
    for h in (t for t in geom.tubes if t.role == "helix"):
        for line in (t for t in geom.tubes if not t.curved):
            z0 = max(h.z_range[0], line.z_range[0])
            z1 = min(h.z_range[1], line.z_range[1])
            if z1 <= z0 or line.z_range[1] - line.z_range[0] < 1e-9:
                continue
            zs = np.linspace(z0, z1, max(3, int(math.ceil((z1 - z0) / step_mm)) + 1))
            ph, pl = h.point_at_z(zs), line.point_at_z(zs)
            delta = _wrap180(np.degrees(np.arctan2(ph[:, 1], ph[:, 0]) - np.arctan2(pl[:, 1], pl[:, 0])))
            pos = delta > 0
            cross = np.flatnonzero((pos[1:] != pos[:-1]) & (np.abs(delta[1:]) < 90) & (np.abs(delta[:-1]) < 90))
            # a helix that only touches the tube's angle at its own end stays in its quadrant
            cross = [c for c in cross if not (c == 0 and delta[0] == 0) and not (delta[c + 1] == 0 and c + 1 == len(zs) - 1)]
            if cross:
                c = cross[0]
                zc = zs[c] + (zs[c + 1] - zs[c]) * delta[c] / (delta[c] - delta[c + 1])
                out.append(Finding("helix_leaves_quadrant",
                                   f"helix {h.id} crosses the angle of straight tube {line.id} at z = {zc:.1f} mm: "
                                   "its angle no longer gives depth uniquely (reduce the pitch or the span)",
                                   f"{h.id}/{line.id} z={zc:.1f} mm"))
    return tuple(out)


def _section_markers(geom: FiducialGeometry, depths_mm: np.ndarray) -> np.ndarray:
    """Tilt-0 marker positions (x, y) of every tube at each depth; shape (Z, N, 2), NaN where absent."""
    n = np.tile([0.0, 0.0, 1.0], (len(depths_mm), 1))
    o = np.zeros_like(n)
    o[:, 2] = depths_mm
    return np.stack([plane_crossings(t, o, n)[1][:, :2] for t in geom.tubes], axis=1)


def _hausdorff(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric Hausdorff distance between point sets a (..., N, 2) and b (..., N, 2), and nearest index."""
    d = np.linalg.norm(a[..., :, None, :] - b[..., None, :, :], axis=-1)
    nearest = np.argmin(d, axis=-1)
    return np.maximum(d.min(axis=-1).max(axis=-1), d.min(axis=-2).max(axis=-1)), nearest


def pattern_symmetries(geom: FiducialGeometry, depths_mm, tolerance_mm: float):
    """Rotations about the axis / reflections mapping the tilt-0 marker set onto itself.

    Candidates map marker 0 onto each marker j: rotation by theta_j - theta_0,
    reflection about the line at (theta_0 + theta_j)/2. A candidate is a
    symmetry if its symmetric Hausdorff mismatch is <= ``tolerance_mm`` and it
    permutes the markers (not the identity). Returns ``(symmetries, min_mismatch)``:
    one Symmetry per depth run, and the smallest mismatch of any non-trivial candidate.
    """
    zs = np.asarray(depths_mm, dtype=float)
    if zs.size == 0:
        return (), None
    P = _section_markers(geom, zs)  # (Z, N, 2)
    Z, N, _ = P.shape
    th = np.arctan2(P[..., 1], P[..., 0])  # (Z, N)
    rot = th - th[:, :1]  # (Z, N): j = 0 is the identity
    refl = 0.5 * (th + th[:, :1])  # mirror-line angles
    ang = np.concatenate([rot[:, 1:], refl], axis=1)  # (Z, C)
    kind = np.array(["rotation"] * (N - 1) + ["reflection"] * N)
    c, s = np.cos(ang), np.sin(ang)
    x, y = P[..., 0][:, None, :], P[..., 1][:, None, :]  # (Z, 1, N)
    is_rot = (kind == "rotation")[None, :, None]
    c2, s2 = np.cos(2 * ang)[..., None], np.sin(2 * ang)[..., None]
    xr = np.where(is_rot, c[..., None] * x - s[..., None] * y, c2 * x + s2 * y)
    yr = np.where(is_rot, s[..., None] * x + c[..., None] * y, s2 * x - c2 * y)
    mapped = np.stack([xr, yr], axis=-1)  # (Z, C, N, 2)
    mism, nearest = _hausdorff(mapped, np.broadcast_to(P[:, None], mapped.shape))
    identity = (nearest == np.arange(N)).all(axis=-1)
    mism = np.where(identity | np.isnan(mism), np.inf, mism)
    best = np.argmin(mism, axis=1)
    best_m = mism[np.arange(Z), best]
    min_mismatch = float(best_m.min()) if np.isfinite(best_m).any() else None
    syms = []
    for a, b in true_runs(np.arange(Z), best_m <= tolerance_mm):
        a, b = int(a), int(b)
        zi = a + int(np.argmin(best_m[a:b + 1]))
        k = str(kind[best[zi]])
        angle = float(np.degrees(ang[zi, best[zi]]) % (360.0 if k == "rotation" else 180.0))
        syms.append(Symmetry(k, angle, (float(zs[a]), float(zs[b])), float(zs[zi]), float(best_m[zi])))
    return tuple(syms), min_mismatch


def symmetry_tolerance(geom: FiducialGeometry, pixel_size_mm: float) -> float:
    """Largest marker displacement an image cannot resolve: one pixel, at least 5 % of the tube diameter.

    One pixel is conservative against the centroid quantisation bound
    (pixel/sqrt(12)), allowing for noise, partial volume and tilt distortion;
    the 5 % floor stands for the printed channel's shape tolerance, which
    bounds how well a marker centre is known even with ideal imaging.
    """
    return max(pixel_size_mm, 0.05 * min(t.diameter for t in geom.tubes))
