"""``chic-design optimize REQUIREMENTS``: search CHIC designs for a tool and protocol; Pareto set, specs and report."""

from __future__ import annotations

from chic_design.errors import ChicDesignError
from chic_design.progress import status


def add_parser(subparsers):
    o = subparsers.add_parser("optimize", help="search designs for a tool and protocol; Pareto set, specs and report")
    o.add_argument("requirements", help="requirements (YAML), e.g. designs/requirements/neuro.yaml")
    o.add_argument("--out", help="output folder (default: exports/optimize-<name>)")
    o.add_argument("--trials", type=int, help="candidates to evaluate (default: the file's search.trials)")
    o.add_argument("--seed", type=int, default=0, help="optimiser seed (default: 0)")
    o.add_argument("--scheduler", help="run on Dask: tcp://HOST:PORT, or local:N for a LocalCluster of N workers")
    o.add_argument("--workers", type=int, help="local worker processes (default: the CPU count)")
    o.add_argument("--quiet", action="store_true", help="no progress bar")
    return o


def run(args) -> int:
    if args.trials is not None and args.trials < 1:
        raise ChicDesignError(f"--trials must be >= 1, got {args.trials}")
    if args.workers is not None and args.workers < 1:
        raise ChicDesignError(f"--workers must be >= 1, got {args.workers}")
    from chic_design.optimize.engine import parse_scheduler  # the inputs first: a bad one is one line
    from chic_design.optimize.requirements import load_requirements

    scheduler = parse_scheduler(args.scheduler)
    req = load_requirements(args.requirements)
    progress = not args.quiet
    if progress:
        status(f"optimizing {req.name} from {args.requirements} (loading the optimiser and the solver)")
    from chic_design.optimize.pipeline import optimize  # optuna, dask and the solver: seconds to load

    result = optimize(args.requirements, out_dir=args.out, trials=args.trials, seed=args.seed, scheduler=scheduler,
                      workers=args.workers, progress=progress)
    if progress:
        for path in result.files:
            status(f"wrote {path}")
    print(result.summary_text())
    return 0
