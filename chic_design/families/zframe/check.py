"""Unambiguity of a Z-frame (``family: zframe``) for ``chic-design check``.

The CHIC rule (a tilt-0 marker pattern that maps onto itself at some depth is a
violation) does not fit the Z-frame: the standard ``z001`` frame is symmetric as
a whole, by design, and real Z-frame registration resolves that with a prior on
the frame's orientation. So for a Z-frame the check reports, as warnings, not
violations:

- ``symmetric_frame``: rotations that map the whole rod set onto itself
  (:func:`chic_register.model.symmetry.frame_symmetries`, the solver's own
  test); an image alone then fixes the pose only up to that rotation (every
  slice has a twin), and ``unambiguity.unambiguous`` is false;
- ``ambiguous_slices``: otherwise, depth ranges where a tilt-0 slice has a twin
  pose, found by :func:`chic_design.families.zframe.twins.slice_twins` (a
  re-labelling of the dots explained by a re-fitted pose within the symmetry
  tolerance; a local search from each rotation/reflection about the axis).
  Such slices fit two poses.

Reversing one x-face diagonal (``diagonals.reversed_faces: ["-x"]``) removes
the whole-frame symmetry of z001; slices near mid-height keep a flipped twin.
"""

from __future__ import annotations

import numpy as np

from chic_design.families.zframe.twins import slice_twins
from chic_design.feasibility.records import Finding, Symmetry, Unambiguity
from chic_register.model.symmetry import frame_symmetries

#: Depth step (mm) of the twin search over the depths usable at tilt 0.
TWIN_STEP_MM = 0.5


def twin_bands(twins, step_mm: float) -> tuple[Symmetry, ...]:
    """Runs of consecutive depths with a twin, as :class:`Symmetry` (best twin of each run)."""
    out, run = [], []
    for tw in twins + [None]:
        if tw is not None and (not run or tw.depth_mm - run[-1].depth_mm <= step_mm + 1e-9):
            run.append(tw)
            continue
        if run:
            best = min(run, key=lambda t: t.rms_mm)
            out.append(Symmetry(best.kind, best.angle_deg, (run[0].depth_mm, run[-1].depth_mm), best.depth_mm,
                                best.rms_mm))
        run = [tw] if tw is not None else []
    return tuple(out)


def slice_twin_bands(geom, usable_ranges_mm, tolerance_mm: float) -> tuple[Symmetry, ...]:
    """The depth bands, over the depths usable at tilt 0 (:data:`TWIN_STEP_MM` apart), where a slice of ``geom``'s
    straight tubes has a twin (:func:`~chic_design.families.zframe.twins.slice_twins`)."""
    depths = np.concatenate([np.arange(a, b + 1e-9, TWIN_STEP_MM) for a, b in usable_ranges_mm] or [np.empty(0)])
    return twin_bands(slice_twins(geom, depths, tolerance_mm), TWIN_STEP_MM)


def ambiguous_slice_findings(bands, tolerance_mm: float) -> list[Finding]:
    """One ``ambiguous_slices`` warning per twin band."""
    out = []
    for sym in bands:
        a, b = sym.depth_range_mm
        out.append(Finding(
            "ambiguous_slices",
            f"tilt-0 slices at z {a:.1f}-{b:.1f} mm have a twin pose: the dots re-labelled by a {sym.describe()} "
            f"fit a re-fitted pose within {tolerance_mm:.2f} mm (best {sym.mismatch_mm:.3f} mm RMS at z = "
            f"{sym.at_depth_mm:.1f} mm): a single slice there fits two poses; image other depths or several "
            "slices, or give the solver the frame's approximate orientation", f"z {a:.1f}-{b:.1f} mm"))
    return out


def zframe_unambiguity(geom, usable_ranges_mm, slice_mismatch_mm: float | None, helix_crossings,
                       tolerance_mm: float) -> tuple[Unambiguity, list[Finding]]:
    """The Z-frame's :class:`Unambiguity` (3-D symmetries, slices with a twin) and the warnings it raises."""
    frame_syms, frame_mismatch = frame_symmetries(geom, tolerance_mm)
    warnings = []
    for fs in frame_syms:
        warnings.append(Finding(
            "symmetric_frame",
            f"a {fs.what} maps the rods onto themselves (worst rod off by {fs.mismatch_mm:.2g} mm; tolerance "
            f"{tolerance_mm:.2f} mm): every slice fits two poses, an image fixes the pose only up to this "
            "rotation, so registration needs the frame's approximate orientation (as Z-frame registration "
            "usually assumes); diagonals.reversed_faces can break the symmetry", "whole frame"))
    bands: tuple[Symmetry, ...] = ()
    if not frame_syms:
        bands = slice_twin_bands(geom, usable_ranges_mm, tolerance_mm)
    warnings += ambiguous_slice_findings(bands, tolerance_mm)
    unamb = Unambiguity(tolerance_mm, slice_mismatch_mm, bands, tuple(helix_crossings),
                        frame_symmetries=frame_syms, frame_min_mismatch_mm=frame_mismatch)
    return unamb, warnings
