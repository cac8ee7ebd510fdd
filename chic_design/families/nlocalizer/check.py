"""Unambiguity of an N-localizer (``family: nlocalizer``) for ``chic-design check``.

As for the Z-frame (:mod:`chic_design.families.zframe.check`), symmetries are
warnings, not violations: commercial N-localizers are symmetric by design and
their registration uses the frame's known orientation on the patient.

- ``symmetric_frame``: rotations that map the whole rod set onto itself
  (:func:`chic_register.model.symmetry.frame_symmetries`, the solver's own
  test). The Leksell box is symmetric under a half turn about x (its two
  diagonals map onto each other): an image fixes the pose only up to that turn,
  so the solver needs a prior (``--prior LPS``: F's axes along the scanner's,
  as the Leksell presets' F is for a head-first supine patient);
- ``ambiguous_slices``: otherwise, depth ranges where a tilt-0 slice of the rods
  that show as dots has a twin pose
  (:func:`chic_design.families.zframe.twins.slice_twins`).

- ``one_plate_direction``: when every N-plate faces along one axis (the
  Leksell box's two lateral plates), a slice's dots fix the rotation about
  that axis only to second order: tilting the plane about it moves every dot
  of a plate along the plate's own line, where only the rods' spacing
  (``width / cos``) and the sections' shapes tell the tilt, and not its sign.
  A single axial slice is then too imprecise to trust and a tilted one has a
  mirrored twin; several parallel slices (a volume) fix the pose, as does a
  plate facing another way.

Edge rods (role ``other``) lie in axial planes: they are part of the 3-D
symmetry test but not of the slice tests.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from chic_design.families.zframe.check import ambiguous_slice_findings, slice_twin_bands
from chic_design.feasibility.records import Finding, Symmetry, Unambiguity
from chic_register.model.symmetry import frame_symmetries

#: Roles of the rods an axial or tilted slice shows as dots.
DOT_ROLES = ("axial", "diagonal")


def dot_tubes(geom):
    """The rods that cross axial and tilted slices as dots (vertical rods and diagonals)."""
    return tuple(t for t in geom.tubes if t.role in DOT_ROLES)


def common_plate_normal(geom) -> np.ndarray | None:
    """The one direction (3,, unit, in the xy plane) that every plate of vertical rods faces, or None.

    A plate is the plane of a diagonal and the vertical rods at its ends; its
    normal is horizontal. None when the plates face two or more ways.
    """
    normals = []
    for t in geom.tubes:
        if t.role != "diagonal":
            continue
        d = np.asarray(t.p1, float) - np.asarray(t.p0, float)
        n = np.cross(d, [0.0, 0.0, 1.0])
        if np.linalg.norm(n) < 1e-9:
            continue
        normals.append(n / np.linalg.norm(n))
    if not normals:
        return None
    ref = normals[0]
    if all(abs(float(np.dot(ref, n))) > 1 - 1e-6 for n in normals):
        return ref if ref[int(np.argmax(np.abs(ref)))] > 0 else -ref
    return None


def nlocalizer_unambiguity(geom, usable_ranges_mm, slice_mismatch_mm: float | None, helix_crossings,
                           tolerance_mm: float) -> tuple[Unambiguity, list[Finding]]:
    """The N-localizer's :class:`Unambiguity` (3-D symmetries, slices with a twin) and the warnings it raises."""
    frame_syms, frame_mismatch = frame_symmetries(geom, tolerance_mm)
    warnings = []
    for fs in frame_syms:
        warnings.append(Finding(
            "symmetric_frame",
            f"a {fs.what} maps the rods onto themselves (worst rod off by {fs.mismatch_mm:.2g} mm; tolerance "
            f"{tolerance_mm:.2f} mm): every slice fits two poses and an image fixes the pose only up to this "
            "rotation, so registration needs a prior on the frame's orientation (chic-register solve --prior "
            "LPS for a head-first supine patient with F's axes along the scanner's); two equal plates are "
            "always symmetric, a third plate can break it", "whole frame"))
    axis = common_plate_normal(geom)
    if axis is not None:
        name = {0: "x", 1: "y"}.get(int(np.argmax(np.abs(axis))), "") if np.max(np.abs(axis)) > 0.999 else ""
        about = f"F's {name} axis" if name else "the axis (" + ", ".join(f"{v:.2f}" for v in axis) + ")"
        warnings.append(Finding(
            "one_plate_direction",
            f"every N-plate faces along {about}: a slice's dots fix the rotation about it only to second order "
            "(tilting the plane about it slides each plate's dots along the plate's own line; only the rods' "
            "spacing tells the tilt, and not its sign), so one axial slice is refused as imprecise and a tilted "
            "one has a mirrored twin; register several parallel slices (a volume), or add a plate facing "
            "another way", "every slice"))
    bands: tuple[Symmetry, ...] = ()
    if not frame_syms:
        bands = slice_twin_bands(replace(geom, tubes=dot_tubes(geom)), usable_ranges_mm, tolerance_mm)
    warnings += ambiguous_slice_findings(bands, tolerance_mm)
    unamb = Unambiguity(tolerance_mm, slice_mismatch_mm, bands, tuple(helix_crossings),
                        frame_symmetries=frame_syms, frame_min_mismatch_mm=frame_mismatch)
    return unamb, warnings
