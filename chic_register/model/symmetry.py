"""Symmetries of a fiducial in 3-D: rigid motions that map its tube set onto itself.

If a proper rotation R (about an axis through the body's centre) maps every tube
centreline onto a tube centreline, then a fiducial at pose T and at pose T R give
the same image in every slice: the image alone cannot tell them apart, and a
solver needs a prior (an approximate orientation) to choose. This is the case of
the standard Z-frame ``z001``: a half turn about the y axis through the frame's
centre maps it onto itself (the +x and -x diagonals swap, the +y diagonal maps
onto itself reversed, the axial rods swap in pairs).

Candidates are the proper rotations of a square prism about its centre
``(0, 0, length / 2)``: quarter turns about z and half turns about the horizontal
axes at 0, 45, 90 and 135 deg. A rigid motion keeps arc length, so a tube i maps
onto tube j exactly when its points at arc-length parameters t match j's at t or
1 - t; the mismatch is the largest such point distance (mm).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from chic_register.model.geometry import FiducialGeometry
from chic_register.model.tube_model import GeometryKey

_N_SAMPLES = 65
_COARSE_SAMPLES = 9  # every 8th of the 65: the solver's up-front test, before the full one (when it may pass)


@dataclass(frozen=True)
class FrameSymmetry:
    """A rotation of the fiducial onto itself: ``what`` it is, worst tube ``mismatch_mm``, tube mapping."""

    what: str
    mismatch_mm: float
    mapping: tuple[tuple[str, str], ...]

    def to_dict(self) -> dict:
        return {"what": self.what, "mismatch_mm": round(float(self.mismatch_mm), 4),
                "maps": {a: b for a, b in self.mapping}}


def _turn(axis: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotation by ``angle_rad`` about the unit ``axis`` (Rodrigues; numpy only: a one-slice solve imports no scipy)."""
    K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + math.sin(angle_rad) * K + (1.0 - math.cos(angle_rad)) * (K @ K)


def candidate_rotations(length_mm: float) -> list[tuple[str, np.ndarray]]:
    """(description, 3x3 rotation) of every non-identity proper symmetry of a square prism."""
    out = [(f"rotation by {a} deg about the z axis", _turn(np.array([0.0, 0.0, 1.0]), math.radians(a)))
           for a in (90, 180, 270)]
    for a in (0, 45, 90, 135):
        axis = np.array([math.cos(math.radians(a)), math.sin(math.radians(a)), 0.0])
        name = {0: "x", 90: "y"}.get(a, f"horizontal {a} deg")
        out.append((f"half turn about the {name} axis through (0, 0, {length_mm / 2:g}) mm "
                    "(the frame upside down)", _turn(axis, math.pi)))
    return out


def _tube_samples(geom: FiducialGeometry, n_samples: int = _N_SAMPLES) -> np.ndarray:
    """Points of every tube at equal arc-length steps; shape (T, n_samples, 3)."""
    t = np.linspace(0.0, 1.0, n_samples)
    return np.stack([tube.points(t) for tube in geom.tubes])


def rotation_mismatch(geom: FiducialGeometry, R: np.ndarray) -> tuple[float, tuple[int, ...]]:
    """Mismatch (mm) of the tube set rotated by R about the body centre, and the mapping.

    The mismatch is the Hausdorff distance between the rotated and the original
    tube sets, each tube a whole curve (0 for an exact symmetry); the mapping
    sends tube i to the tube nearest its image.
    """
    return mismatches(geom, np.asarray(R, dtype=float)[None])[0]


def mismatches(geom: FiducialGeometry, Rs: np.ndarray, n_samples: int = _N_SAMPLES) -> list[tuple[float, tuple[int, ...]]]:
    """:func:`rotation_mismatch` of every rotation of ``Rs`` (shape (K, 3, 3)) at once. With fewer ``n_samples``
    (``n_samples - 1`` dividing ``_N_SAMPLES - 1``: a subset of the same points) each mismatch is a lower bound."""
    c = np.array([0.0, 0.0, geom.body.length / 2])
    P = _tube_samples(geom, n_samples)  # (T, N, 3)
    Q = np.einsum("tnj,kij->ktni", P - c, Rs) + c  # (K, T, N, 3): every tube turned by every rotation
    fwd = np.linalg.norm(Q[:, :, None] - P[None, None], axis=-1).max(axis=-1)  # (K, T, T)
    rev = np.linalg.norm(Q[:, :, None] - P[None, None, :, ::-1], axis=-1).max(axis=-1)
    diam = np.array([t.diameter for t in geom.tubes])
    d = np.where(diam[:, None] == diam[None, :], np.minimum(fwd, rev), np.inf)
    return [(float(max(dk.min(axis=1).max(), dk.min(axis=0).max())), tuple(int(j) for j in np.argmin(dk, axis=1)))
            for dk in d]


