"""The CHIC design space: a candidate's parameters, their ranges, and the spec they make.

Parameters are integers on printable grids (0.5 mm outer diameter, 0.1 mm
channel, 1 mm length, 1 deg angles) so equal designs have equal keys in the
result store, plus a few categorical choices. The ranges are fixed for a
requirements file, which keeps the search space static (what NSGA-II
needs). The four diametric tubes stay at 0/90/180/270 deg.

========================  =====================================================
``od_halfmm``             body outer diameter in 0.5 mm steps
``length_mm``             body length
``channel_tenthmm``       channel diameter in 0.1 mm steps
``circle_pos``            channel circle between its innermost and outermost
                          printable place, 0..20 (10 = middle of that span)
``offset_deg``            helix offset from its quadrant's diametric tube
``direction``             helix turning sense (+1 counter-clockwise going up)
``free_quadrant``         the quadrant without a helix (holds the orientation tubes)
``n_orientation``         1 or 2 orientation tubes
``orient_a_deg``,         orientation tubes' angles from the free quadrant's start
``orient_b_deg``          (b only with two tubes)
========================  =====================================================
"""

from __future__ import annotations

import hashlib
import json
import math

from chic_design.optimize.requirements import Requirements

CIRCLE_STEPS = 20
OFFSET_RANGE_DEG = (2, 30)
ORIENT_RANGE_DEG = (5, 85)
PARAM_ORDER = ("od_halfmm", "length_mm", "channel_tenthmm", "circle_pos", "offset_deg", "direction",
               "free_quadrant", "n_orientation", "orient_a_deg", "orient_b_deg")


def int_ranges(req: Requirements) -> dict[str, tuple[int, int]]:
    """Inclusive integer ranges of the numeric parameters for these requirements."""
    od_lo, od_hi = req.body_od_range_mm
    l_lo, l_hi = req.length_range_mm
    p = req.printer
    return {
        "od_halfmm": (math.ceil(od_lo * 2 - 1e-9), math.floor(od_hi * 2 + 1e-9)),
        "length_mm": (math.ceil(l_lo - 1e-9), math.floor(l_hi + 1e-9)),
        "channel_tenthmm": (math.ceil(p.min_channel_diameter * 10 - 1e-9),
                            math.floor(p.max_channel_diameter * 10 + 1e-9)),
        "circle_pos": (0, CIRCLE_STEPS),
        "offset_deg": OFFSET_RANGE_DEG,
        "orient_a_deg": ORIENT_RANGE_DEG,
        "orient_b_deg": ORIENT_RANGE_DEG,
    }


CHOICES = {"direction": (1, -1), "free_quadrant": (3, 0, 1, 2), "n_orientation": (2, 1)}


def suggest(trial, req: Requirements) -> dict:
    """Ask an Optuna trial for one candidate's parameters (always all of them, in a fixed order)."""
    ranges = int_ranges(req)
    out = {}
    for name in PARAM_ORDER:
        if name in CHOICES:
            out[name] = trial.suggest_categorical(name, CHOICES[name])
        else:
            out[name] = trial.suggest_int(name, *ranges[name])
    return out


def canonical(params: dict) -> dict:
    """The parameters that define the design (an unused second orientation angle is dropped)."""
    out = {k: int(params[k]) for k in PARAM_ORDER}
    if out["n_orientation"] == 1:
        out["orient_b_deg"] = 0
    return out


def candidate_key(params: dict, req: Requirements, version: str) -> str:
    """Store key: SHA-256 of the canonical parameters, the scoring requirements and the scorer version."""
    doc = {"params": canonical(params), "requirements": req.scoring_dict(), "scorer": version}
    return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


def circle_span_mm(req: Requirements, od_mm: float, channel_mm: float) -> tuple[float, float]:
    """Innermost and outermost channel-circle diameter that leave ``min_wall`` to bore and outside."""
    w = req.printer.min_wall
    return req.tool.bore_mm + channel_mm + 2 * w, od_mm - channel_mm - 2 * w


def wall_deficit_mm(params: dict, req: Requirements) -> float:
    """How much wider the body must be for the channels to fit with ``min_wall`` both sides (0 = fits)."""
    p = canonical(params)
    lo, hi = circle_span_mm(req, p["od_halfmm"] / 2, p["channel_tenthmm"] / 10)
    return max(0.0, lo - hi)


