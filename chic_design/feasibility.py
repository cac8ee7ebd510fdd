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
from chic_register.geometry import FiducialGeometry, LineTube

from .spec import Spec

USABLE_TILTS_DEG = (0.0, 15.0, 30.0, 45.0)
TILT_CAP_DEG = 89.0
OUTSIDE = "tube_outside_body"
NO_LIMIT = "none_below_89_deg"
_ROLE_RANK = {"helix": 0, "orientation": 1, "diametric": 2, "other": 3}
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
    ``intersect_z_mm`` / ``thin_z_mm``: z-ranges (on channel ``a``) where they
    intersect / are closer than the minimum wall.
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

    def to_dict(self) -> dict:
        return {
            "tolerance_mm": round(self.tolerance_mm, 4),
            "tolerance_rule": "max(pixel size, 5% of the tube diameter)",
            "min_mismatch_mm": None if self.min_mismatch_mm is None else round(self.min_mismatch_mm, 4),
            "symmetries": [s.to_dict() for s in self.symmetries],
            "helix_leaves_quadrant": [f.to_dict() for f in self.helix_crossings],
        }


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


# ----------------------------------------------------------------------------- plane crossings


def plane_normals(tilt_deg, azimuth_deg) -> np.ndarray:
    """Unit normals of planes with these tilts/azimuths (pose.slice_frame convention); shape (..., 3)."""
    t = np.radians(np.asarray(tilt_deg, dtype=float))
    a = np.radians(np.asarray(azimuth_deg, dtype=float))
    t, a = np.broadcast_arrays(t, a)
    return np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], axis=-1)


def _sample_params(tube, eps_mm: float = 1e-6) -> np.ndarray:
    """Parameters along a tube where plane crossings are bracketed (a hair beyond both ends)."""
    eps = eps_mm / max(tube.length_mm, 1e-9)
    if isinstance(tube, LineTube):
        return np.array([-eps, 1.0 + eps])
    n = max(9, int(math.ceil(tube.length_mm / 2.0)) + 1)
    return np.linspace(-eps, 1.0 + eps, n)


def crossing_counts(tube, origins, normals) -> np.ndarray:
    """How many times a tube centreline crosses each plane (origins, normals: (P, 3)); shape (P,)."""
    pts = tube.points(_sample_params(tube))
    g = np.asarray(normals, dtype=float) @ pts.T - np.einsum("pi,pi->p", origins, normals)[:, None]
    pos = g >= 0
    return (pos[:, 1:] != pos[:, :-1]).sum(axis=1)


def plane_crossings(tube, origins, normals, n_iter: int = 4):
    """Crossings of a tube centreline with many planes at once (vectorised ``intersect_plane``).

    ``origins``, ``normals``: shape (P, 3). The centreline is bracketed at
    samples (its two ends for a line, <= 2 mm apart otherwise) and each first
    bracket refined by Illinois regula falsi on ``tube.points``. Returns
    ``(t, points, tangents, count)``: shapes (P,), (P, 3), (P, 3), (P,); ``t``
    and the points are NaN where the plane misses the tube, ``count`` is the
    number of crossings.
    """
    o = np.asarray(origins, dtype=float)
    n = np.asarray(normals, dtype=float)
    ts = _sample_params(tube)
    pts = tube.points(ts)  # (K, 3)
    off = np.einsum("pi,pi->p", o, n)
    g = n @ pts.T - off[:, None]  # (P, K)
    pos = g >= 0
    change = pos[:, 1:] != pos[:, :-1]
    count = change.sum(axis=1)
    hit = count > 0
    k = np.argmax(change, axis=1)
    rows = np.arange(len(g))
    ta, tb = ts[k], ts[k + 1]
    ga, gb = g[rows, k], g[rows, k + 1]
    denom = np.where(gb != ga, gb - ga, 1.0)
    t = ta - ga * (tb - ta) / denom
    if not isinstance(tube, LineTube):
        side = np.zeros(len(t))  # +1: end a was replaced last time, -1: end b
        for _ in range(n_iter):
            gt = np.einsum("pi,pi->p", n, tube.points(t)) - off
            same = np.sign(gt) == np.sign(ga)  # t replaces end a
            # Illinois: halve the kept end's value when the same end is replaced twice in a row
            ga, gb = (np.where(same, gt, np.where(side == -1, 0.5 * ga, ga)),
                      np.where(same, np.where(side == 1, 0.5 * gb, gb), gt))
            ta, tb = np.where(same, t, ta), np.where(same, tb, t)
            side = np.where(same, 1.0, -1.0)
            denom = np.where(gb != ga, gb - ga, 1.0)
            t = np.clip(ta - ga * (tb - ta) / denom, np.minimum(ta, tb), np.maximum(ta, tb))
    t = np.where(hit, t, np.nan)
    safe = np.where(hit, t, 0.0)
    points = np.where(hit[:, None], tube.points(safe), np.nan)
    tangents = np.where(hit[:, None], tube.tangents(safe), np.nan)
    return t, points, tangents, count


