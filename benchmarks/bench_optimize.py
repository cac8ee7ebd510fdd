"""Benchmark of ``chic-design optimize``: candidates evaluated per second on 1 and 2 local workers and a 2-worker Dask LocalCluster.

Run: ``.venv/bin/python benchmarks/bench_optimize.py [REQUIREMENTS] [--trials N] [--seed S]``.
Each engine runs the same seeded search (same candidates, fresh in-memory
store, so nothing is cached) and the script checks that all find the same
Pareto set. Prints wall time, candidates/s, the workers' CPU time, and the
load average before and after each run (the machine is shared: the figures
are only comparable at similar load). The Dask cluster's start-up is timed
separately and not counted in its candidates/s.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from chic_design.optimize import space  # noqa: E402
from chic_design.optimize.engine import DaskEngine, LocalEngine, SerialEngine  # noqa: E402
from chic_design.optimize.requirements import baseline_path, load_requirements  # noqa: E402
from chic_design.optimize.search import run_search  # noqa: E402
from chic_design.optimize.store import ResultStore  # noqa: E402
from chic_design.spec import load_spec  # noqa: E402


def _load() -> str:
    return "/".join(f"{v:.1f}" for v in os.getloadavg())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("requirements", nargs="?", default=str(ROOT / "designs/requirements/neuro.yaml"))
    ap.add_argument("--trials", type=int, default=48)
    ap.add_argument("--population", type=int, default=24)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    req = load_requirements(args.requirements)
    bpath = baseline_path(req, args.requirements)
    start = space.params_from_spec(load_spec(bpath), req) if bpath else None
    start = start if start is not None else space.default_start(req)
    fronts = {}
    print(f"{args.requirements}: {args.trials} candidates, population {args.population}, seed {args.seed}; "
          f"{os.cpu_count()} CPUs")
    for label, make in (("serial, 1 worker", SerialEngine), ("local pool, 2 workers", lambda: LocalEngine(2)),
                        ("Dask LocalCluster, 2 workers", lambda: DaskEngine("local:2"))):
        load0 = _load()
        t0 = time.perf_counter()
        engine = make()
        t_start = time.perf_counter() - t0
        try:
            with ResultStore(None) as store:
                res = run_search(req, engine, store, args.trials, seed=args.seed, population=args.population,
                                 start_params=start, progress=False)
        finally:
            engine.close()
        fronts[label] = [p["key"] for p in res.pareto]
        print(f"  {label:30s} {res.evaluated / res.wall_s:5.2f} candidates/s  wall {res.wall_s:6.1f} s  "
              f"worker CPU {res.cpu_s:6.1f} s  ({res.cpu_s / res.evaluated:.2f} s/candidate)  "
              f"start-up {t_start:4.1f} s  feasible {res.feasible}/{len(res.candidates)}  "
              f"load {load0} -> {_load()}")
    same = len({tuple(v) for v in fronts.values()}) == 1
    print(f"  same Pareto set on every engine: {same}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
