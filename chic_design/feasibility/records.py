"""The results of ``chic-design check``: findings, per-check records and the whole report.

Plain frozen dataclasses with their JSON (``to_dict``), the terminal summary and
the report.md section: what the checks of :mod:`chic_design.feasibility` return
(the checks themselves live in :mod:`~chic_design.feasibility.tilt_search`,
:mod:`~chic_design.feasibility.printability`, :mod:`~chic_design.feasibility.unambiguity`
and :mod:`~chic_design.feasibility.depth_precision`). This module imports no check, so
every check can import its result type from here.
"""

from __future__ import annotations

from dataclasses import dataclass


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
    planes z = const overlap: :func:`chic_design.feasibility.contacts.channel_contacts`, the
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
    frame_symmetries: tuple | None = None  # 3-D symmetries, where a family checks them (chic_register.model.symmetry)
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
    """Depth per degree of helix angle, and the expected depth precision (item 6 of :mod:`chic_design.feasibility.engine`)."""

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
    """Everything ``check`` found (:func:`~chic_design.feasibility.engine.check_geometry`). ``feasible`` = no violations.

    ``usable_note``: what "usable" means for the fiducial's family, a line of the summary ("" for none).
    """

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
    usable_note: str = ""

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
        if self.usable_note:
            lines.append(self.usable_note)
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
