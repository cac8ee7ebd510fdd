"""Score one candidate: feasibility first (tilt limits, printability, unambiguity), then precision.

A candidate is *feasible* when its spec validates, the feasibility check
(:func:`chic_design.feasibility.engine.check_geometry`, for the required protocol and
printer, plus what ``build`` refuses, :func:`chic_design.feasibility.printability.build_violations`)
finds no violation, its assembled outer diameter is within the limit,
every depth sample in the required range registers at the required
maximum tilt, and the solver will trust its poses there: the precision bound
times the solver's measured conservatism (:mod:`.trust`) predicts a 3-sigma
error within ``SolveOptions``' trust limits at every required pose (else
``register`` would refuse the slices as too imprecise). Only candidates
passing the first checks get the precision bound; only feasible ones reach
the output. The three objectives:

- ``outer_diameter_mm`` (minimise): the body's outer diameter (the assembly is
  wider by the cap allowance, the same for every candidate);
- ``usable_region_deg_mm`` (maximise): the area under the max-tilt-vs-depth
  curve (deg x mm), trapezoidal over the 1 mm depth samples;
- ``tre_mm`` (minimise): the worst predicted target registration error over
  the required poses (:mod:`.precision`).

Results are plain JSON-ready dicts so they can be stored and sent between
processes; :data:`SCORER_VERSION` is part of the store key.
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from chic_design.errors import SpecError
from chic_design.families import family_of
from chic_design.families.chic.spec import ChicSpec
from chic_design.feasibility.engine import check_geometry
from chic_design.feasibility.printability import build_violations
from chic_design.optimize import space
from chic_design.optimize.precision import predicted_precision
from chic_design.optimize.requirements import Requirements
from chic_design.optimize.trust import solver_limits, trust_excess, trust_reason
from chic_design.spec import parse_spec

SCORER_VERSION = "4"
OBJECTIVES = ("outer_diameter_mm", "usable_region_deg_mm", "tre_mm")
DIRECTIONS = ("minimize", "maximize", "minimize")
N_CONSTRAINTS = 5


def usable_region(report) -> float:
    """Area (deg x mm) under max tilt vs depth, counting depths unusable at tilt 0 as 0."""
    z = np.array([t.depth_mm for t in report.tilt_limits])
    tilt = np.array([t.max_tilt_deg if t.usable_at_zero_tilt else 0.0 for t in report.tilt_limits])
    return float(np.sum(0.5 * (tilt[1:] + tilt[:-1]) * np.diff(z)))


def required_shortfall_deg(report, req: Requirements) -> float:
    """How many degrees the worst required depth falls short of the required tilt (0 = meets it)."""
    d0, d1 = req.required.depth_mm
    need = req.required.tilt_deg[1]
    if d1 > report.body_length_mm:
        return need + 10.0 * (d1 - report.body_length_mm)
    inside = [t for t in report.tilt_limits if d0 - 1e-9 <= t.depth_mm <= d1 + 1e-9]
    worst = min((t.max_tilt_deg if t.usable_at_zero_tilt else -1.0) for t in inside)
    return max(0.0, need - worst)


def _infeasible(reasons, constraints, spec_data, t0) -> dict:
    return {"feasible": False, "reasons": list(reasons), "constraints": [float(c) for c in constraints],
            "objectives": None, "precision": None, "spec": spec_data, "cpu_s": time.process_time() - t0}


def score_spec(spec: ChicSpec, req: Requirements, spec_data: dict | None = None) -> dict:
    """Score a validated spec against the requirements (see module docstring)."""
    t0 = time.process_time()
    family = family_of(spec)
    geom = family.geometry(spec)
    report = check_geometry(geom, family, pixel_size_mm=req.imaging.pixel_size,
                            slice_thickness_mm=req.imaging.slice_thickness,
                            min_wall_mm=req.printer.min_wall, max_overhang_deg=req.printer.max_overhang_deg)
    hard = build_violations(spec, geom, req.imaging.pixel_size, family.length_key)  # what build refuses
    report = replace(report, violations=report.violations + tuple(hard))
    reasons = [f"{v.code} ({v.where})" for v in report.violations]
    envelope = spec.body.outer_diameter + 2 * (spec.caps.clearance + spec.caps.skirt_wall)
    over = max(0.0, envelope - req.limits.max_outer_diameter)
    if over > 1e-9:
        reasons.append(f"assembly {envelope:g} mm wide > limits.max_outer_diameter")
    short = required_shortfall_deg(report, req)
    if short > 0:
        reasons.append(f"required depths reach only {req.required.tilt_deg[1] - short:.1f} of "
                       f"{req.required.tilt_deg[1]:g} deg tilt")
    if spec.channels.diameter < req.printer.min_channel_diameter - 1e-9:
        reasons.append("channel narrower than printer.min_channel_diameter")
    constraints = [0.0, float(len(report.violations)), short / 10.0, over, 0.0]
    if reasons:
        return _infeasible(reasons, constraints, spec_data, t0)
    prec = predicted_precision(geom, req)
    if not np.isfinite(prec["tre_mm"]):
        return _infeasible(["precision bound is infinite (pose not determined)"], [0, 1, 0, 0, 0], spec_data, t0)
    limits = solver_limits()
    refused = trust_reason(prec, limits)
    if refused is not None:  # graded by how far the worse of the two errors is over its limit
        out = _infeasible([refused], [0, 0, 0, 0, trust_excess(prec, limits)], spec_data, t0)
        return {**out, "precision": prec, "outer_diameter_mm": float(spec.body.outer_diameter)}
    objectives = {"outer_diameter_mm": float(spec.body.outer_diameter),
                  "usable_region_deg_mm": usable_region(report), "tre_mm": prec["tre_mm"]}
    usable = {f"{u.tilt_deg:g}": u.total_mm for u in report.usable_depth}
    return {"feasible": True, "reasons": [], "constraints": constraints, "objectives": objectives,
            "precision": prec, "usable_depth_mm": usable, "length_mm": float(spec.body.length),
            "envelope_od_mm": float(envelope), "min_mismatch_mm": report.unambiguity.min_mismatch_mm,
            "warnings": len(report.warnings), "spec": spec_data, "cpu_s": time.process_time() - t0}


def evaluate_candidate(params: dict, req_data: dict) -> dict:
    """Score one candidate from its parameters (a top-level function: it runs in worker processes)."""
    t0 = time.process_time()
    req = Requirements.model_validate(req_data)
    data = space.spec_dict(params, req, name=f"{req.name}-candidate")
    try:
        spec = parse_spec(data, "<candidate>")
    except SpecError as exc:
        # graded, so the optimiser learns which way the wall is too thin for the channels
        c0 = 1.0 + space.wall_deficit_mm(params, req)
        return _infeasible([str(exc).removeprefix("<candidate>: ")], [c0, 0.0, 0.0, 0.0, 0.0], data, t0)
    out = score_spec(spec, req, data)
    out["cpu_s"] = time.process_time() - t0
    return out


def dominates(a: dict, b: dict, tol: float = 1e-9) -> bool:
    """True if objectives ``a`` are at least as good as ``b`` everywhere and better somewhere."""
    ge, gt = True, False
    for name, direction in zip(OBJECTIVES, DIRECTIONS):
        da, db = (a[name], b[name]) if direction == "maximize" else (-a[name], -b[name])
        if da < db - tol:
            ge = False
        elif da > db + tol:
            gt = True
    return ge and gt


def pareto_front(results: list[dict]) -> list[dict]:
    """Feasible results no other feasible result dominates (first of equal objectives kept)."""
    ok = [r for r in results if r["feasible"]]
    front, seen = [], set()
    for r in ok:
        objs = tuple(r["objectives"][k] for k in OBJECTIVES)
        if objs in seen or any(dominates(o["objectives"], r["objectives"]) for o in ok):
            continue
        seen.add(objs)
        front.append(r)
    return front