# ----------------------------------------------------------------------------- tilt limits


def _pair_order(geom: FiducialGeometry) -> list[tuple[int, int]]:
    """All tube pairs, each ordered helix < orientation < diametric < other (``H0/D0``)."""
    idx = list(range(len(geom.tubes)))
    rank = sorted(idx, key=lambda i: (_ROLE_RANK.get(geom.tubes[i].role, 9), i))
    pos = {i: p for p, i in enumerate(rank)}
    pairs = []
    for i in idx:
        for j in idx:
            if i < j:
                pairs.append((i, j) if pos[i] < pos[j] else (j, i))
    return pairs


def _blob_gap(phi, dist, pi, qi, pj, qj, ai, aj, slice_mm):
    """Strip width between two blobs across the in-plane direction at angle ``phi`` from their centre line.

    Each blob is an ellipse (semi-minor a, semi-major a/cos(beta) along the
    tube's projection) plus a smear segment of slice*tan(beta) along it; its
    support along a unit in-plane e is ``a sqrt(1 + w^2) + slice/2 |w|`` with
    ``w = (e . t) / cos(beta)`` (p, q: w for e along / across the centre line).
    """
    c, s = np.cos(phi), np.sin(phi)
    wi = c * pi + s * qi
    wj = c * pj + s * qj
    hi = ai * np.sqrt(1 + wi**2) + 0.5 * slice_mm * np.abs(wi)
    hj = aj * np.sqrt(1 + wj**2) + 0.5 * slice_mm * np.abs(wj)
    return c * dist - hi - hj


def _max_blob_gap(dist, pi, qi, pj, qj, ai, aj, slice_mm, n_coarse: int = 61, n_golden: int = 14):
    """Distance between two convex blobs: the widest separating strip over all in-plane directions.

    Separating-axis theorem: max over e of (e . delta - h_i(e) - h_j(e)); < 0 when
    they overlap. Coarse sampling of the direction over +-90 deg from the
    centre line, then golden-section refinement around the best sample. Shapes (K,).
    """
    args = [a[:, None] for a in (dist, pi, qi, pj, qj, ai, aj)]
    phis = np.linspace(-np.pi / 2, np.pi / 2, n_coarse)
    vals = _blob_gap(phis[None, :], *args, slice_mm)
    vals = np.where(np.isnan(vals), -np.inf, vals)
    k = np.argmax(vals, axis=1)
    step = phis[1] - phis[0]
    lo, hi = phis[k] - step, phis[k] + step
    args = [a[:, 0] for a in args]
    r = (math.sqrt(5) - 1) / 2
    x1, x2 = hi - r * (hi - lo), lo + r * (hi - lo)
    f1, f2 = _blob_gap(x1, *args, slice_mm), _blob_gap(x2, *args, slice_mm)
    for _ in range(n_golden):
        left = f1 > f2  # the max lies in [lo, x2]
        hi = np.where(left, x2, hi)
        lo = np.where(left, lo, x1)
        x1n = np.where(left, hi - r * (hi - lo), x2)
        x2n = np.where(left, x1, lo + r * (hi - lo))
        f1n = np.where(left, _blob_gap(x1n, *args, slice_mm), f2)
        f2n = np.where(left, f1, _blob_gap(x2n, *args, slice_mm))
        x1, x2, f1, f2 = x1n, x2n, f1n, f2n
    best = np.maximum(np.maximum(f1, f2), vals.max(axis=1))
    return best


