"""The optimiser's written outputs: Pareto table (CSV + markdown), spec YAMLs, and report.md."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import yaml

from chic_design.optimize.choose import LABELS, compare
from chic_design.optimize.score import OBJECTIVES
from chic_design.optimize.trust import SOLVER_OVER_CRLB, trust_excess
from chic_design.spec import parse_spec
from chic_register.util.atomic import write_text

TABLE_COLUMNS = ("name", "outer_diameter_mm", "envelope_od_mm", "length_mm", "usable_region_deg_mm",
                 "usable_15deg_mm", "tre_mm", "sd_depth_mm", "sd_normal_deg", "sd_twist_deg", "solver_rot_deg",
                 "solver_tre_mm",
                 "channel_mm", "circle_mm", "offset_deg", "direction", "orientation_deg", "key")


def table_row(name: str, r: dict) -> dict:
    s, p, o = r["spec"], r["precision"], r["objectives"]
    return {"name": name, "outer_diameter_mm": o["outer_diameter_mm"], "envelope_od_mm": r["envelope_od_mm"],
            "length_mm": r["length_mm"], "usable_region_deg_mm": round(o["usable_region_deg_mm"], 1),
            "usable_15deg_mm": round(r["usable_depth_mm"].get("15", 0.0), 1), "tre_mm": round(o["tre_mm"], 4),
            "sd_depth_mm": round(p["sd_depth_mm"], 4), "sd_normal_deg": round(p["sd_normal_deg"], 4),
            "sd_twist_deg": round(p["sd_twist_deg"], 4), "solver_rot_deg": round(p["solver_rot_deg"], 3),
            "solver_tre_mm": round(p["solver_tre_mm"], 3), "channel_mm": s["channels"]["diameter"],
            "circle_mm": s["channels"]["circle_diameter"], "offset_deg": s["helix"]["offset_deg"],
            "direction": "cw" if "pitch_deg_per_mm" in s["helix"] else "ccw",
            "orientation_deg": " ".join(f"{a:g}" for a in s["markers"]["orientation_deg"]),
            "key": r.get("key", "")[:12]}


def write_csv(rows: list[dict], path) -> Path:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=TABLE_COLUMNS, lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    return write_text(path, buf.getvalue())


def markdown_table(rows: list[dict], columns=TABLE_COLUMNS[:-1]) -> str:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for r in rows:
        lines.append("| " + " | ".join("" if r[c] is None else f"{r[c]}" for c in columns) + " |")
    return "\n".join(lines)


def write_spec(spec_data: dict, path) -> Path:
    """Write a design spec YAML after validating it (a spec that would not build is never written)."""
    parse_spec(spec_data, path)
    header = "# Written by chic-design optimize; build with: chic-design build " + Path(path).name + "\n"
    return write_text(path, header + yaml.safe_dump(spec_data, sort_keys=False))


def _cmp_lines(cmp: list[dict], a_name: str, b_name: str) -> list[str]:
    out = [f"| objective | {a_name} | {b_name} | difference | |", "|---|---|---|---|---|"]
    for c in cmp:
        rel = f" ({100 * c['rel']:+.1f} %)" if c["rel"] == c["rel"] else ""
        out.append(f"| {c['label']} ({c['unit']}) | {c['a']:.4g} | {c['b']:.4g} | {c['diff']:+.4g}{rel} | "
                   f"{c['verdict']} |")
    return out


def confirm_lines(named: list[tuple[str, dict]], confirmed: dict) -> list[str]:
    out = ["| design | slices | no-lock | depth RMS / max (mm) | predicted depth SD (mm) | "
           "normal RMS / max (deg) | predicted normal SD (deg) | twist RMS / max (deg) | "
           "predicted twist SD (deg) | confirmed |", "|---|---|---|---|---|---|---|---|---|---|"]
    f = lambda v: "-" if v is None else f"{v:.3f}"  # noqa: E731
    for name, r in named:
        c = confirmed.get(name)
        if c is None:
            continue
        p = r["precision"]
        out.append(f"| {name} | {c['slices']} | {c['no_lock']} | {f(c['depth_rms_mm'])} / {f(c['depth_max_mm'])} | "
                   f"{f(p['sd_depth_mm'])} | {f(c['normal_rms_deg'])} / {f(c['normal_max_deg'])} | "
                   f"{f(p['sd_normal_deg'])} | {f(c['twist_rms_deg'])} / {f(c['twist_max_deg'])} | "
                   f"{f(p['sd_twist_deg'])} | {confirmed_verdict(c)} |")
    for name, _ in named:
        c = confirmed.get(name)
        if c and c["no_lock"] and c.get("refusals"):
            why = "; ".join(f"{k} x{v}" for k, v in sorted(c["refusals"].items(), key=lambda kv: -kv[1])[:3])
            cases = ", ".join(f"{k} {v}" for k, v in c.get("locked_by_case", {}).items())
            out.append(f"\n`{name}` refused: {why}. Locked per pose (of {c['settings']['draws']}): {cases}.")
    return out


#: Largest share of simulated slices the solver may refuse for a design to count as confirmed.
MAX_NO_LOCK_SHARE = 0.1


def confirmed_verdict(c: dict) -> str:
    """'yes' when the solver locked at least 90 % of the simulated series, else 'NO' with the share refused."""
    share = c["no_lock"] / c["slices"] if c["slices"] else 1.0
    if share <= MAX_NO_LOCK_SHARE:
        return "yes"
    why = f" ({c['imprecise']} as too imprecise)" if c.get("imprecise") else ""
    return f"NO: {c['no_lock']}/{c['slices']} refused{why}"


def trust_lines(candidates, limits) -> list[str]:
    """The candidates the solver-trust constraint alone made infeasible, nearest the limits first."""
    failed = [c for c in candidates if not c["feasible"] and c.get("precision") is not None]
    if not failed:
        return []
    failed.sort(key=lambda c: trust_excess(c["precision"], limits))
    out = [f"{len(failed)} candidates passed every other check but the bound (x {SOLVER_OVER_CRLB:g}, the solver's "
           f"measured conservatism) predicts the solver would refuse their slices ({limits.sigmas:g} sigma over "
           f"{limits.rot_deg:g} deg or {limits.tre_mm:g} mm at the frame centre); nearest the limits:", "",
           "| key | OD (mm) | predicted rotation (deg) | predicted centre TRE (mm) | over by | at depth, tilt |",
           "|---|---|---|---|---|---|"]
    for c in failed[:5]:
        p = c["precision"]
        z, t, _ = p["solver_worst_pose"]
        out.append(f"| {c.get('key', '')[:12]} | {c.get('outer_diameter_mm', float('nan')):g} | "
                   f"{p['solver_rot_deg']:.3f} | {p['solver_tre_mm']:.3f} | "
                   f"{100 * trust_excess(p, limits):.1f} % | {z:g} mm, {t:g} deg |")
    return out + [""]


def report_markdown(ctx: dict) -> str:
    """The decision report (``ctx`` is assembled by :func:`chic_design.optimize.pipeline.optimize`)."""
    req, search = ctx["req"], ctx["search"]
    chosen_name, chosen = ctx["named"][0]
    L = [f"# chic-design optimize: {req.name}", "", req.description, "",
         f"Requirements: `{ctx['req_path']}`. Bore {req.tool.bore_mm:g} mm; assembly OD <= "
         f"{req.limits.max_outer_diameter:g} mm; body length {req.length_range_mm[0]:g}-{req.length_range_mm[1]:g} mm; "
         f"pixel {req.imaging.pixel_size:g} mm, slice {req.imaging.slice_thickness:g} mm, SNR {req.imaging.snr:g}, "
         f"{req.imaging.n_slices} slice(s); must register at depths {req.required.depth_mm[0]:g}-"
         f"{req.required.depth_mm[1]:g} mm up to {req.required.tilt_deg[1]:g} deg tilt; target "
         f"{list(req.required.target_mm)} mm in F.", "",
         "## Search", "",
         f"{len(search.candidates)} candidates (NSGA-II, population {search.settings['population']}, seed "
         f"{search.settings['seed']}, Optuna {search.settings['optuna']}) on {search.engine} with {search.workers} "
         f"worker(s): {search.evaluated} evaluated, {search.cached} taken from the result store; "
         f"{search.feasible} feasible; {len(ctx['named'])} on the Pareto front. Wall {search.wall_s:.1f} s, "
         f"worker CPU {search.cpu_s:.1f} s.", "",
         f"Precision: {ctx['precision_method']}.", "",
         "Objectives: outer diameter of the body (min; the assembly adds "
         f"{req.cap_allowance_mm:g} mm of cap skirts), usable tilt x depth region = area under the max-tilt "
         "curve of `chic-design check` (max), predicted TRE at the target, worst over the required poses (min). "
         "A candidate is feasible only if `check` finds no violation, the assembly fits, every required "
         "depth works at the required tilt, and the solver will trust its poses (the bound times the "
         "solver's measured conservatism keeps its 3-sigma error within the trust limits at every required "
         "pose); infeasible candidates are never written.", "",
         *trust_lines(search.candidates, ctx["trust_limits"]),
         "![Pareto set](pareto.png)", "", "## Pareto set", "",
         "Specs in `specs/` (each validated; `chic-design build specs/<name>.yaml`). Ordered by distance to "
         "the ideal point (each objective scaled over the set): the first is chosen.", "",
         markdown_table(ctx["rows"]), ""]
    L += [f"## Chosen design: `{chosen_name}`", "",
          f"`specs/{chosen_name}.yaml`: OD {chosen['spec']['body']['outer_diameter']:g} mm, length "
          f"{chosen['length_mm']:g} mm, channels {chosen['spec']['channels']['diameter']:g} mm on "
          f"{chosen['spec']['channels']['circle_diameter']:g} mm, helix offset "
          f"{chosen['spec']['helix']['offset_deg']:g} deg, orientation tubes at "
          f"{chosen['spec']['markers']['orientation_deg']} deg.", "",
          ]
    if ctx.get("pictures"):
        L += ["![preview](chosen/preview.png)", "", "![tilt limits](chosen/tilt_limits.png)", "",
              "![precision map](chosen/precision_map.png)", ""]
    if len(ctx["named"]) > 1:
        ru_name, ru = ctx["named"][1]
        L += [f"### Why it beat the runner-up `{ru_name}`", "",
              f"Distance to the ideal point {ctx['distances'][0]:.3f} vs {ctx['distances'][1]:.3f} "
              "(0 = best on every objective at once). Objective by objective:", ""]
        cmp = compare(chosen, ru)
        L += _cmp_lines(cmp, chosen_name, ru_name)
        gains = [c["label"] for c in cmp if c["verdict"] == "better"]
        losses = [c["label"] for c in cmp if c["verdict"] == "worse"]
        L += ["", f"`{chosen_name}` is better on {', '.join(gains) or 'nothing'}"
              + (f" and worse on {', '.join(losses)}" if losses else "")
              + "; with each objective scaled over the Pareto set and weighted equally, "
              + ("its gains outweigh that loss." if losses else "it is better or equal everywhere."), ""]
    if ctx.get("baseline") is not None:
        b = ctx["baseline"]
        L += [f"## Against the baseline `{ctx['baseline_path']}`", ""]
        if not b["feasible"]:
            L += [f"The baseline does not meet these requirements: {'; '.join(b['reasons'])}.", ""]
        else:
            best = ctx.get("beats_baseline")
            if best is None:
                L += ["No Pareto design is at least as good as the baseline on every objective.", ""]
            else:
                L += [f"`{best[0]}` is at least as good as the baseline on every objective:", ""]
                L += _cmp_lines(compare(best[1], b), best[0], "baseline")
                L.append("")
                beating = ctx.get("all_beating") or []
                if beating:
                    L += [f"All {len(beating)} Pareto designs that beat the baseline (better somewhere, worse "
                          "nowhere), difference to it:", "",
                          "| design | " + " | ".join(LABELS[k][0] for k in OBJECTIVES) + " |",
                          "|---|" + "---|" * len(OBJECTIVES)]
                    for n, r in beating:
                        cells = [f"{c['diff']:+.4g} {c['unit']} ({100 * c['rel']:+.1f} %)" for c in compare(r, b)]
                        L.append(f"| {n} | " + " | ".join(cells) + " |")
                    L.append("")
    if ctx.get("confirmed"):
        L += ["## Confirmed by simulation", "",
              "Simulated series of the required protocol (its number of parallel slices, Rician noise at the "
              "required SNR, the required pixel size and slice thickness) at three depths across the required "
              "range, at tilt 0 and at the highest required tilt with random azimuths, registered by "
              "`chic-register` with its default options (every trust check on); 'slices' counts series; measured errors "
              "beside the predicted bound (worst required pose). A measured RMS near the predicted SD "
              "means the solver reaches the bound; measured errors include any bias. A design is confirmed "
              f"when the solver locks at least {100 * (1 - MAX_NO_LOCK_SHARE):g} % of the slices: it refuses "
              "poses it cannot trust (e.g. too imprecise from one slice), so a refused design needs a "
              "different protocol (more slices) before use.", ""]
        L += confirm_lines(ctx["confirm_named"], ctx["confirmed"])
        L.append("")
    return "\n".join(L) + "\n"
