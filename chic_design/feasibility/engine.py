"""Feasibility of a design of any family: where in the scanner it works, and whether it prints.

:func:`check_geometry` computes, from the geometry objects of a family's
:meth:`~chic_design.families.base.Family.geometry` (never from a re-derived layout):

1. **Tilt limits** at each depth z (1 mm steps or finer, both ends and mid-depth
   included): the largest tilt of an image plane through the axis point
   ``(0, 0, z)`` such that, for every azimuth (10 deg grid, then a 0.5 deg grid
   over +-10 deg around the worst one; twist is an in-plane rotation of the image and changes
   none of the constraints, so it needs no sampling):

   a. every tube centreline crosses the plane inside its own extent
      (``tube_outside_body``); for axial tubes at radius r this is
      ``tan(tilt) <= min(z, L - z) / r``;
   b. every tube crosses it only once (``tube_crosses_twice:H0``), since a
      second blob of one tube would be an extra, unexplained marker;
   c. no two cross-sections merge (``tubes_merge:H0/D0``): each is an ellipse of
      semi-minor ``d/2`` and semi-major ``(d/2)/cos(beta)`` along the projected
      tube direction (beta = angle between tube tangent and plane normal),
      smeared by ``slice_thickness * tan(beta)`` along that direction; the gap
      between two blobs measured along the line joining their centres (the gap
      between their projections onto that line, from the blobs' support
      functions, so a positive gap is a real separating strip) must be at least
      one pixel.

   The max tilt is the first failure going up from 0: a tilt grid of 5 deg,
   then bisection to < 0.05 deg. Where tilt 0 already fails, ``max_tilt_deg``
   is 0 and ``limited_by`` names the failing constraint.
2. **Usable depth** ranges at tilts 0, 15, 30 and 45 deg.
3. **Clearances** in 3-D between channel surfaces, and between each channel
   and the bore, the outside and the end faces, against ``print.min_wall``.
   Decision: a channel wall to the bore, the outside or an end face thinner
   than ``min_wall`` is a VIOLATION (``wall_too_thin``: the fluid would leak or
   the print fail). Channel-to-channel gaps below ``min_wall`` and intersecting
   channels are WARNINGS (``channel_wall_thin``, ``channels_intersect``, with
   their z-range): every channel holds the same fluid, so a merge cannot leak,
   and its imaging consequence is already in the tilt limits and usable depth
   (the paper's prototype has its helices touch the diametric tubes near both
   ends by design). Channels running the full length open onto the end faces
   by design (sealed by the caps); that is reported, not a violation.
4. **Overhang**: the steepest angle of each channel from the build direction
   (the axis), ``acos(|t_z|)`` over its unit tangents, against
   ``print.max_overhang_deg`` (violation ``overhang_too_steep``).
5. **Unambiguity**: at every depth usable at tilt 0, the rotations about the
   axis and reflections that map the tilt-0 marker positions (sampled every
   0.1 mm in depth) onto themselves within ``max(pixel, 5 % of d)`` (see
   :func:`~chic_design.feasibility.unambiguity.symmetry_tolerance`), judged by
   the family (:meth:`~chic_design.families.base.Family.unambiguity`; for CHIC
   each is a violation ``symmetric_pattern``). All blobs look alike, so a
   reflection that swaps helices and diametric tubes counts: it is the
   fiducial seen upside down. A helix
   whose angle crosses the angle of a straight tube
   (``helix_leaves_quadrant``), and a design with no depth usable at tilt 0
   (``no_usable_depth``) are violations too.
6. **Depth sensitivity**: mm of depth per degree of helix angle (1/|pitch|) and
   the expected depth precision at the protocol's pixel size, from a centroid
   quantisation bound ``sigma_xy = pixel / sqrt(12)``, ``sigma_theta =
   sigma_xy / r``, ``sigma_z = sigma_theta / |pitch|``, combined over the n
   helices as ``/ sqrt(n)`` (tilt 0, no image noise).

The checks live in one module each; this module runs them (:func:`check_geometry`):

- :mod:`chic_design.feasibility.records`: the result records and the report's
  JSON, summary and markdown;
- :mod:`chic_register.model.envelope`: the plane checks of item 1 (crossings, blob
  sections, gaps), shared with the solver;
- :mod:`chic_design.feasibility.tilt_search`: items 1-2, the tilt search over depth and azimuth;
- :mod:`chic_design.feasibility.printability`: items 3-4, and the rules ``build`` refuses;
- :mod:`chic_design.feasibility.unambiguity`: item 5;
- :mod:`chic_design.feasibility.depth_precision`: item 6;
- :mod:`chic_design.feasibility.tilt_plot`: the max-tilt-vs-depth plot.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Protocol

import numpy as np

from chic_design.feasibility.depth_precision import depth_sensitivity
from chic_design.feasibility.printability import channel_clearances, channel_overhangs
from chic_design.feasibility.records import FeasibilityReport, Finding, Symmetry, Unambiguity
from chic_design.feasibility.tilt_search import tilt_limits, usable_depth
from chic_design.feasibility.unambiguity import helix_quadrant_crossings, pattern_symmetries, symmetry_tolerance
from chic_register.model.geometry import FiducialGeometry


class FamilyRules(Protocol):
    """What the engine asks a fiducial's family (:class:`chic_design.families.base.Family` implements it)."""

    def unambiguity(self, geometry: FiducialGeometry, *, usable_ranges_mm, tolerance_mm: float,
                    symmetries: tuple[Symmetry, ...], min_mismatch_mm: float | None,
                    helix_crossings: tuple[Finding, ...]) -> tuple[Unambiguity, list[Finding], list[Finding]]: ...

    def usable_note(self, geometry: FiducialGeometry) -> str: ...