#: A rotation mapping every tube within this share of the thinnest tube's diameter onto another is a symmetry no
#: image can break (the printed channel's own shape tolerance;
#: ``chic_design.feasibility.unambiguity.symmetry_tolerance``'s floor): the solver then asks for a prior before it
#: reads a pixel.
EXACT_SHARE = 0.05


def _candidates(geom: FiducialGeometry) -> tuple[tuple[str, float, tuple[int, ...]], ...]:
    """``(what, mismatch mm, mapping)`` of every candidate rotation of ``geom``."""
    named = candidate_rotations(geom.body.length)
    found = mismatches(geom, np.stack([R for _, R in named]))
    return tuple((what, mism, mapping) for (what, _), (mism, mapping) in zip(named, found))


@functools.lru_cache(maxsize=8)
def _memo_candidates(key) -> tuple[tuple[str, float, tuple[int, ...]], ...]:
    """:func:`_candidates` once per distinct geometry (the solver asks on every call without a prior)."""
    return _candidates(key.geom)


def frame_symmetries(geom: FiducialGeometry, tolerance_mm: float) -> tuple[tuple[FrameSymmetry, ...], float | None]:
    """Symmetries within ``tolerance_mm``, and the smallest mismatch of any candidate (None if none maps)."""
    try:
        candidates = _memo_candidates(GeometryKey(geom))
    except TypeError:  # an unhashable value somewhere: no memo
        candidates = _candidates(geom)
    found, best = [], None
    for what, mism, mapping in candidates:
        best = mism if best is None else min(best, mism)
        if mism <= tolerance_mm:
            ids = geom.ids
            found.append(FrameSymmetry(what, mism, tuple((ids[i], ids[k]) for i, k in enumerate(mapping))))
    return tuple(found), best


def prior_needed(geom: FiducialGeometry, tolerance_mm: float) -> str | None:
    """Why no image alone can register ``geom`` (a rotation maps its tubes onto themselves within
    ``tolerance_mm``), with what to give instead; None when it has no such symmetry.

    The solver says this before it reads a pixel when no prior is given: the
    twin pose explains every slice exactly as well, so a search could only
    end in an ambiguous fit (or, worse, a coin toss). Memoised per distinct
    geometry and tolerance (the solver asks on every call without a prior).
    """
    try:
        return _memo_prior_needed(GeometryKey(geom), float(tolerance_mm))
    except TypeError:  # an unhashable value somewhere: no memo
        return prior_needed_unmemoised(geom, tolerance_mm)


@functools.lru_cache(maxsize=16)
def _memo_prior_needed(key, tolerance_mm: float) -> str | None:
    return prior_needed_unmemoised(key.geom, tolerance_mm)


def prior_needed_unmemoised(geom: FiducialGeometry, tolerance_mm: float) -> str | None:
    """:func:`prior_needed` without the memo."""
    named = candidate_rotations(geom.body.length)
    coarse = mismatches(geom, np.stack([R for _, R in named]), _COARSE_SAMPLES)
    if min(m for m, _ in coarse) > tolerance_mm:  # a lower bound of every mismatch: no symmetry (the common case)
        return None
    found, _ = frame_symmetries(geom, tolerance_mm)
    if not found:
        return None
    what = found[0].what + (f" (and {len(found) - 1} more)" if len(found) > 1 else "")
    return (f"ambiguous fit: '{geom.name}' maps onto itself under a {what}, so every image fits two poses and "
            "only the frame's approximate orientation can pick one; give it with --prior: the scanner directions "
            "the frame's x, y, z point along (within --prior-max-deg, default 60 deg), e.g. '--prior RAS' (x to "
            "the patient's right, y anterior, z superior) or '--prior LPS' (also '--prior identity'), else "
            "'--prior FILE', a JSON file holding {\"T_scanner_from_fiducial\": 4x4 matrix} (only its rotation is "
            "used) or a 3D Slicer .tfm")
