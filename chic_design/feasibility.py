"""Feasibility of a CHIC design: where in the scanner it works, and whether it prints.

:func:`check_design` computes, from the geometry objects of
:func:`chic_design.layout.fiducial_geometry` (never from a re-derived layout):

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
5. **Unambiguity**: at every depth usable at tilt 0, no rotation about the axis
   or reflection maps the tilt-0 marker positions (sampled every 0.1 mm in
   depth) onto themselves within ``max(pixel, 5 % of d)`` (see
   :func:`symmetry_tolerance`) -> violation ``symmetric_pattern``. All blobs
   look alike, so a reflection that swaps helices and diametric tubes counts: it
   is the fiducial seen upside down. A helix
   whose angle crosses the angle of a straight tube
   (``helix_leaves_quadrant``), and a design with no depth usable at tilt 0
   (``no_usable_depth``) are violations too.
6. **Depth sensitivity**: mm of depth per degree of helix angle (1/|pitch|) and
   the expected depth precision at the protocol's pixel size, from a centroid
   quantisation bound ``sigma_xy = pixel / sqrt(12)``, ``sigma_theta =
   sigma_xy / r``, ``sigma_z = sigma_theta / |pitch|``, combined over the n
   helices as ``/ sqrt(n)`` (tilt 0, no image noise).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from chic_register.atomic import atomic_path
from chic_register.envelope import (  # noqa: F401 - the plane checks live with the solver, re-exported here
    OUTSIDE, _clipped_disc_distance, _pair_order, _PlaneChecker, crossing_counts, plane_crossings, plane_normals,
    section_gap,
)
from chic_register.geometry import FiducialGeometry, LineTube

from .spec import Spec

USABLE_TILTS_DEG = (0.0, 15.0, 30.0, 45.0)
TILT_CAP_DEG = 89.0
NO_LIMIT = "none_below_89_deg"
_WALL_TOL_MM = 1e-6


# ----------------------------------------------------------------------------- results


@dataclass(frozen=True)
class Finding:
    """A violation or warning: machine ``code``, one-line ``message``, ``where`` (tube, z-range...)."""

    code: str
    message: str
    where: str

    def to_dict(self) -> dict:
        return {"code": self.code, "message": self.message, "where": self.where}


@dataclass(frozen=True)
class TiltLimit:
    """Max tilt (deg) of an image plane through the axis at ``depth_mm``, over all azimuths.

    ``limited_by`` names the constraint that fails just above it; ``azimuth_deg``
    is the worst azimuth; ``usable_at_zero_tilt`` is False where even tilt 0 fails;
    ``visibility_tilt_deg`` is the limit from constraint (a) alone (every tube
    crosses the plane inside its extent), for comparison with the paper.
    """

    depth_mm: float
    max_tilt_deg: float
    limited_by: str
    azimuth_deg: float = 0.0
    usable_at_zero_tilt: bool = True
    visibility_tilt_deg: float | None = None

    def to_dict(self) -> dict:
        return {
            "depth_mm": round(float(self.depth_mm), 4),
            "max_tilt_deg": round(float(self.max_tilt_deg), 2),
            "limited_by": self.limited_by,
            "azimuth_deg": round(float(self.azimuth_deg), 2),
            "usable_at_zero_tilt": bool(self.usable_at_zero_tilt),
            "visibility_tilt_deg": None if self.visibility_tilt_deg is None
            else round(float(self.visibility_tilt_deg), 2),
        }


@dataclass(frozen=True)
class UsableDepth:
    """Contiguous depth intervals ``ranges_mm`` ((z0, z1), ...) where max tilt >= ``tilt_deg``."""

    tilt_deg: float
    ranges_mm: tuple[tuple[float, float], ...]

    @property
    def total_mm(self) -> float:
        return float(sum(b - a for a, b in self.ranges_mm))

    def to_dict(self) -> dict:
        return {
            "tilt_deg": float(self.tilt_deg),
            "ranges_mm": [[round(a, 4), round(b, 4)] for a, b in self.ranges_mm],
            "total_mm": round(self.total_mm, 4),
        }


@dataclass(frozen=True)
class Clearance:
    """Smallest surface-to-surface gap between channel ``a`` and ``b`` (a channel or a body surface).

    ``b`` is a tube id or ``bore``, ``outside``, ``bottom_face``, ``top_face``.
    ``gap_mm`` < 0 means overlap. ``status``: ok, thin, intersect, open (a
    channel that runs through an end face by design), too_thin (a wall violation).
    ``intersect_z_mm``: z-ranges where they intersect (where their sections by
    planes z = const overlap: :func:`chic_design.contacts.channel_contacts`, the
    answer the report gives too); ``thin_z_mm``: z-ranges (on channel ``a``)
    where they are closer than the minimum wall.
    """

    a: str
    b: str
    gap_mm: float
    at_z_mm: float
    status: str
    intersect_z_mm: tuple[tuple[float, float], ...] = ()
    thin_z_mm: tuple[tuple[float, float], ...] = ()

    def to_dict(self) -> dict:
        return {
            "a": self.a,
            "b": self.b,
            "gap_mm": round(float(self.gap_mm), 4),
            "at_z_mm": round(float(self.at_z_mm), 4),
            "status": self.status,
            "intersect_z_mm": [[round(p, 3), round(q, 3)] for p, q in self.intersect_z_mm],
            "thin_z_mm": [[round(p, 3), round(q, 3)] for p, q in self.thin_z_mm],
        }


@dataclass(frozen=True)
class Overhang:
    """Steepest angle (deg) of channel ``tube_id`` from the build direction (the axis)."""

    tube_id: str
    max_overhang_deg: float
    at_z_mm: float

    def to_dict(self) -> dict:
        return {"tube": self.tube_id, "max_overhang_deg": round(self.max_overhang_deg, 3),
                "at_z_mm": round(self.at_z_mm, 3)}


@dataclass(frozen=True)
class Symmetry:
    """A (near) symmetry of the tilt-0 marker pattern over ``depth_range_mm``.

    ``kind``: rotation (about the axis, by ``angle_deg``) or reflection (about the
    line at ``angle_deg``), the one with the smallest ``mismatch_mm`` (worst
    marker displacement) in the range, at ``at_depth_mm``.
    """

    kind: str
    angle_deg: float
    depth_range_mm: tuple[float, float]
    at_depth_mm: float
    mismatch_mm: float

    def describe(self) -> str:
        if self.kind == "rotation":
            return f"rotation by {self.angle_deg:.1f} deg about the axis"
        return f"reflection about the {self.angle_deg:.1f}/{self.angle_deg + 180:.1f} deg line"

    def to_dict(self) -> dict:
        return {"kind": str(self.kind), "angle_deg": round(float(self.angle_deg), 3),
                "depth_range_mm": [round(float(v), 4) for v in self.depth_range_mm],
                "at_depth_mm": round(float(self.at_depth_mm), 4),
                "mismatch_mm": round(float(self.mismatch_mm), 4), "what": self.describe()}


@dataclass(frozen=True)
class Unambiguity:
    """Symmetry analysis of the marker pattern at the depths usable at tilt 0.

    ``tolerance_mm``: a symmetry counts if it maps every marker within this of
    another; ``min_mismatch_mm``: over the usable depths and all candidate
    rotations/reflections, the smallest worst-marker mismatch (how far the
    pattern is from symmetric; > tolerance means unambiguous).
    """

    tolerance_mm: float
    min_mismatch_mm: float | None
    symmetries: tuple[Symmetry, ...]
    helix_crossings: tuple[Finding, ...]
    frame_symmetries: tuple | None = None  # 3-D (Z-frame family): chic_design.frame_symmetry
    frame_min_mismatch_mm: float | None = None

    @property
    def unambiguous(self) -> bool:
        """No symmetry of the slice pattern or (where checked) of the whole fiducial."""
        return not self.symmetries and not self.helix_crossings and not self.frame_symmetries

    def to_dict(self) -> dict:
        out = {
            "tolerance_mm": round(self.tolerance_mm, 4),
            "tolerance_rule": "max(pixel size, 5% of the tube diameter)",
            "min_mismatch_mm": None if self.min_mismatch_mm is None else round(self.min_mismatch_mm, 4),
            "symmetries": [s.to_dict() for s in self.symmetries],
            "helix_leaves_quadrant": [f.to_dict() for f in self.helix_crossings],
        }
        if self.frame_symmetries is not None:
            out["frame_symmetries"] = [f.to_dict() for f in self.frame_symmetries]
            out["frame_min_mismatch_mm"] = (None if self.frame_min_mismatch_mm is None
                                            else round(self.frame_min_mismatch_mm, 4))
            out["unambiguous"] = self.unambiguous
        return out


@dataclass(frozen=True)
class DepthSensitivity:
    """Depth per degree of helix angle, and the expected depth precision (see module docstring)."""

    per_helix_mm_per_deg: tuple[tuple[str, float], ...]
    sigma_xy_mm: float
    per_helix_sigma_z_mm: tuple[tuple[str, float], ...]
    combined_sigma_z_mm: float | None

    METHOD = (
        "centroid quantisation bound sigma_xy = pixel/sqrt(12) per blob; helix angle "
        "sigma_theta = sigma_xy/r (rad); depth sigma_z = sigma_theta/|pitch|; combined over "
        "the n helices as 1/sqrt(n); tilt 0, no image noise, slice-thickness smear ignored "
        "(it blurs symmetrically and does not bias the centroid)"
    )

    def to_dict(self) -> dict:
        return {
            "mm_per_deg": {k: round(v, 6) for k, v in self.per_helix_mm_per_deg},
            "sigma_xy_mm": round(self.sigma_xy_mm, 6),
            "sigma_z_mm": {k: round(v, 6) for k, v in self.per_helix_sigma_z_mm},
            "combined_sigma_z_mm": None if self.combined_sigma_z_mm is None
            else round(self.combined_sigma_z_mm, 6),
            "method": self.METHOD,
        }


@dataclass(frozen=True)
class FeasibilityReport:
    """Everything :func:`check_design` found. ``feasible`` = no violations."""

    name: str
    pixel_size_mm: float
    slice_thickness_mm: float
    min_wall_mm: float
    max_overhang_deg: float
    body_length_mm: float
    violations: tuple[Finding, ...]
    warnings: tuple[Finding, ...]
    tilt_limits: tuple[TiltLimit, ...]
    usable_depth: tuple[UsableDepth, ...]
    clearances: tuple[Clearance, ...]
    overhangs: tuple[Overhang, ...]
    unambiguity: Unambiguity
    depth_sensitivity: DepthSensitivity
    plot_name: str = "tilt_limits.png"
    family: str = "chic"
    n_tubes: int = 0

    @property
    def feasible(self) -> bool:
        return not self.violations

    @property
    def mid_depth_limit(self) -> TiltLimit:
        mid = self.body_length_mm / 2
        return min(self.tilt_limits, key=lambda t: abs(t.depth_mm - mid))

    def to_dict(self) -> dict:
        return {
            "feasible": self.feasible,
            "violations": [v.to_dict() for v in self.violations],
            "tilt_limits": [t.to_dict() for t in self.tilt_limits],
            "warnings": [w.to_dict() for w in self.warnings],
            "name": self.name,
            "protocol": {"pixel_size_mm": self.pixel_size_mm, "slice_thickness_mm": self.slice_thickness_mm},
            "mid_depth": self.mid_depth_limit.to_dict(),
            "usable_depth": [u.to_dict() for u in self.usable_depth],
            "clearances": {
                "min_wall_mm": self.min_wall_mm,
                "policy": "channel to bore/outside/end face thinner than min_wall: violation "
                "wall_too_thin; channel to channel thinner or intersecting: warning "
                "(same fluid, cannot leak; imaging effect is in the tilt limits); full-length "
                "channels open onto the end faces by design (sealed by the caps)",
                "pairs": [c.to_dict() for c in self.clearances],
            },
            "overhangs": {"max_overhang_deg": self.max_overhang_deg,
                          "channels": [o.to_dict() for o in self.overhangs]},
            "unambiguity": self.unambiguity.to_dict(),
            "depth_sensitivity": self.depth_sensitivity.to_dict(),
        }

    def summary_text(self) -> str:
        mid = self.mid_depth_limit
        lines = [
            f"{self.name}: {'FEASIBLE' if self.feasible else 'INFEASIBLE'} "
            f"(pixel {self.pixel_size_mm:g} mm, slice {self.slice_thickness_mm:g} mm)",
            f"tilt limit at mid-depth z = {mid.depth_mm:g} mm: {mid.max_tilt_deg:.1f} deg, "
            f"limited by {mid.limited_by} (worst azimuth {mid.azimuth_deg:.1f} deg); "
            f"visibility alone (every tube inside the body) allows {mid.visibility_tilt_deg:.1f} deg",
        ]
        if self.family == "zframe":  # what a Z-frame user asks: where are all rods seen apart
            lines.append(f"usable = all {self.n_tubes} rods visible and separate (one blob each, at least one "
                         "pixel apart), for every azimuth:")
        for u in self.usable_depth:
            rng = ", ".join(f"{a:g}-{b:g} mm" for a, b in u.ranges_mm) or "none"
            lines.append(f"usable depth at tilt {u.tilt_deg:g} deg: {rng} ({u.total_mm:g} mm)")
        walls = [c for c in self.clearances if c.b in ("bore", "outside")]
        if walls:
            w = min(walls, key=lambda c: c.gap_mm)
            lines.append(f"thinnest body wall: {w.gap_mm:.3f} mm ({w.a} to {w.b}; min {self.min_wall_mm:g} mm)")
        worst = max(self.overhangs, key=lambda o: o.max_overhang_deg, default=None)
        if worst is not None:
            lines.append(f"steepest overhang: {worst.max_overhang_deg:.1f} deg ({worst.tube_id}; "
                         f"max {self.max_overhang_deg:g} deg)")
        ds = self.depth_sensitivity
        if ds.per_helix_mm_per_deg:
            mpd = ", ".join(f"{k} {v:.3f}" for k, v in ds.per_helix_mm_per_deg)
            prec = "n/a" if ds.combined_sigma_z_mm is None else f"{ds.combined_sigma_z_mm:.3f} mm"
            lines.append(f"depth sensitivity (mm/deg): {mpd}; expected depth precision {prec} "
                         "(pixel/sqrt(12) centroid bound)")
        for v in self.violations:
            lines.append(f"VIOLATION {v.code} ({v.where}): {v.message}")
        for w in self.warnings:
            lines.append(f"warning {w.code} ({w.where}): {w.message}")
        return "\n".join(lines)

    def markdown(self) -> str:
        """A ``## Feasibility`` section for report.md (refers to the plot ``tilt_limits.png``)."""
        mid = self.mid_depth_limit
        out = [
            "## Feasibility",
            "",
            f"**{'Feasible' if self.feasible else 'Infeasible'}** for pixel size "
            f"{self.pixel_size_mm:g} mm and slice thickness {self.slice_thickness_mm:g} mm.",
            "",
            f"Tilt limit at mid-depth (z = {mid.depth_mm:g} mm): **{mid.max_tilt_deg:.1f} deg**, "
            f"limited by `{mid.limited_by}` (visibility alone: {mid.visibility_tilt_deg:.1f} deg).",
            "",
            f"![max tilt vs depth]({self.plot_name})",
            "",
            "| tilt (deg) | usable depth (mm) | total (mm) |",
            "|---|---|---|",
        ]
        for u in self.usable_depth:
            rng = ", ".join(f"{a:g}-{b:g}" for a, b in u.ranges_mm) or "none"
            out.append(f"| {u.tilt_deg:g} | {rng} | {u.total_mm:g} |")
        out += ["", "| violation | where | message |", "|---|---|---|"]
        out += [f"| {v.code} | {v.where} | {v.message} |" for v in self.violations] or ["| none | | |"]
        out += ["", "| warning | where | message |", "|---|---|---|"]
        out += [f"| {w.code} | {w.where} | {w.message} |" for w in self.warnings] or ["| none | | |"]
        out += ["", f"Walls (min {self.min_wall_mm:g} mm):", "", "| channel | to | gap (mm) | status |",
                "|---|---|---|---|"]
        out += [f"| {c.a} | {c.b} | {c.gap_mm:.3f} | {c.status} |" for c in self.clearances
                if c.b in ("bore", "outside", "bottom_face", "top_face") or c.status != "ok"]
        ds = self.depth_sensitivity
        if ds.per_helix_mm_per_deg:
            out += ["", "Depth sensitivity: " + ", ".join(f"{k} {v:.3f} mm/deg" for k, v in ds.per_helix_mm_per_deg)
                    + (f"; expected depth precision {ds.combined_sigma_z_mm:.3f} mm" if ds.combined_sigma_z_mm
                       is not None else "") + f" ({ds.METHOD})."]
        return "\n".join(out) + "\n"