def spec_dict(params: dict, req: Requirements, name: str) -> dict:
    """The design spec (as a YAML-ready mapping) of a candidate; validated by ``chic_design.spec``."""
    p = canonical(params)
    od = p["od_halfmm"] / 2
    length = float(p["length_mm"])
    d = p["channel_tenthmm"] / 10
    lo, hi = circle_span_mm(req, od, d)
    circle = round(lo + (hi - lo) * p["circle_pos"] / CIRCLE_STEPS, 3)
    free = p["free_quadrant"]
    quadrants = sorted({0, 1, 2, 3} - {free})
    start = 90.0 * free
    angles = sorted([p["orient_a_deg"]] + ([p["orient_b_deg"]] if p["n_orientation"] == 2 else []))
    orientation = [float((start + a) % 360) for a in angles]
    helix: dict = {"offset_deg": float(p["offset_deg"])}
    if p["direction"] < 0:
        helix["pitch_deg_per_mm"] = -round((90.0 - 2 * p["offset_deg"]) / length, 9)
    c = req.caps
    return {
        "name": name,
        "description": f"found by chic-design optimize for requirements '{req.name}'",
        "body": {"length": length, "outer_diameter": od, "inner_diameter": req.tool.bore_mm},
        "channels": {"diameter": d, "circle_diameter": circle},
        "helix": helix,
        "markers": {"diametric_deg": [0.0, 90.0, 180.0, 270.0], "helix_quadrants": quadrants,
                    "orientation_deg": orientation},
        "caps": {"thickness": c.thickness, "clearance": c.clearance, "skirt_height": c.skirt_height,
                 "skirt_wall": c.skirt_wall, "fill_port_diameter": round(min(1.2, 0.6 * d), 2)},
        "print": {"min_wall": req.printer.min_wall, "max_overhang_deg": req.printer.max_overhang_deg},
        "imaging": {"pixel_size": req.imaging.pixel_size, "slice_thickness": req.imaging.slice_thickness},
    }


#: One-step moves around a start design (the first generation's seeds): parameter, step.
NEIGHBOUR_STEPS = (("orient_a_deg", 5), ("orient_b_deg", 5), ("channel_tenthmm", 2), ("circle_pos", 3),
                   ("offset_deg", 1), ("length_mm", 2), ("od_halfmm", 1))


def neighbours(params: dict, req: Requirements) -> list[dict]:
    """The start design moved one step up and one step down along each of :data:`NEIGHBOUR_STEPS`.

    Seeding the first generation with these lets NSGA-II's crossover work
    near a known good design (its own mutation resamples a parameter anywhere
    in its range, so it rarely makes small moves). Out-of-range moves are dropped.
    """
    ranges = int_ranges(req)
    out = []
    for name, step in NEIGHBOUR_STEPS:
        for sign in (-1, 1):
            p = dict(params)
            p[name] = params[name] + sign * step
            lo, hi = ranges[name]
            if lo <= p[name] <= hi and canonical(p) != canonical(params):
                out.append(p)
    return out


def default_start(req: Requirements) -> dict:
    """Where the search starts without a baseline: the roomiest body with the shipped marker layout.

    Largest allowed outer diameter and length, narrowest printable channel on
    a circle three quarters of the way out (more room between the tubes),
    and the layout of ``designs/needle-guide.yaml``: helix offset 15 deg,
    orientation tubes 24 and 60 deg into the free quadrant 3.
    """
    r = int_ranges(req)
    return {"od_halfmm": r["od_halfmm"][1], "length_mm": r["length_mm"][1],
            "channel_tenthmm": r["channel_tenthmm"][0], "circle_pos": (3 * CIRCLE_STEPS) // 4,
            "offset_deg": 15, "direction": 1, "free_quadrant": 3, "n_orientation": 2,
            "orient_a_deg": 24, "orient_b_deg": 60}


def params_from_spec(spec, req: Requirements) -> dict | None:
    """The candidate parameters that reproduce ``spec``'s design, or None if it is outside the space.

    Used to start the search from a baseline design (``search.baseline``).
    """
    m = spec.markers
    if tuple(m.diametric_deg) != (0.0, 90.0, 180.0, 270.0) or len(m.orientation_deg) > 2:
        return None
    if abs(spec.body.inner_diameter - req.tool.bore_mm) > 1e-9 or spec.helix.offset_top_deg is not None:
        return None
    free = m.free_quadrant
    rel = sorted(round((a - 90.0 * free) % 360) for a in m.orientation_deg)
    d = spec.channels.diameter
    lo, hi = circle_span_mm(req, spec.body.outer_diameter, d)
    pos = CIRCLE_STEPS * (2 * spec.channel_radius - lo) / (hi - lo) if hi > lo else -1
    direction = -1 if (spec.helix.pitch_deg_per_mm or 1) < 0 else 1
    params = {
        "od_halfmm": round(spec.body.outer_diameter * 2), "length_mm": round(spec.body.length),
        "channel_tenthmm": round(d * 10), "circle_pos": round(pos), "offset_deg": round(spec.helix.offset_deg),
        "direction": direction, "free_quadrant": free, "n_orientation": len(rel),
        "orient_a_deg": rel[0], "orient_b_deg": rel[-1] if len(rel) == 2 else ORIENT_RANGE_DEG[0],
    }
    ranges = int_ranges(req)
    if any(not lo_ <= params[k] <= hi_ for k, (lo_, hi_) in ranges.items()):
        return None
    return params
