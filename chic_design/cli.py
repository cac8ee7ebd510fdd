"""``chic-design``: build a CHIC fiducial from a spec, check its feasibility, print the spec schema.

A thin layer over the library: :func:`chic_design.build.build_design`,
:func:`chic_design.feasibility.check_design`, :func:`chic_design.spec.json_schema`.
``main(argv) -> int`` is testable in-process.
"""

from __future__ import annotations

import argparse
import json
import sys

from . import __version__
from chic_register.errors import ChicRegisterError

from .errors import ChicDesignError


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="chic-design", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"chic-design {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    b = sub.add_parser("build", help="make the printable parts, geometry.yaml, preview and report")
    b.add_argument("spec", help="design spec (YAML), e.g. designs/neuro.yaml")
    b.add_argument("--out", default="exports", help="export root; the design goes to OUT/<name>/ (default: exports)")
    b.add_argument("--force", action="store_true", help="build even if the feasibility checks find violations")
    b.add_argument("--quiet", action="store_true", help="no progress output")

    c = sub.add_parser("check", help="feasibility limits of a design, without building")
    c.add_argument("spec", help="design spec (YAML)")
    c.add_argument("--json", action="store_true", help="print one JSON object (CONTRACT.md section 4)")
    c.add_argument("--slice-thickness", type=float, metavar="MM", help="override imaging.slice_thickness")
    c.add_argument("--pixel-size", type=float, metavar="MM", help="override imaging.pixel_size")
    c.add_argument("--plot", metavar="PNG", help="also save the max-tilt-vs-depth plot here")

    sub.add_parser("schema", help="print the spec's JSON Schema")

    o = sub.add_parser("optimize", help="search designs for a tool and protocol; Pareto set, specs and report")
    o.add_argument("requirements", help="requirements (YAML), e.g. designs/requirements/neuro.yaml")
    o.add_argument("--out", help="output folder (default: exports/optimize-<name>)")
    o.add_argument("--trials", type=int, help="candidates to evaluate (default: the file's search.trials)")
    o.add_argument("--seed", type=int, default=0, help="optimiser seed (default: 0)")
    o.add_argument("--scheduler", help="run on Dask: tcp://HOST:PORT, or local:N for a LocalCluster of N workers")
    o.add_argument("--workers", type=int, help="local worker processes (default: the CPU count)")
    o.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _non_negative(value, flag: str) -> float | None:
    if value is not None and (value < 0 or value != value):
        raise ChicDesignError(f"{flag} must be >= 0 mm, got {value}")
    return value


def _run(args) -> int:
    if args.command == "schema":
        from .spec import json_schema

        print(json.dumps(json_schema(), indent=2))
        return 0
    if args.command == "check":
        from .feasibility import check_design, save_tilt_plot
        from .spec import load_spec

        spec = load_spec(args.spec)
        report = check_design(
            spec,
            pixel_size_mm=_non_negative(args.pixel_size, "--pixel-size"),
            slice_thickness_mm=_non_negative(args.slice_thickness, "--slice-thickness"),
        )
        if args.plot:
            save_tilt_plot(report, args.plot)
        if args.json:
            print(json.dumps(report.to_dict(), indent=2))
        else:
            print(report.summary_text())
        return 0 if report.feasible else 1
    if args.command == "optimize":
        from .optimize.engine import parse_scheduler
        from .optimize.pipeline import optimize

        if args.trials is not None and args.trials < 1:
            raise ChicDesignError(f"--trials must be >= 1, got {args.trials}")
        if args.workers is not None and args.workers < 1:
            raise ChicDesignError(f"--workers must be >= 1, got {args.workers}")
        result = optimize(args.requirements, out_dir=args.out, trials=args.trials, seed=args.seed,
                          scheduler=parse_scheduler(args.scheduler), workers=args.workers,
                          progress=not args.quiet)
        print(result.summary_text())
        return 0
    if args.command == "build":
        from .build import build_design

        result = build_design(args.spec, out_root=args.out, force=args.force, progress=not args.quiet)
        print(result.summary_text())
        return 0
    raise AssertionError(args.command)


def main(argv=None) -> int:
    args = None
    try:
        args = _parser().parse_args(argv)  # inside: `--help | head` must not traceback either
        return _run(args)
    except (ChicDesignError, ChicRegisterError) as exc:  # the geometry file is chic_register's
        return _report(f"error: {exc}", exc.exit_code)
    except KeyboardInterrupt:
        return _report("interrupted", 130)
    except BrokenPipeError:  # e.g. `chic-design schema | head`: the reader left; nothing more to say
        return _quiet_broken_pipe()
    except OSError as exc:  # an output that cannot be written (disk full, permission, vanished folder)
        where = f"{exc.filename}: " if exc.filename else ""
        return _report(f"error: {where}{exc.strerror or exc}", 1)


def _report(text: str, code: int) -> int:
    """Print one ``chic-design: ...`` line on stderr (if stderr is still there) and return ``code``."""
    try:
        print(f"chic-design: {text}", file=sys.stderr)
    except (BrokenPipeError, OSError):
        pass
    return code


def _quiet_broken_pipe() -> int:
    """Point stdout at /dev/null so the interpreter's final flush does not fail again; exit 141 (SIGPIPE)."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):
        pass
    return 141


if __name__ == "__main__":
    sys.exit(main())
