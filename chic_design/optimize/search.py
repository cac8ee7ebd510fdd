"""The search loop: Optuna's NSGA-II asks a generation, the engine evaluates it, results are told in order.

Determinism: the sampler is seeded, a whole generation is asked before any
result is told, and results are told in ask order whatever order the workers
finish in, so a serial run, a process pool and a Dask cluster visit the same
candidates and find the same Pareto set. Finished candidates go to the
:class:`~.store.ResultStore` as they arrive; a rerun replays the same asks
and takes every stored candidate from the store instead of evaluating it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import optuna
from tqdm import tqdm

from chic_design.optimize import space
from chic_design.optimize.requirements import Requirements
from chic_design.optimize.score import DIRECTIONS, OBJECTIVES, SCORER_VERSION, evaluate_candidate, pareto_front

_WORST = {"minimize": 1e9, "maximize": -1e9}


@dataclass(frozen=True)
class SearchResult:
    """Every candidate visited (in ask order, with key and params), the Pareto set, and run counts."""

    candidates: tuple[dict, ...]
    pareto: tuple[dict, ...]
    evaluated: int
    cached: int
    wall_s: float
    cpu_s: float
    engine: str
    workers: int
    settings: dict = field(default_factory=dict)

    @property
    def feasible(self) -> int:
        return sum(1 for c in self.candidates if c["feasible"])


def _values(result: dict) -> list[float]:
    if not result["feasible"]:
        return [_WORST[d] for d in DIRECTIONS]
    return [result["objectives"][k] for k in OBJECTIVES]


def make_study(seed: int, population: int) -> optuna.Study:
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    sampler = optuna.samplers.NSGAIISampler(population_size=population, seed=seed)
    return optuna.create_study(directions=list(DIRECTIONS), sampler=sampler)


def run_search(req: Requirements, engine, store, trials: int, seed: int = 0, population: int | None = None,
               start_params: dict | None = None, progress: bool = True) -> SearchResult:
    """Search ``trials`` candidates; returns all of them and the Pareto set of the feasible ones."""
    population = population or req.search.population
    study = make_study(seed, population)
    if start_params is not None:  # the start design and its neighbours open the first generation
        for p in [start_params] + space.neighbours(start_params, req)[:population - 1]:
            study.enqueue_trial(p)
    req_data = req.model_dump()
    bar = None
    if progress:
        bar = tqdm(total=trials, desc=f"optimize {req.name} ({engine.name}, {engine.workers} workers)",
                   unit="cand")
    t0 = time.perf_counter()
    visited, evaluated, cached, cpu = [], 0, 0, 0.0
    try:
        while len(visited) < trials:
            batch = [study.ask() for _ in range(min(population, trials - len(visited)))]
            params = [space.suggest(t, req) for t in batch]
            keys = [space.candidate_key(p, req, SCORER_VERSION) for p in params]
            results = store.get_many(keys)
            stored = sum(1 for k in keys if k in results)
            cached += stored
            todo = list(dict.fromkeys(k for k in keys if k not in results))
            if bar is not None and stored:
                bar.update(stored)  # each evaluated key below counts once per time it was asked
            first = {k: params[keys.index(k)] for k in todo}
            jobs = [(first[k], req_data) for k in todo]
            for i, res in engine.map_unordered(evaluate_candidate, jobs):
                store.put(todo[i], space.canonical(first[todo[i]]), res)
                results[todo[i]] = res
                evaluated += 1
                cpu += res.get("cpu_s", 0.0)
                if bar is not None:
                    bar.update(keys.count(todo[i]))
            for trial, p, k in zip(batch, params, keys):  # tell in ask order: engine-independent
                res = results[k]
                for j, c in enumerate(res["constraints"]):
                    trial.set_constraint(f"c{j}", float(c))
                study.tell(trial, _values(res))
                visited.append({"key": k, "params": space.canonical(p), **res})
    finally:
        if bar is not None:
            bar.close()
    front = pareto_front(visited)
    return SearchResult(tuple(visited), tuple(front), evaluated, cached, time.perf_counter() - t0,
                        cpu,
                        engine.name, engine.workers,
                        {"seed": seed, "trials": trials, "population": population, "sampler": "NSGA-II",
                         "optuna": optuna.__version__})