def _max_tilt(checker: _PlaneChecker, z: np.ndarray, az: np.ndarray, grid_step: float = 5.0,
              tol_deg: float = 0.05):
    """Per (depth, azimuth) pair: first failing tilt (grid, then bisection). Returns tilt, code, ok0."""
    grid = np.append(np.arange(0.0, TILT_CAP_DEG, grid_step), TILT_CAP_DEG)
    P = z.size
    k = np.full(P, grid.size)  # index of the first failing grid tilt
    first_code = np.zeros(P, dtype=int)
    alive = np.arange(P)
    for i, g in enumerate(grid):  # only planes that have not failed yet
        if not alive.size:
            break
        c = checker.codes(z[alive], g, az[alive])
        bad = c != 0
        k[alive[bad]] = i
        first_code[alive[bad]] = c[bad]
        alive = alive[~bad]
    anyfail = k < grid.size
    ok0 = k > 0
    tilt = np.where(anyfail, 0.0, TILT_CAP_DEG)
    code = np.where(k == 0, first_code, 0)
    sel = np.flatnonzero(anyfail & (k > 0))
    if sel.size:
        lo, hi = grid[k[sel] - 1], grid[k[sel]]
        hic = first_code[sel]
        while np.max(hi - lo) > tol_deg:
            mid = 0.5 * (lo + hi)
            c = checker.codes(z[sel], mid, az[sel])
            bad = c != 0
            hi = np.where(bad, mid, hi)
            hic = np.where(bad, c, hic)
            lo = np.where(bad, lo, mid)
        tilt[sel] = lo
        code[sel] = hic
    return tilt, code, ok0


