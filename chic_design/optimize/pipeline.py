"""``optimize``: requirements in; Pareto table, plot, spec YAMLs, confirmation and report out.

The library entry point behind ``chic-design optimize`` (the CLI only parses
arguments). Output folder ``out_dir``:

- ``candidates.sqlite``: every finished candidate (the resumable store);
- ``pareto.csv``, ``pareto.png``, ``specs/<name>.yaml`` (one per Pareto design);
- ``chosen/``: the chosen design's preview, tilt-limit plot and precision map;
- ``confirm.json``: the simulation study of the finalists;
- ``report.md`` and ``result.json``.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from tqdm import tqdm

from chic_design.families import family_of
from chic_design.families.chic.spec import ChicSpec
from chic_design.feasibility.engine import check_geometry
from chic_design.feasibility.tilt_plot import save_tilt_plot
from chic_design.optimize import space
from chic_design.optimize.choose import compare, ideal_distances, knee_order, weakly_dominating
from chic_design.optimize.confirm import confirm_design
from chic_design.optimize.engine import make_engine
from chic_design.optimize.errors import NoFeasibleDesign, RequirementsError
from chic_design.optimize.plots import save_pareto_plot, save_precision_map
from chic_design.optimize.precision import method as precision_method
from chic_design.optimize.precision import protocol_of
from chic_design.optimize.report import confirmed_verdict, report_markdown, table_row, write_csv, write_spec
from chic_design.optimize.requirements import Requirements, baseline_path, load_requirements
from chic_design.optimize.score import dominates, score_spec
from chic_design.optimize.search import SearchResult, run_search
from chic_design.optimize.store import ResultStore
from chic_design.optimize.trust import solver_limits, trust_excess
from chic_design.progress import status
from chic_design.report.pictures import render_preview
from chic_design.spec import load_spec, parse_spec
from chic_register.precision.crlb import precision_map
from chic_register.util.atomic import write_json, write_text


@dataclass(frozen=True)
class OptimizeResult:
    out_dir: Path
    search: SearchResult
    pareto: tuple[tuple[str, dict], ...]   # (name, result) in choice order; [0] is chosen
    baseline: dict | None
    beats_baseline: tuple[str, dict] | None
    confirmed: dict
    files: tuple[Path, ...] = ()

    def summary_text(self) -> str:
        s = self.search
        name, best = self.pareto[0]
        o = best["objectives"]
        again = len(s.candidates) - s.evaluated - s.cached
        lines = [f"chic-design optimize: {len(s.candidates)} candidates ({s.evaluated} evaluated, {s.cached} "
                 f"from the store{f', {again} asked twice in one generation' if again else ''}), {s.feasible} "
                 f"feasible, {len(self.pareto)} Pareto designs",
                 f"chosen: {name}: OD {o['outer_diameter_mm']:g} mm, usable region "
                 f"{o['usable_region_deg_mm']:.0f} deg mm, predicted TRE {o['tre_mm']:.3f} mm"]
        if self.beats_baseline is not None:
            bn, br = self.beats_baseline
            diffs = ", ".join(f"{c['label']} {c['diff']:+.4g} {c['unit']} ({100 * c['rel']:+.1f} %)"
                              for c in compare(br, self.baseline))
            lines.append(f"{bn} is at least as good as the baseline on every objective: {diffs}")
        elif self.baseline is not None:
            lines.append("no Pareto design is at least as good as the baseline on every objective")
        for n, c in self.confirmed.items():
            lines.append(f"simulation: {n}: {c['slices'] - c['no_lock']}/{c['slices']} slices registered; "
                         f"confirmed: {confirmed_verdict(c)}")
        lines.append(f"report: {self.out_dir / 'report.md'}")
        return "\n".join(lines)


def _no_feasible_message(req: Requirements, search: SearchResult) -> str:
    reasons = Counter(c["reasons"][0].split(" (")[0].split(": predicted")[0] for c in search.candidates
                      if c["reasons"])
    common = ", ".join(f"{k} x{n}" for k, n in reasons.most_common(3))
    limits = solver_limits()
    refused = sorted((c for c in search.candidates if c.get("precision") is not None and not c["feasible"]),
                     key=lambda c: trust_excess(c["precision"], limits))
    nearest = f"; nearest to the solver's trust: {refused[0]['reasons'][0]}" if refused else ""
    return (f"requirements '{req.name}': none of {len(search.candidates)} candidates meets every requirement "
            f"(most common reasons: {common}{nearest}); relax the limits or the required tilt/depth, use more "
            "parallel slices (imaging.n_slices), or search longer")


def _chosen_pictures(req: Requirements, name: str, result: dict, folder: Path, progress: bool) -> list[Path]:
    """Preview, tilt plot and precision map (CRLB over depth x tilt) of the chosen design; returns the files."""
    if progress:
        status(f"chosen design {name}: preview and tilt limits")
    spec = parse_spec(result["spec"], name)
    family = family_of(spec)
    geom = family.geometry(spec)
    folder.mkdir(parents=True, exist_ok=True)
    render_preview(geom, folder / "preview.png")
    report = check_geometry(geom, family, pixel_size_mm=req.imaging.pixel_size,
                            slice_thickness_mm=req.imaging.slice_thickness, min_wall_mm=req.printer.min_wall,
                            max_overhang_deg=req.printer.max_overhang_deg)
    save_tilt_plot(report, folder / "tilt_limits.png")
    t1 = req.required.tilt_deg[1]
    tilts = sorted({0.0, float(t1), round(1.5 * t1, 1)}) if t1 > 0 else [0.0, 10.0, 20.0]
    L = spec.body.length
    depths = [round(L * f, 1) for f in (0.1, 0.3, 0.5, 0.7, 0.9)]
    if progress:
        status(f"chosen design {name}: precision map (Cramer-Rao bound at {len(depths)} depths x {len(tilts)} tilts)")
    pmap = precision_map(geom, protocol_of(req), depths_mm=depths, tilts_deg=tilts,
                         target_F_mm=req.required.target_mm)
    write_json(folder / "precision_map.json", pmap.to_dict())
    save_precision_map(pmap, report.tilt_limits, folder / "precision_map.png",
                       f"{name}: predicted TRE at {list(req.required.target_mm)} mm (CRLB)")
    return [folder / f for f in ("preview.png", "tilt_limits.png", "precision_map.json", "precision_map.png")]


def _confirm(engine, finalists, jobs, progress: bool) -> dict:
    """Run the simulation study of every finalist on ``engine``, with a progress bar; the results in the
    finalists' order (they finish in any order), so the summary and ``confirm.json`` read the same every run."""
    bar = None
    if progress:
        bar = tqdm(total=len(jobs), desc=f"confirm {len(jobs)} designs by simulated registration", unit="design")
    confirmed = {}
    try:
        for i, res in engine.map_unordered(confirm_design, jobs):
            confirmed[finalists[i][0]] = res
            if bar is not None:
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    return {name: confirmed[name] for name, _ in finalists if name in confirmed}


