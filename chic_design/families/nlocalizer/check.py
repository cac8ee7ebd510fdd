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

Edge rods (role ``other``) lie in axial planes: they are part of the 3-D
symmetry test but not of the slice tests.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from chic_design.families.zframe.check import TWIN_STEP_MM, twin_bands
from chic_design.families.zframe.twins import slice_twins
from chic_design.feasibility.records import Finding, Symmetry, Unambiguity
from chic_register.model.symmetry import frame_symmetries

#: Roles of the rods an axial or tilted slice shows as dots.
DOT_ROLES = ("axial", "diagonal")


def dot_tubes(geom):
    """The rods that cross axial and tilted slices as dots (vertical rods and diagonals)."""
    return tuple(t for t in geom.tubes if t.role in DOT_ROLES)


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
    bands: tuple[Symmetry, ...] = ()
    if not frame_syms:
        dots = replace(geom, tubes=dot_tubes(geom))
        depths = np.concatenate([np.arange(a, b + 1e-9, TWIN_STEP_MM) for a, b in usable_ranges_mm] or [np.empty(0)])
        bands = twin_bands(slice_twins(dots, depths, tolerance_mm), TWIN_STEP_MM)
    for sym in bands:
        a, b = sym.depth_range_mm
        warnings.append(Finding(
            "ambiguous_slices",
            f"tilt-0 slices at z {a:.1f}-{b:.1f} mm have a twin pose: the dots re-labelled by a {sym.describe()} "
            f"fit a re-fitted pose within {tolerance_mm:.2f} mm (best {sym.mismatch_mm:.3f} mm RMS at z = "
            f"{sym.at_depth_mm:.1f} mm): a single slice there fits two poses; image other depths or several "
            "slices, or give the solver the frame's approximate orientation", f"z {a:.1f}-{b:.1f} mm"))
    unamb = Unambiguity(tolerance_mm, slice_mismatch_mm, bands, tuple(helix_crossings),
                        frame_symmetries=frame_syms, frame_min_mismatch_mm=frame_mismatch)
    return unamb, warnings