def depth_samples(length_mm: float, step_mm: float = 1.0) -> np.ndarray:
    """Depths from 0 to ``length_mm`` at <= ``step_mm``, both ends and mid-depth included."""
    n = max(2, int(math.ceil(length_mm / step_mm)))
    n += n % 2  # even number of intervals: mid-depth is a sample
    return np.linspace(0.0, length_mm, n + 1)


def tilt_limits(geom: FiducialGeometry, pixel_size_mm: float, slice_thickness_mm: float,
                depths_mm=None, azimuth_step_deg: float = 10.0, refine_step_deg: float = 0.5,
                merges: bool = True, exact: bool = False) -> tuple[TiltLimit, ...]:
    """Max tilt at each depth (default :func:`depth_samples`), worst case over azimuth.

    Azimuths on a ``azimuth_step_deg`` grid, then a ``refine_step_deg`` grid of
    +-``azimuth_step_deg`` around each depth's worst azimuth. Twist is an
    in-plane rotation of the image and changes none of the constraints.
    ``merges=False`` checks visibility (tubes inside the body, crossed once) only.
    ``exact=True`` replaces the ellipse gap of pairs with a helix or a blob cut
    by an end face, where it is within ``0.1 mm`` of one pixel, by the exact
    :func:`section_gap` (about 15x slower; for designs/neuro.yaml it gives the
    same limits to 0.1 deg, so :func:`check_geometry` uses the ellipse model).
    """
    checker = _PlaneChecker(geom, pixel_size_mm, slice_thickness_mm, merges=merges, exact=exact)
    zs = depth_samples(geom.body.length) if depths_mm is None else np.asarray(depths_mm, dtype=float)
    azs = np.arange(0.0, 360.0, azimuth_step_deg)
    Z, A = np.meshgrid(zs, azs, indexing="ij")
    tilt, code, ok0 = (v.reshape(Z.shape) for v in _max_tilt(checker, Z.ravel(), A.ravel()))
    w = np.argmin(tilt, axis=1)
    rows = np.arange(len(zs))
    best_t, best_c, best_a = tilt[rows, w], code[rows, w], A[rows, w]
    usable0 = ok0.all(axis=1)
    # refine azimuth around the worst one (where something above tilt 0 limits it)
    need = usable0 & (best_t < TILT_CAP_DEG)
    if need.any():
        # bracket each neighbour azimuth in [worst - 3, worst + tol]: only lower limits matter
        off = np.arange(-azimuth_step_deg, azimuth_step_deg + 1e-9, refine_step_deg)
        rows2 = np.repeat(np.flatnonzero(need), off.size)
        Z2 = zs[rows2]
        A2 = (best_a[rows2] + np.tile(off, need.sum())) % 360.0
        hi = best_t[rows2] + 0.05
        lo = np.maximum(best_t[rows2] - 3.0, 0.0)
        c_lo = checker.codes(Z2, lo, A2)
        low_fail = c_lo != 0
        t2 = np.empty(Z2.size)
        c2 = np.zeros(Z2.size, dtype=int)
        if low_fail.any():  # rare: far lower than the grid showed; search from tilt 0
            t2[low_fail], c2[low_fail], _ = _max_tilt(checker, Z2[low_fail], A2[low_fail])
        ok = np.flatnonzero(~low_fail)
        lo, hi, hic = lo[ok], hi[ok], np.zeros(ok.size, dtype=int)
        while ok.size and np.max(hi - lo) > 0.05:
            mid = 0.5 * (lo + hi)
            c = checker.codes(Z2[ok], mid, A2[ok])
            bad = c != 0
            hi, hic, lo = np.where(bad, mid, hi), np.where(bad, c, hic), np.where(bad, lo, mid)
        t2[ok], c2[ok] = lo, hic
        for r in np.flatnonzero(need):
            m = rows2 == r
            j = np.argmin(np.where(c2[m] != 0, t2[m], np.inf))
            if c2[m][j] != 0 and t2[m][j] < best_t[r]:
                best_t[r], best_c[r], best_a[r] = t2[m][j], c2[m][j], A2[m][j]
    return tuple(
        TiltLimit(float(z), float(t) if u else 0.0, checker.labels[int(c)] if c else NO_LIMIT,
                  float(a), bool(u))
        for z, t, c, a, u in zip(zs, best_t, best_c, best_a, usable0)
    )