def check_geometry(geom: FiducialGeometry, family: FamilyRules, *, pixel_size_mm: float, slice_thickness_mm: float,
                   min_wall_mm: float, max_overhang_deg: float, required_tubes=None,
                   printed: bool = True) -> FeasibilityReport:
    """All feasibility checks on a geometry of ``family`` (its unambiguity judged by the family).

    ``required_tubes``: the tubes an image must show as separate dots (None: all); the tilt limits,
    usable depth and pattern symmetries are judged on them alone. ``printed=False`` (hardware not
    made here) leaves out the printability checks (items 3 and 4).
    """
    seen = geom if required_tubes is None else replace(geom, tubes=tuple(required_tubes))
    full = tilt_limits(seen, pixel_size_mm, slice_thickness_mm)
    vis = tilt_limits(seen, pixel_size_mm, slice_thickness_mm, merges=False)
    limits = tuple(replace(f, visibility_tilt_deg=v.max_tilt_deg if v.usable_at_zero_tilt else 0.0)
                   for f, v in zip(full, vis))
    usable = usable_depth(limits)
    violations: list[Finding] = []
    warnings: list[Finding] = []
    if not usable[0].ranges_mm:
        mid = limits[len(limits) // 2]
        violations.append(Finding("no_usable_depth", "no depth is usable even at tilt 0 "
                                  f"(e.g. z = {mid.depth_mm:g} mm: {mid.limited_by})", "all depths"))
    clearances, overhangs = (), ()
    if printed:
        clearances, v, w = channel_clearances(geom, min_wall_mm)
        violations += v
        warnings += w
        overhangs, v = channel_overhangs(geom, max_overhang_deg)
        violations += v
    crossings = helix_quadrant_crossings(seen)
    violations += crossings
    tol = symmetry_tolerance(seen, pixel_size_mm)
    usable_z = np.concatenate([np.linspace(a, b, max(2, int(math.ceil((b - a) / 0.1)) + 1))
                               for a, b in usable[0].ranges_mm] or [np.empty(0)])
    syms, mismatch = pattern_symmetries(seen, usable_z, tol)
    unamb, v, w = family.unambiguity(geom, usable_ranges_mm=usable[0].ranges_mm, tolerance_mm=tol, symmetries=syms,
                                     min_mismatch_mm=mismatch, helix_crossings=crossings)
    violations += v
    warnings += w
    sens = depth_sensitivity(seen, pixel_size_mm)
    return FeasibilityReport(
        name=geom.name,
        pixel_size_mm=float(pixel_size_mm),
        slice_thickness_mm=float(slice_thickness_mm),
        min_wall_mm=float(min_wall_mm),
        max_overhang_deg=float(max_overhang_deg),
        body_length_mm=float(geom.body.length),
        violations=tuple(violations),
        warnings=tuple(warnings),
        tilt_limits=limits,
        usable_depth=usable,
        clearances=clearances,
        overhangs=overhangs,
        unambiguity=unamb,
        depth_sensitivity=sens,
        usable_note=family.usable_note(geom),
    )
