"""Unambiguity of a Z-frame (``family: zframe``) for ``chic-design check``.

The CHIC rule (a tilt-0 marker pattern that maps onto itself at some depth is a
violation) does not fit the Z-frame: the standard ``z001`` frame is symmetric as
a whole, by design, and real Z-frame registration resolves that with a prior on
the frame's orientation. So for a Z-frame the check reports, as warnings, not
violations:

- ``symmetric_frame``: rotations that map the whole rod set onto itself
  (:mod:`chic_design.frame_symmetry`); an image alone then fixes the pose only up
  to that rotation, and ``unambiguity.unambiguous`` is false;
- ``ambiguous_slices``: depth ranges where the tilt-0 slice pattern has a
  rotation or reflection symmetry of its own (the CHIC check's
  :func:`~chic_design.feasibility.pattern_symmetries`), i.e. single slices that
  fit two poses even if the frame as a whole is not symmetric.

Reversing one x-face diagonal (``diagonals.reversed_faces: ["-x"]``) removes
the whole-frame symmetry of z001.
"""

from __future__ import annotations

from .feasibility import Finding, Symmetry, Unambiguity
from .frame_symmetry import frame_symmetries


def zframe_unambiguity(geom, slice_symmetries: tuple[Symmetry, ...], slice_mismatch_mm: float | None,
                       helix_crossings, tolerance_mm: float) -> tuple[Unambiguity, list[Finding]]:
    """The Z-frame's :class:`Unambiguity` (with its 3-D symmetries) and the warnings it raises."""
    frame_syms, frame_mismatch = frame_symmetries(geom, tolerance_mm)
    warnings = []
    for fs in frame_syms:
        warnings.append(Finding(
            "symmetric_frame",
            f"a {fs.what} maps the rods onto themselves (worst rod off by {fs.mismatch_mm:.2g} mm; tolerance "
            f"{tolerance_mm:.2f} mm): an image fixes the pose only up to this rotation, so registration needs "
            "the frame's approximate orientation (as Z-frame registration usually assumes); "
            "diagonals.reversed_faces can break the symmetry", "whole frame"))
    for sym in slice_symmetries:
        a, b = sym.depth_range_mm
        warnings.append(Finding(
            "ambiguous_slices",
            f"the tilt-0 slice pattern maps onto itself under a {sym.describe()} (worst rod off by "
            f"{sym.mismatch_mm:.2f} mm at z = {sym.at_depth_mm:.2f} mm; tolerance {tolerance_mm:.2f} mm): "
            "a single slice there fits two poses", f"z {a:.2f}-{b:.2f} mm"))
    unamb = Unambiguity(tolerance_mm, slice_mismatch_mm, tuple(slice_symmetries), tuple(helix_crossings),
                        frame_symmetries=frame_syms, frame_min_mismatch_mm=frame_mismatch)
    return unamb, warnings