def usable_depth(limits, tilts_deg=USABLE_TILTS_DEG) -> tuple[UsableDepth, ...]:
    """Contiguous runs of depth samples usable at each tilt (range ends are sample depths)."""
    zs = np.array([t.depth_mm for t in limits])
    out = []
    for tilt in tilts_deg:
        ok = np.array([t.usable_at_zero_tilt and t.max_tilt_deg >= tilt for t in limits])
        out.append(UsableDepth(float(tilt), _runs(zs, ok)))
    return tuple(out)


def _runs(zs: np.ndarray, mask: np.ndarray) -> tuple[tuple[float, float], ...]:
    """(first z, last z) of every run of True in ``mask`` (zs sorted)."""
    runs, start = [], None
    for i, m in enumerate(mask):
        if m and start is None:
            start = i
        if start is not None and (not m or i == len(mask) - 1):
            end = i if m else i - 1
            runs.append((float(zs[start]), float(zs[end])))
            start = None
    return tuple(runs)


# ----------------------------------------------------------------------------- clearances


def _samples(tube, spacing_mm: float):
    """Centreline parameters, points (N, 3) and unit tangents (N, 3) at <= ``spacing_mm``."""
    n = max(2, int(math.ceil(tube.length_mm / spacing_mm)) + 1)
    t = np.linspace(0.0, 1.0, n)
    return t, tube.points(t), tube.tangents(t)


