"""Slices with a twin: a second, different pose of the fiducial that gives (nearly) the same image.

A slice of a fiducial shows one dot per tube, and all dots look alike. It is
ambiguous when the dots can be re-labelled and explained by another pose: the
pattern seen from the other side (a reflection), or turned (a rotation), at a
re-fitted depth, tilt and position. The CHIC check compares the re-labelled
pattern with the pattern at the same depth only; for a Z-frame that misses
twins that need a small tilt (a Z-frame whose diagonals are not symmetric still
has, near mid-height, a flipped twin tilted by about ``atan(2 s / (side / 2 - s))``
for a slice s mm from mid-height, off by only a second-order amount).

:func:`slice_twins` searches for them at tilt-0 slices: for each candidate
re-labelling (the rotations and reflections about the axis that map one dot onto
another, as :func:`~chic_design.feasibility.unambiguity.pattern_symmetries`), it starts from
the pose that re-labelling implies and fits the pose (rotation and position, six
numbers) so that each dot lies on the section of its new tube, by least squares
(:func:`scipy.optimize.least_squares`). A fit with RMS dot error within the
tolerance is a twin. Straight tubes only (the Z-frame family).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from chic_register.model.geometry import FiducialGeometry


@dataclass(frozen=True)
class Twin:
    """A twin pose at one depth: the re-labelling (``kind``, ``angle_deg``) and its RMS dot error (mm)."""

    depth_mm: float
    kind: str
    angle_deg: float
    rms_mm: float
    tilt_deg: float


def _candidates(xy: np.ndarray):
    """(kind, angle_deg, 3x3 rotation about the axis) mapping dot 0 onto each other dot."""
    th = np.arctan2(xy[:, 1], xy[:, 0])
    out = []
    for j in range(1, len(xy)):
        a = th[j] - th[0]
        out.append(("rotation", math.degrees(a) % 360.0, Rotation.from_euler("z", a).as_matrix()))
    for j in range(len(xy)):
        phi = 0.5 * (th[0] + th[j])  # the half turn about the horizontal line at phi: a reflection in the plane
        axis = np.array([math.cos(phi), math.sin(phi), 0.0])
        out.append(("reflection", math.degrees(phi) % 180.0, Rotation.from_rotvec(math.pi * axis).as_matrix()))
    return out


def _fit(lines_p0: np.ndarray, lines_d: np.ndarray, xy: np.ndarray, R0: np.ndarray, z_mm: float):
    """Least-squares pose (rotation about R0, origin) putting dot i on line i; returns (RMS mm, tilt deg)."""
    obs = np.column_stack([xy, np.zeros(len(xy))])

    def residual(p):
        R = Rotation.from_rotvec(p[:3]).as_matrix() @ R0
        o = np.array([p[3], p[4], z_mm + p[5]])
        n = R[:, 2]
        denom = lines_d @ n
        denom = np.where(np.abs(denom) < 1e-9, 1e-9, denom)
        t = ((o - lines_p0) @ n) / denom
        cross = lines_p0 + t[:, None] * lines_d
        return ((cross - o) @ R - obs)[:, :2].ravel()

    fit = least_squares(residual, np.zeros(6), method="lm", xtol=1e-10, ftol=1e-10)
    rms = float(np.sqrt(np.mean(fit.fun.reshape(-1, 2) ** 2) * 2))
    n = (Rotation.from_rotvec(fit.x[:3]).as_matrix() @ R0)[:, 2]
    return rms, math.degrees(math.acos(min(1.0, abs(float(n[2])))))


def slice_twins(geom: FiducialGeometry, depths_mm, tolerance_mm: float, prefilter_mm: float = 8.0) -> list[Twin]:
    """The best twin (if its RMS dot error is <= ``tolerance_mm``) of the tilt-0 slice at each depth.

    Candidates whose re-labelled dots are more than ``prefilter_mm`` (Hausdorff)
    from the dots at the same depth are not fitted: a twin needs a small change
    of pose. Tubes must all be straight and cross each plane once.
    """
    if any(t.curved for t in geom.tubes):
        raise ValueError("slice_twins handles straight tubes only")
    p0 = np.array([t.p0 for t in geom.tubes])
    d = np.array([t.direction for t in geom.tubes])
    out = []
    for z in np.atleast_1d(np.asarray(depths_mm, dtype=float)):
        xy = np.stack([t.point_at_z(z)[0, :2] for t in geom.tubes])
        best = None
        for kind, angle, R0 in _candidates(xy):
            mapped = xy @ R0[:2, :2].T
            dist = np.linalg.norm(mapped[:, None] - xy[None], axis=-1)
            perm = np.argmin(dist, axis=1)
            if len(set(perm.tolist())) != len(perm) or np.all(perm == np.arange(len(perm))):
                continue
            if dist[np.arange(len(perm)), perm].max() > prefilter_mm:
                continue
            # dot i is explained by tube perm[i]: R0 maps the dots' plane onto the re-labelled tubes' crossings
            rms, tilt = _fit(p0[perm], d[perm], xy, R0, float(z))
            if best is None or rms < best.rms_mm:
                best = Twin(float(z), kind, angle, rms, tilt)
        if best is not None and best.rms_mm <= tolerance_mm:
            out.append(best)
    return out