def _disc_union(tube, t_center, origins, normals, slice_mm, half_mm, n: int):
    """Disc-union samples of one tube's blob: centres (K, n, 3) in the plane, radii (K, n) (NaN = no disc).

    The tube is the union of balls of radius d/2 on its centreline; a ball at
    height h above the plane meets the slab |h| <= slice/2 in a set whose
    projection is the disc of radius sqrt((d/2)^2 - max(0, |h| - slice/2)^2).
    Centreline parameters: ``t_center`` (K,) +- ``half_mm`` (K,) of arc, clipped to [0, 1].
    """
    L = max(tube.length_mm, 1e-9)
    u = np.linspace(-1.0, 1.0, n)
    t = np.clip(t_center[:, None] + u[None, :] * (half_mm / L)[:, None], 0.0, 1.0)  # (K, n)
    p = tube.points(t.ravel()).reshape(t.shape + (3,))
    h = np.einsum("kni,ki->kn", p - origins[:, None, :], normals)
    c = p - h[..., None] * normals[:, None, :]
    r = tube.diameter / 2
    over = np.maximum(np.abs(h) - 0.5 * slice_mm, 0.0)
    with np.errstate(invalid="ignore"):
        rho = np.where(over < r, np.sqrt(np.maximum(r * r - over * over, 0.0)), np.nan)
    return t, c, rho


def _clipped_disc_distance(c1, r1, c2, r2, G, f1, f2):
    """Distance between discs clipped to a half-plane {f >= 0} (f: in-plane distance to the face line).

    c1, c2: centres (..., 3); r1, r2: radii; G: unit in-plane gradient of f
    (broadcastable to c1); f1, f2: f at the centres. Exact: the closest pair is
    either the two arc points on the centre line (when both lie in the
    half-plane), or involves a point on the face line (a chord). Where the
    clipped discs overlap, returns ``|c1 - c2| - r1 - r2`` (< 0, a depth);
    where either is empty, +inf.
    """
    dv = c2 - c1
    dist = np.linalg.norm(dv, axis=-1)
    e = dv / np.where(dist > 0, dist, 1.0)[..., None]
    eg = np.sum(e * G, axis=-1)
    plain = dist - r1 - r2
    valid_a = (f1 + r1 * eg >= -1e-12) & (f2 - r2 * eg >= -1e-12)
    # chords on the face line, in a coordinate tau along it
    T = np.cross(np.cross(G, e), G)  # any in-plane vector along the line would do; use G x (e x G)
    Tn = np.linalg.norm(T, axis=-1)
    T = np.where(Tn[..., None] > 1e-12, T / np.where(Tn > 1e-12, Tn, 1.0)[..., None], 0.0)
    tau1, tau2 = np.sum(c1 * T, axis=-1), np.sum(c2 * T, axis=-1)
    with np.errstate(invalid="ignore"):
        l1 = np.sqrt(np.maximum(r1 * r1 - f1 * f1, 0.0))
        l2 = np.sqrt(np.maximum(r2 * r2 - f2 * f2, 0.0))
    has1, has2 = np.abs(f1) <= r1, np.abs(f2) <= r2
    chord = np.maximum(np.maximum(tau2 - l2 - (tau1 + l1), tau1 - l1 - (tau2 + l2)), 0.0)

    def seg_to_clipped(tau_s, l_s, has_s, tau_o, f_o, r_o, has_o):
        dt = np.maximum(np.maximum(tau_s - l_s - tau_o, tau_o - (tau_s + l_s)), 0.0)
        val = np.where(f_o >= 0, np.hypot(dt, f_o) - r_o, np.where(has_o, chord, np.inf))
        return np.where(has_s, np.maximum(val, 0.0), np.inf)

    b = seg_to_clipped(tau1, l1, has1, tau2, f2, r2, has2)
    c = seg_to_clipped(tau2, l2, has2, tau1, f1, r1, has1)
    out = np.minimum(np.where(valid_a, plain, np.inf), np.minimum(b, c))
    # overlapping discs: does their lens reach the half-plane?
    with np.errstate(invalid="ignore", divide="ignore"):
        a = (dist * dist + r1 * r1 - r2 * r2) / (2 * np.where(dist > 0, dist, 1.0))
        hgt = np.sqrt(np.maximum(r1 * r1 - a * a, 0.0))
    eperp_g = np.sqrt(np.maximum(1.0 - eg * eg, 0.0))
    cross_ok = (dist > np.abs(r1 - r2)) & (f1 + a * eg + hgt * eperp_g >= 0)
    top1 = (np.linalg.norm(c1 + r1[..., None] * G - c2, axis=-1) <= r2) & (f1 + r1 >= 0)
    top2 = (np.linalg.norm(c2 + r2[..., None] * G - c1, axis=-1) <= r1) & (f2 + r2 >= 0)
    lens_in = (plain < 0) & (cross_ok | top1 | top2)
    out = np.where(lens_in, plain, np.where(plain < 0, np.minimum(b, c), out))
    empty = (f1 < -r1) | (f2 < -r2) | np.isnan(r1) | np.isnan(r2)
    return np.where(empty, np.inf, out)