def _pair_gap(ta, tb, min_wall_mm: float, spacing_mm: float):
    """Surface gap between two channels: min (refined), z there, intersect / thin z-ranges on ``ta``."""
    from scipy.spatial import cKDTree

    ra, rb = ta.diameter / 2, tb.diameter / 2
    sa, pa, _ = _samples(ta, spacing_mm)
    sb, pb, _ = _samples(tb, spacing_mm)
    d, nb = cKDTree(pb).query(pa)
    gap = d - ra - rb
    k = int(np.argmin(gap))
    # refine the minimum on a fine parameter grid around the best sample pair
    fine = np.linspace(-1.0, 1.0, 41)
    ua = np.clip(sa[k] + fine * (sa[1] - sa[0]), 0.0, 1.0)
    ub = np.clip(sb[nb[k]] + fine * (sb[1] - sb[0]), 0.0, 1.0)
    qa, qb = ta.points(ua), tb.points(ub)
    dd = np.linalg.norm(qa[:, None, :] - qb[None, :, :], axis=-1)
    i, _ = np.unravel_index(np.argmin(dd), dd.shape)
    best = float(min(dd.min(), d[k])) - ra - rb
    at = qa[i] if dd.min() <= d[k] else pa[k]
    zs = pa[:, 2]
    order = np.argsort(zs, kind="stable")
    inter = _runs(zs[order], (gap < 0)[order])
    thin = _runs(zs[order], ((gap >= 0) & (gap < min_wall_mm - _WALL_TOL_MM))[order])
    return best, float(at[2]), inter, thin