def _beats_baseline(named, baseline):
    """The first design in choice order better than the baseline somewhere and worse nowhere; else an equal one."""
    if baseline is None or not baseline["feasible"]:
        return None
    strict = [(n, r) for n, r in named if dominates(r["objectives"], baseline["objectives"])]
    equal = [(n, r) for n, r in named if weakly_dominating([r], baseline)]
    return (strict or equal or [None])[0]


def optimize(req_path, out_dir=None, trials: int | None = None, seed: int = 0, scheduler: str | None = None,
             workers: int | None = None, progress: bool = True, confirm: int | None = None,
             pictures: bool = True) -> OptimizeResult:
    """Search the CHIC design space for ``req_path``'s requirements and write the outputs (module docstring)."""
    req = load_requirements(req_path)
    out = Path(out_dir) if out_dir is not None else Path("exports") / f"optimize-{req.name}"
    trials = trials if trials is not None else req.search.trials
    n_confirm = req.search.confirm if confirm is None else confirm
    bpath = baseline_path(req, req_path)
    baseline, start = None, None
    if bpath is not None:
        bspec = load_spec(bpath)
        if not isinstance(bspec, ChicSpec):
            raise RequirementsError(f"{req_path}: search.baseline: {bpath} is a {bspec.family} design; the "
                                    "optimiser searches CHIC designs, so the baseline must be one")
        baseline = score_spec(bspec, req, bspec.model_dump())
        start = space.params_from_spec(bspec, req)
    start = start if start is not None else space.default_start(req)
    engine = make_engine(scheduler, workers)
    try:
        with ResultStore(out / "candidates.sqlite") as store:
            search = run_search(req, engine, store, trials, seed=seed, start_params=start, progress=progress)
        front = list(search.pareto)
        if not front:
            raise NoFeasibleDesign(_no_feasible_message(req, search))
        order = knee_order(front)
        named = []
        for rank, i in enumerate(order, 1):
            nm = f"{req.name}-p{rank:02d}"
            named.append((nm, {**front[i], "spec": {**front[i]["spec"], "name": nm}}))
        beats = _beats_baseline(named, baseline)
        finalists = named[:n_confirm]
        if n_confirm and beats is not None and beats not in finalists:
            finalists.append(beats)
        if n_confirm and baseline is not None and baseline["feasible"]:
            finalists.append(("baseline", baseline))
        jobs = [(r["spec"], req.model_dump(), req.search.confirm_draws, seed) for _, r in finalists]
        confirmed = _confirm(engine, finalists, jobs, progress) if jobs else {}
    finally:
        engine.close()
    files = [out / "candidates.sqlite"]
    specs = out / "specs"
    specs.mkdir(parents=True, exist_ok=True)
    wanted = {f"{n}.yaml" for n, _ in named}
    for old in specs.glob("*.yaml"):
        if old.name not in wanted:
            old.unlink()
    for n, r in named:
        files.append(write_spec(r["spec"], specs / f"{n}.yaml"))
    rows = [table_row(n, r) for n, r in named]
    files.append(write_csv(rows, out / "pareto.csv"))
    if pictures:
        if progress:
            status(f"drawing the Pareto set of {len(named)} designs")
        files.append(save_pareto_plot(search.candidates, [r for _, r in named], named[0][1], baseline,
                                      out / "pareto.png"))
        files += _chosen_pictures(req, named[0][0], named[0][1], out / "chosen", progress)
    files.append(write_json(out / "confirm.json", confirmed))
    dist = [float(d) for d in ideal_distances([r for _, r in named])]
    ctx = {"req": req, "req_path": str(req_path), "search": search, "named": named, "rows": rows,
           "baseline": baseline, "baseline_path": str(bpath) if bpath else None, "beats_baseline": beats,
           "all_beating": [(n, r) for n, r in named if baseline is not None and baseline["feasible"]
                           and dominates(r["objectives"], baseline["objectives"])],
           "confirmed": confirmed, "confirm_named": finalists, "pictures": pictures, "distances": dist,
           "precision_method": precision_method(req), "trust_limits": solver_limits()}
    files.append(write_text(out / "report.md", report_markdown(ctx)))
    files.append(write_json(out / "result.json", {
        "requirements": str(req_path), "settings": search.settings, "engine": search.engine,
        "workers": search.workers, "evaluated": search.evaluated, "cached": search.cached,
        "feasible": search.feasible, "candidates": len(search.candidates), "wall_s": search.wall_s,
        "cpu_s": search.cpu_s, "pareto": [{"name": n, "key": r["key"], "objectives": r["objectives"],
                                           "precision": r["precision"]} for n, r in named],
        "baseline": None if baseline is None else {"feasible": baseline["feasible"],
                                                   "objectives": baseline["objectives"],
                                                   "reasons": baseline["reasons"]},
        "beats_baseline": None if beats is None else {"name": beats[0], "comparison": compare(beats[1], baseline)},
        "confirmed": confirmed}))
    return OptimizeResult(out, search, tuple(named), baseline, beats, confirmed, tuple(files))