def section_gap(tube_a, tube_b, origins, normals, slice_thickness_mm: float, body_length_mm: float | None = None,
                t_a=None, t_b=None, n_samples: int = 17, n_zoom: int = 5):
    """Exact in-image gap (mm) between the blobs of two tubes on planes (origins, normals: (K, 3)).

    Each blob is the projection onto the plane of the tube (the union of balls
    of radius d/2 along its centreline, within its extent) cut by the slab of
    thickness ``slice_thickness_mm``: a union of discs (see
    :func:`_disc_union`), clipped by the end face (z = 0 or
    ``body_length_mm``, the one nearer the crossings; None: no clipping). The
    distance between two such sets is the smallest distance between a disc of
    one and a disc of the other (:func:`_clipped_disc_distance`), found on an
    ``n_samples``^2 grid of centreline parameters around the crossings
    (``t_a``, ``t_b``: crossing parameters, computed if None), zoomed in
    ``n_zoom`` times. Negative = the blobs overlap (then only the sign is
    meaningful). Exact for helices, where the tangent-cylinder ellipse is
    not, and for blobs cut by an end face, with zero slice thickness; with a
    slab the face clip is the widest over the slab (the blobs can only be
    smaller, so the gap is conservative). Returns ``(gap, z_a, z_b)``: shape
    (K,) each, the gap and the z (mm) of the centreline points of the two closest discs.
    """
    o = np.asarray(origins, dtype=float).reshape(-1, 3)
    n = np.asarray(normals, dtype=float).reshape(-1, 3)
    if t_a is None:
        t_a = plane_crossings(tube_a, o, n)[0]
    if t_b is None:
        t_b = plane_crossings(tube_b, o, n)[0]
    t_a, t_b = np.asarray(t_a, dtype=float), np.asarray(t_b, dtype=float)
    K = len(o)
    gap = np.full(K, np.nan)
    za, zb = np.full(K, np.nan), np.full(K, np.nan)
    ok = np.isfinite(t_a) & np.isfinite(t_b)
    if not ok.any():
        return gap, za, zb
    o, n, ca, cb = o[ok], n[ok], t_a[ok], t_b[ok]
    S = float(slice_thickness_mm)
    halves = []
    for tube, tc in ((tube_a, ca), (tube_b, cb)):
        tg = tube.tangents(tc)
        cosb = np.abs(np.einsum("ki,ki->k", tg, n))
        reach = tube.diameter / 2 + 0.5 * S
        halves.append(np.minimum(1.05 * reach / np.maximum(cosb, 1e-3) + 0.1, tube.length_mm))
    ha, hb = halves
    # face half-plane f >= 0, f = sigma (x_z - z_face) / sin(tilt): in-plane distance to the face line
    sin_t = np.sqrt(np.maximum(1.0 - n[:, 2] ** 2, 0.0))
    zmid = 0.5 * (tube_a.points(ca)[:, 2] + tube_b.points(cb)[:, 2])
    clip = np.zeros(len(o), dtype=bool) if body_length_mm is None else sin_t > 1e-9
    L = 0.0 if body_length_mm is None else float(body_length_mm)
    sigma = np.where(zmid <= 0.5 * L, 1.0, -1.0)
    zface = np.where(sigma > 0, 0.0, L) - sigma * 0.5 * S * np.abs(n[:, 2])
    grad = np.array([0.0, 0.0, 1.0]) - n[:, 2:3] * n
    G = sigma[:, None] * grad / np.where(sin_t > 1e-9, sin_t, 1.0)[:, None]
    G = np.where(clip[:, None], G, 0.0)[:, None, None, :]
    rows = np.arange(len(o))
    for _ in range(n_zoom + 1):
        sa, pa, ra = _disc_union(tube_a, ca, o, n, S, ha, n_samples)
        sb, pb, rb = _disc_union(tube_b, cb, o, n, S, hb, n_samples)

        def f_of(p):
            return np.where(clip[:, None], sigma[:, None] * (p[..., 2] - zface[:, None])
                            / np.where(sin_t > 1e-9, sin_t, 1.0)[:, None], np.inf)

        fa, fb = f_of(pa), f_of(pb)
        fa, fb = np.where(np.isinf(fa), 1e9, fa), np.where(np.isinf(fb), 1e9, fb)
        d = _clipped_disc_distance(pa[:, :, None, :], ra[:, :, None], pb[:, None, :, :], rb[:, None, :],
                                   G, fa[:, :, None], fb[:, None, :])
        d = np.where(np.isnan(d), np.inf, d).reshape(len(o), -1)
        k = np.argmin(d, axis=1)
        i, j = np.divmod(k, n_samples)
        best = d[rows, k]
        ca, cb = sa[rows, i], sb[rows, j]
        step = 2.0 / (n_samples - 1)
        ha, hb = ha * 1.5 * step, hb * 1.5 * step
    gap[ok] = best
    za[ok] = tube_a.points(ca)[:, 2]
    zb[ok] = tube_b.points(cb)[:, 2]
    return gap, za, zb