def _fmt_ranges(ranges) -> str:
    return ", ".join(f"{a:.1f}-{b:.1f}" for a, b in ranges)


def channel_clearances(geom: FiducialGeometry, min_wall_mm: float, spacing_mm: float = 0.1):
    """Clearances channel-channel and channel-body (see module docstring, item 3).

    Returns ``(clearances, violations, warnings)``.
    """
    out: list[Clearance] = []
    viol: list[Finding] = []
    warn: list[Finding] = []
    body = geom.body
    length = body.length
    from .contacts import channel_contacts

    # z-ranges where two channels touch: the one answer (contacts), also used by the report
    touch = {frozenset((c.a, c.b)): c.z_ranges_mm for c in channel_contacts(geom)}
    for i, j in _pair_order(geom):
        a, b = geom.tubes[i], geom.tubes[j]
        gap, z, inter, thin = _pair_gap(a, b, min_wall_mm, spacing_mm)
        inter = touch.get(frozenset((a.id, b.id)), inter)
        if gap < 0:
            status = "intersect"
            warn.append(Finding("channels_intersect", f"channels {a.id} and {b.id} intersect (overlap "
                                f"{-gap:.2f} mm) at z {_fmt_ranges(inter)} mm; same fluid, no leak; "
                                "those depths are limited in the tilt limits", f"{a.id}/{b.id}"))
        elif gap < min_wall_mm - _WALL_TOL_MM:
            status = "thin"
            warn.append(Finding("channel_wall_thin", f"wall between {a.id} and {b.id} is {gap:.3f} mm "
                                f"(< min_wall {min_wall_mm:g}) at z {_fmt_ranges(thin)} mm", f"{a.id}/{b.id}"))
        else:
            status = "ok"
        out.append(Clearance(a.id, b.id, gap, z, status, inter, thin))
    for tube in geom.tubes:
        r = tube.diameter / 2
        _, p, _ = _samples(tube, spacing_mm)
        for name, gaps in (("bore", body.bore_gap_mm(p[:, :2]) - r), ("outside", body.outside_gap_mm(p[:, :2]) - r)):
            k = int(np.argmin(gaps))
            g = float(gaps[k])
            bad = g < min_wall_mm - _WALL_TOL_MM
            out.append(Clearance(tube.id, name, g, float(p[k, 2]), "too_thin" if bad else "ok"))
            if bad:
                viol.append(Finding("wall_too_thin", f"wall from channel {tube.id} to the "
                                    f"{'bore' if name == 'bore' else 'outside surface'} is {g:.3f} mm; "
                                    f"min_wall is {min_wall_mm:g} mm", f"{tube.id} z={p[k, 2]:.1f} mm"))
        for name, zc in (("bottom_face", float(p[:, 2].min())), ("top_face", float(length - p[:, 2].max()))):
            g = zc - r
            zat = 0.0 if name == "bottom_face" else length
            if zc <= _WALL_TOL_MM:
                out.append(Clearance(tube.id, name, g, zat, "open"))
            elif g < min_wall_mm - _WALL_TOL_MM:
                out.append(Clearance(tube.id, name, g, zat, "too_thin"))
                viol.append(Finding("wall_too_thin", f"channel {tube.id} ends {g:.3f} mm from the {name.replace('_', ' ')}"
                                    f"; min_wall is {min_wall_mm:g} mm", f"{tube.id} {name}"))
            else:
                out.append(Clearance(tube.id, name, g, zat, "ok"))
    return tuple(out), viol, warn


