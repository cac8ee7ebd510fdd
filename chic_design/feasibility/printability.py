"""Whether a design prints: channel walls, overhangs, and the rules ``build`` refuses even with ``--force``.

Items 3 and 4 of :mod:`chic_design.feasibility.engine`: :func:`channel_clearances` (the
walls between channels and from each channel to the bore, the outside and the
end faces, against ``print.min_wall``) and :func:`channel_overhangs` (the
steepest angle of each channel from the build direction, against
``print.max_overhang_deg``).

``chic-design check`` and ``chic-design build`` must agree: a design that
``check`` calls feasible always builds. ``check``
(:meth:`chic_design.families.base.Family.check`) adds the findings of
:func:`build_violations` to its violations, and
``build`` refuses every one of them even with ``--force`` (each makes the
build fail or its output useless):

- ``caps_meet``: the two caps' skirts would reach each other along the body
  (``2 * caps.skirt_height >= body.length``);
- ``cap_wall_too_thin``: the cap plate (``caps.thickness``) or the skirt
  (``caps.skirt_wall``) is thinner than ``print.min_wall``, the same rule as
  the body's walls;
- ``no_clear_section``: no height of the body where every channel is at least
  :data:`~chic_design.feasibility.sections.SECTION_MARGIN_MM` from the others and from the
  walls, so the build's own section check of ``body.stl`` cannot run;
- ``depth_imprecise``: the helices turn so little that the expected depth
  precision (the feasibility report's centroid-quantisation bound, at the
  protocol's pixel or :data:`IDEAL_PIXEL_MM` for an ideal one) is worse than
  :data:`MAX_DEPTH_SIGMA_MM`: such a design "registers" with a useless depth.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from chic_design.feasibility.contacts import channel_contacts
from chic_design.feasibility.depth_precision import depth_sensitivity
from chic_design.feasibility.records import Clearance, Finding, Overhang
from chic_design.feasibility.runs import true_runs
from chic_design.feasibility.sections import SECTION_MARGIN_MM, section_heights
from chic_register.model.envelope import pair_order
from chic_register.model.geometry import FiducialGeometry

#: Worst acceptable 1-sigma depth precision (mm) from the quantisation bound; the repository's designs
#: reach 0.27 (neuro) and 0.32 (needle guide). Noise and tilt only make it worse.
MAX_DEPTH_SIGMA_MM = 1.0
#: Pixel size (mm) at which an "ideal" protocol (pixel_size 0) is judged: the paper's 0.5 mm.
IDEAL_PIXEL_MM = 0.5
#: The codes of :func:`build_violations`: ``build`` refuses them even with ``--force``.
HARD_CODES = frozenset({"caps_meet", "cap_wall_too_thin", "no_clear_section", "depth_imprecise"})
_WALL_TOL_MM = 1e-6


def build_violations(spec, geom: FiducialGeometry, pixel_size_mm: float, length_key: str) -> list[Finding]:
    """Findings that would make ``build`` fail or its output useless.

    ``spec`` is any family's spec (its ``caps`` and ``print`` are read);
    ``length_key`` names the spec key of the body length in messages.
    """
    out = []
    caps, wall, length = spec.caps, spec.print.min_wall, geom.body.length
    if 2 * caps.skirt_height >= length:
        out.append(Finding("caps_meet", f"caps.skirt_height ({caps.skirt_height:g} mm) must be less than half "
                           f"of {length_key} ({length:g} mm): the two caps' skirts would meet",
                           "caps.skirt_height"))
    for key, value in (("thickness", caps.thickness), ("skirt_wall", caps.skirt_wall)):
        if value < wall:
            out.append(Finding("cap_wall_too_thin", f"caps.{key} ({value:g} mm) is thinner than print.min_wall "
                               f"({wall:g} mm)", f"caps.{key}"))
    if section_heights(geom).size == 0:
        out.append(Finding("no_clear_section", "no height of the body where every channel is at least "
                           f"{SECTION_MARGIN_MM:g} mm from the others and from the bore and outside: the "
                           "build's section check of body.stl cannot run; widen the wall or thin the channels",
                           "all depths"))
    pixel = pixel_size_mm if pixel_size_mm > 0 else IDEAL_PIXEL_MM
    sigma = depth_sensitivity(geom, pixel).combined_sigma_z_mm
    if sigma is not None and sigma > MAX_DEPTH_SIGMA_MM:
        out.append(Finding("depth_imprecise", f"the helices turn too little: expected depth precision "
                           f"{sigma:.3g} mm at {pixel:g} mm pixels (allowed at most {MAX_DEPTH_SIGMA_MM:g} mm); "
                           "lower helix.offset_deg or raise |helix.pitch_deg_per_mm|", "helix"))
    return out


def _samples(tube, spacing_mm: float):
    """Centreline parameters, points (N, 3) and unit tangents (N, 3) at <= ``spacing_mm``."""
    n = max(2, int(math.ceil(tube.length_mm / spacing_mm)) + 1)
    t = np.linspace(0.0, 1.0, n)
    return t, tube.points(t), tube.tangents(t)


def _pair_gap(ta, tb, min_wall_mm: float, spacing_mm: float):
    """Surface gap between two channels: min (refined), z there, intersect / thin z-ranges on ``ta``."""
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
    inter = true_runs(zs[order], (gap < 0)[order])
    thin = true_runs(zs[order], ((gap >= 0) & (gap < min_wall_mm - _WALL_TOL_MM))[order])
    return best, float(at[2]), inter, thin


def _fmt_ranges(ranges) -> str:
    return ", ".join(f"{a:.1f}-{b:.1f}" for a, b in ranges)


def channel_clearances(geom: FiducialGeometry, min_wall_mm: float, spacing_mm: float = 0.1):
    """Clearances channel-channel and channel-body (see :mod:`chic_design.feasibility.engine`, item 3).

    Returns ``(clearances, violations, warnings)``.
    """
    out: list[Clearance] = []
    viol: list[Finding] = []
    warn: list[Finding] = []
    body = geom.body
    length = body.length
    # z-ranges where two channels touch: the one answer (contacts), also used by the report
    touch = {frozenset((c.a, c.b)): c.z_ranges_mm for c in channel_contacts(geom)}
    for i, j in pair_order(geom):
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