class _PlaneChecker:
    """Evaluates the tilt constraints on many planes through the axis at once."""

    def __init__(self, geom: FiducialGeometry, pixel_size_mm: float, slice_thickness_mm: float,
                 merges: bool = True, exact: bool = True):
        self.geom = geom
        self.tubes = geom.tubes
        self.pixel = float(pixel_size_mm)
        self.slice = float(slice_thickness_mm)
        self.pairs = _pair_order(geom) if merges else []
        self.I = np.array([p[0] for p in self.pairs], dtype=int)
        self.J = np.array([p[1] for p in self.pairs], dtype=int)
        self.semi = np.array([t.diameter / 2 for t in self.tubes])
        self.curved = np.array([not isinstance(t, LineTube) for t in self.tubes])
        self.exact = exact
        n = len(self.tubes)
        self.labels = ["ok", OUTSIDE] + [f"tube_crosses_twice:{t.id}" for t in self.tubes] + [
            f"tubes_merge:{self.tubes[i].id}/{self.tubes[j].id}" for i, j in self.pairs
        ]
        self._merge0 = 2 + n

    def margins(self, depth_mm, tilt_deg, azimuth_deg):
        """Crossing counts (P, N) and merge margins (P, M) (mm; < 0 = merged) for planes (P,)."""
        z = np.asarray(depth_mm, dtype=float)
        normals = plane_normals(tilt_deg, azimuth_deg).reshape(-1, 3)
        origins = np.zeros_like(normals)
        origins[:, 2] = z
        P, N = len(normals), len(self.tubes)
        C = np.empty((P, N, 3))
        T = np.empty((P, N, 3))
        tpar = np.empty((P, N))
        cnt = np.empty((P, N), dtype=int)
        if len(self.pairs) == 0:  # visibility only: crossing counts suffice
            for k, tube in enumerate(self.tubes):
                cnt[:, k] = crossing_counts(tube, origins, normals)
            return cnt, np.zeros((P, 0))
        for k, tube in enumerate(self.tubes):
            tpar[:, k], C[:, k], T[:, k], cnt[:, k] = plane_crossings(tube, origins, normals)
        d = C[:, self.J] - C[:, self.I]  # (P, M, 3)
        dist = np.linalg.norm(d, axis=-1)
        e0 = d / np.where(dist > 0, dist, 1.0)[..., None]
        e1 = np.cross(normals[:, None, :], e0)  # in-plane, perpendicular to the centre line
        cosb = np.abs(np.einsum("pni,pi->pn", T, normals))  # (P, N) = cos(beta)
        with np.errstate(divide="ignore", invalid="ignore"):
            pi = np.einsum("pmi,pmi->pm", e0, T[:, self.I]) / cosb[:, self.I]
            qi = np.einsum("pmi,pmi->pm", e1, T[:, self.I]) / cosb[:, self.I]
            pj = np.einsum("pmi,pmi->pm", e0, T[:, self.J]) / cosb[:, self.J]
            qj = np.einsum("pmi,pmi->pm", e1, T[:, self.J]) / cosb[:, self.J]
        args = (dist, pi, qi, pj, qj, self.semi[self.I], self.semi[self.J])
        with np.errstate(invalid="ignore"):
            gap = _blob_gap(0.0, *args, self.slice)  # along the centre line: a lower bound
            rows, cols = np.nonzero((gap < self.pixel) & np.isfinite(gap))
            if rows.size:
                sub = [np.broadcast_to(a, gap.shape)[rows, cols] for a in args]
                gap[rows, cols] = _max_blob_gap(*sub, self.slice)
            if self.exact:
                self._exact_gaps(gap, origins, normals, C, cosb, tpar)
        margin = gap - self.pixel
        margin = np.where(np.isnan(dist), np.nan, np.where(np.isnan(margin), -np.inf, margin))
        return cnt, margin

    def _exact_gaps(self, gap, origins, normals, C, cosb, tpar, margin_mm: float = 0.1):
        """Replace, in place, the ellipse gaps (P, M) near or below one pixel by :func:`section_gap`.

        Only where the ellipse model is not exact: a pair with a helix, or a
        blob that may reach an end face (the face cuts it). The ellipse model
        is within a few hundredths of a mm of the truth or conservative, so
        pairs more than ``margin_mm`` above one pixel are left as they are.
        """
        L = self.geom.body.length
        with np.errstate(divide="ignore", invalid="ignore"):
            reach = (self.semi[None, :] + 0.5 * self.slice) / np.maximum(cosb, 1e-3) + 0.5 * self.slice
        near_face = (np.minimum(C[..., 2], L - C[..., 2]) < reach)  # (P, N)
        special = self.curved[self.I][None, :] | self.curved[self.J][None, :] | near_face[:, self.I] | near_face[:, self.J]
        rows, cols = np.nonzero(special & (gap < self.pixel + margin_mm) & np.isfinite(gap))
        for m in np.unique(cols):
            r = rows[cols == m]
            i, j = self.I[m], self.J[m]
            gap[r, m] = section_gap(self.tubes[i], self.tubes[j], origins[r], normals[r], self.slice,
                                    L, tpar[r, i], tpar[r, j])[0]

    def codes(self, depth_mm, tilt_deg, azimuth_deg, chunk: int = 20000) -> np.ndarray:
        """Label index (into ``self.labels``) of the failing constraint per plane; 0 = all pass."""
        z, t, a = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (depth_mm, tilt_deg, azimuth_deg)))
        z, t, a = z.ravel(), t.ravel(), a.ravel()
        out = np.zeros(z.size, dtype=int)
        for s in range(0, z.size, chunk):
            cnt, margin = self.margins(z[s:s + chunk], t[s:s + chunk], a[s:s + chunk])
            code = np.zeros(len(cnt), dtype=int)
            m = np.where(np.isnan(margin), np.inf, margin)
            if m.shape[1]:
                worst = np.argmin(m, axis=1)
                merged = m[np.arange(len(m)), worst] < 0
                code[merged] = self._merge0 + worst[merged]
            twice = cnt > 1
            code[twice.any(1)] = 2 + np.argmax(twice, axis=1)[twice.any(1)]
            code[(cnt == 0).any(1)] = 1
            out[s:s + chunk] = code
        return out


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
    r_in, r_out, length = body.inner_diameter / 2, body.outer_diameter / 2, body.length
    for i, j in _pair_order(geom):
        a, b = geom.tubes[i], geom.tubes[j]
        gap, z, inter, thin = _pair_gap(a, b, min_wall_mm, spacing_mm)
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
        rho = np.hypot(p[:, 0], p[:, 1])
        for name, gaps in (("bore", rho - r_in - r), ("outside", r_out - rho - r)):
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
    for sym in syms:
        a, b = sym.depth_range_mm
        violations.append(Finding("symmetric_pattern", f"the tilt-0 marker pattern maps onto itself under a "
                                  f"{sym.describe()} (worst marker off by {sym.mismatch_mm:.2f} mm at z = "
                                  f"{sym.at_depth_mm:.2f} mm; tolerance {tol:.2f} mm): twist/depth are "
                                  "ambiguous; move the orientation tubes so that no tube is equally far "
                                  "from its two neighbours", f"z {a:.2f}-{b:.2f} mm"))
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
    from .layout import fiducial_geometry
    from .printability import build_violations

    geom = fiducial_geometry(spec)
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