def channel_overhangs(geom: FiducialGeometry, max_overhang_deg: float, spacing_mm: float = 0.5):
    """Steepest angle from the build direction (+z) of each channel: max acos(|t_z|). Returns (overhangs, violations)."""
    out, viol = [], []
    for tube in geom.tubes:
        _, p, tg = _samples(tube, spacing_mm)
        ang = np.degrees(np.arccos(np.clip(np.abs(tg[:, 2]), 0.0, 1.0)))
        k = int(np.argmax(ang))
        out.append(Overhang(tube.id, float(ang[k]), float(p[k, 2])))
        if ang[k] > max_overhang_deg + 1e-9:
            viol.append(Finding("overhang_too_steep", f"channel {tube.id} runs {ang[k]:.1f} deg from the "
                                f"build direction; max_overhang_deg is {max_overhang_deg:g}", tube.id))
    return tuple(out), viol


# ----------------------------------------------------------------------------- unambiguity


def _wrap180(a):
    return (np.asarray(a) + 180.0) % 360.0 - 180.0


def helix_quadrant_crossings(geom: FiducialGeometry, step_mm: float = 0.05) -> tuple[Finding, ...]:
    """Helices whose angle crosses the angle of a straight tube within their common z extent."""
    out = []
    for h in (t for t in geom.tubes if t.role == "helix"):
        for line in (t for t in geom.tubes if isinstance(t, LineTube)):
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
    for a, b in _runs(np.arange(Z), best_m <= tolerance_mm):
        a, b = int(a), int(b)
        zi = a + int(np.argmin(best_m[a:b + 1]))
        k = str(kind[best[zi]])
        angle = float(np.degrees(ang[zi, best[zi]]) % (360.0 if k == "rotation" else 180.0))
        syms.append(Symmetry(k, angle, (float(zs[a]), float(zs[b])), float(zs[zi]), float(best_m[zi])))
    return tuple(syms), min_mismatch


def depth_sensitivity(geom: FiducialGeometry, pixel_size_mm: float) -> DepthSensitivity:
    """mm of depth per degree of helix angle and expected depth precision (see module docstring, item 6)."""
    sigma_xy = pixel_size_mm / math.sqrt(12.0)
    per, sig = [], []
    for h in (t for t in geom.tubes if t.role == "helix" and hasattr(t, "pitch_deg_per_mm")):
        w = abs(h.pitch_deg_per_mm)
        per.append((h.id, 1.0 / w))
        sig.append((h.id, math.degrees(sigma_xy / h.radius) / w))
    combined = None
    if sig:
        inv = sum(1.0 / v**2 for _, v in sig if v > 0)
        combined = 0.0 if inv == 0 else 1.0 / math.sqrt(inv)
    return DepthSensitivity(tuple(per), sigma_xy, tuple(sig), combined)


# ----------------------------------------------------------------------------- check_design


def check_geometry(geom: FiducialGeometry, *, pixel_size_mm: float, slice_thickness_mm: float,
                   min_wall_mm: float, max_overhang_deg: float) -> FeasibilityReport:
    """All feasibility checks on a geometry (what :func:`check_design` runs for a spec)."""
    full = tilt_limits(geom, pixel_size_mm, slice_thickness_mm)
    vis = tilt_limits(geom, pixel_size_mm, slice_thickness_mm, merges=False)
    limits = tuple(replace(f, visibility_tilt_deg=v.max_tilt_deg if v.usable_at_zero_tilt else 0.0)
                   for f, v in zip(full, vis))
    usable = usable_depth(limits)
    violations: list[Finding] = []
    warnings: list[Finding] = []
    if not usable[0].ranges_mm:
        mid = limits[len(limits) // 2]
        violations.append(Finding("no_usable_depth", "no depth is usable even at tilt 0 "
                                  f"(e.g. z = {mid.depth_mm:g} mm: {mid.limited_by})", "all depths"))
    clearances, v, w = channel_clearances(geom, min_wall_mm)
    violations += v
    warnings += w
    overhangs, v = channel_overhangs(geom, max_overhang_deg)
    violations += v
    crossings = helix_quadrant_crossings(geom)
    violations += crossings
    tol = symmetry_tolerance(geom, pixel_size_mm)
    usable_z = np.concatenate([np.linspace(a, b, max(2, int(math.ceil((b - a) / 0.1)) + 1))
                               for a, b in usable[0].ranges_mm] or [np.empty(0)])
    syms, mismatch = pattern_symmetries(geom, usable_z, tol)
    if geom.family == "zframe":
        from .zframe_check import zframe_unambiguity

        unamb, w = zframe_unambiguity(geom, usable[0].ranges_mm, mismatch, crossings, tol)
        warnings += w
        syms = ()  # reported as warnings above
    for sym in syms:
        a, b = sym.depth_range_mm
        violations.append(Finding("symmetric_pattern", f"the tilt-0 marker pattern maps onto itself under a "
                                  f"{sym.describe()} (worst marker off by {sym.mismatch_mm:.2f} mm at z = "
                                  f"{sym.at_depth_mm:.2f} mm; tolerance {tol:.2f} mm): twist/depth are "
                                  "ambiguous; move the orientation tubes so that no tube is equally far "
                                  "from its two neighbours", f"z {a:.2f}-{b:.2f} mm"))
    if geom.family != "zframe":
        unamb = Unambiguity(tol, mismatch, syms, crossings)
    sens = depth_sensitivity(geom, pixel_size_mm)
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
        family=geom.family,
        n_tubes=len(geom.tubes),
    )


def symmetry_tolerance(geom: FiducialGeometry, pixel_size_mm: float) -> float:
    """Largest marker displacement an image cannot resolve: one pixel, at least 5 % of the tube diameter.

    One pixel is conservative against the centroid quantisation bound
    (pixel/sqrt(12)), allowing for noise, partial volume and tilt distortion;
    the 5 % floor stands for the printed channel's shape tolerance, which
    bounds how well a marker centre is known even with ideal imaging.
    """
    return max(pixel_size_mm, 0.05 * min(t.diameter for t in geom.tubes))


def check_design(spec: Spec, pixel_size_mm: float | None = None,
                 slice_thickness_mm: float | None = None) -> FeasibilityReport:
    """Feasibility of ``spec`` for its imaging protocol (pixel size / slice thickness overridable)."""
    from .layout import design_geometry
    from .printability import build_violations

    geom = design_geometry(spec)
    pixel = spec.imaging.pixel_size if pixel_size_mm is None else float(pixel_size_mm)
    report = check_geometry(
        geom,
        pixel_size_mm=pixel,
        slice_thickness_mm=spec.imaging.slice_thickness if slice_thickness_mm is None else float(slice_thickness_mm),
        min_wall_mm=spec.print.min_wall,
        max_overhang_deg=spec.print.max_overhang_deg,
    )
    extra = build_violations(spec, geom, pixel)  # caps, output checks, depth precision (check == build)
    return replace(report, violations=report.violations + tuple(extra)) if extra else report


# ----------------------------------------------------------------------------- plot


def save_tilt_plot(report: FeasibilityReport, png_path) -> Path:
    """Max tilt vs depth, coloured by limiting constraint, usable-depth bands at 0/15/30/45 deg.

    Written atomically (temporary file, then rename).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(png_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    zs = np.array([t.depth_mm for t in report.tilt_limits])
    ts = np.array([t.max_tilt_deg for t in report.tilt_limits])
    labels = [t.limited_by if t.usable_at_zero_tilt else "unusable even at tilt 0"
              for t in report.tilt_limits]
    vis = [t.visibility_tilt_deg for t in report.tilt_limits]
    fig, ax = plt.subplots(figsize=(8, 4.5), dpi=120)
    try:
        ax.plot(zs, ts, color="0.6", lw=1, zorder=1)
        if all(v is not None for v in vis):
            ax.plot(zs, vis, color="0.3", lw=1, ls="--", zorder=1, label="visibility alone")
        cmap = plt.get_cmap("tab10")
        for k, lab in enumerate(dict.fromkeys(labels)):
            m = np.array([x == lab for x in labels])
            color = "0.5" if lab.startswith("unusable") else cmap(k % 10)
            ax.scatter(zs[m], ts[m], s=14, color=color, label=lab, zorder=2)
        for u in report.usable_depth:
            for a, b in u.ranges_mm:
                ax.plot([a, b], [u.tilt_deg, u.tilt_deg], color="k", lw=3, alpha=0.35,
                        solid_capstyle="butt")
            ax.axhline(u.tilt_deg, color="k", lw=0.5, ls=":")
            ax.text(zs[-1], u.tilt_deg + 0.8, f"{u.tilt_deg:g} deg: {u.total_mm:g} mm usable",
                    ha="right", va="bottom", fontsize=7)
        ax.set_xlabel("depth z along the axis (mm)")
        ax.set_ylabel("max tilt, worst azimuth (deg)")
        ax.set_title(f"{report.name}: max image tilt (pixel {report.pixel_size_mm:g} mm, "
                     f"slice {report.slice_thickness_mm:g} mm)", fontsize=9)
        ax.set_xlim(zs[0], zs[-1])
        ax.set_ylim(0, 90)
        ax.legend(fontsize=7, loc="upper left", title="limited by", title_fontsize=7, framealpha=0.9)
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png")
    finally:
        plt.close(fig)
    return path
