"""``chic-design``: build a CHIC fiducial from a spec, check its feasibility, print the spec schema, search designs.

A thin layer over the library: :func:`chic_design.build.build_design`,
:func:`chic_design.feasibility.check_design`, :func:`chic_design.spec.json_schema`.
``main(argv) -> int`` is testable in-process.
"""

from __future__ import annotations

import argparse
import json
import sys

from chic_register.cli import exits
from chic_register.errors import ChicRegisterError

from . import __version__
from .errors import ChicDesignError

PROG = "chic-design"


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
    c.add_argument("--json", action="store_true", help="print one JSON object (docs/interfaces.md section 4)")
    c.add_argument("--slice-thickness", type=float, metavar="MM", help="override imaging.slice_thickness")
    c.add_argument("--pixel-size", type=float, metavar="MM", help="override imaging.pixel_size")
    c.add_argument("--plot", metavar="PNG", help="also save the max-tilt-vs-depth plot here")
    c.add_argument("--precision", action="store_true",
                   help="add the precision map (Cramer-Rao bound over depth and tilt, one slice; a few seconds)")
    c.add_argument("--snr", type=float, default=20.0, metavar="S", help="fluid SNR for --precision (default 20)")
    c.add_argument("--precision-plot", metavar="PNG", help="with --precision: save the precision plot here")

    sc = sub.add_parser("schema", help="print the spec's JSON Schema")
    sc.add_argument("--family", default="chic", choices=["chic", "zframe"],
                    help="which spec family's schema (default chic)")

    o = sub.add_parser("optimize", help="search designs for a tool and protocol; Pareto set, specs and report")
    o.add_argument("requirements", help="requirements (YAML), e.g. designs/requirements/neuro.yaml")
    o.add_argument("--out", help="output folder (default: exports/optimize-<name>)")
    o.add_argument("--trials", type=int, help="candidates to evaluate (default: the file's search.trials)")
    o.add_argument("--seed", type=int, default=0, help="optimiser seed (default: 0)")
    o.add_argument("--scheduler", help="run on Dask: tcp://HOST:PORT, or local:N for a LocalCluster of N workers")
    o.add_argument("--workers", type=int, help="local worker processes (default: the CPU count)")
    o.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def _precision(args, spec, report):
    """The coarse precision map of ``chic-design check --precision`` (None for ideal pixels)."""
    import math

    from chic_register.precision.report import design_precision, plot_map

    from .layout import fiducial_geometry

    if not (args.snr > 0 and math.isfinite(args.snr)):
        raise ChicDesignError(f"--snr must be > 0, got {args.snr}")
    if args.precision_plot and not args.precision_plot.lower().endswith(".png"):
        raise ChicDesignError(f"--precision-plot {args.precision_plot}: the plot is a PNG file (name it *.png)")
    geometry = fiducial_geometry(spec)
    pm = design_precision(geometry, report.pixel_size_mm, report.slice_thickness_mm, args.snr)
    if pm is not None and args.precision_plot:
        plot_map(pm, args.precision_plot, title=spec.name)
    return pm


def _run(args) -> int:
    if args.command == "schema":
        from .spec import json_schema

        print(json.dumps(json_schema(args.family), indent=2))
        return 0
    if args.command == "check":
        from .feasibility import check_design, save_tilt_plot
        from .spec import load_spec, parse_spec

        spec = load_spec(args.spec)
        overrides = {k: v for k, v in (("pixel_size", args.pixel_size), ("slice_thickness", args.slice_thickness))
                     if v is not None}
        if overrides:  # the flags meet the spec's own ranges (finite, physical)
            data = spec.model_dump()
            data["imaging"].update(overrides)
            spec = parse_spec(data, f"{args.spec} with --pixel-size/--slice-thickness")
        report = check_design(spec)
        if args.plot:
            save_tilt_plot(report, args.plot)
        pm = _precision(args, spec, report) if args.precision else None
        if args.json:
            doc = report.to_dict()
            if args.precision:
                doc["precision"] = pm.to_dict() if pm is not None else None
            print(json.dumps(doc, indent=2))
        else:
            print(report.summary_text())
            if args.precision:
                from chic_register.precision.report import format_map

                print(format_map(pm, spec.name) if pm is not None else
                      "precision: not computed (ideal 0 mm pixels have no noise model)")
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
        return exits.report(PROG, f"error: {exc}", exc.exit_code)
    except KeyboardInterrupt:
        return exits.report(PROG, "interrupted", 130)
    except BrokenPipeError:  # e.g. `chic-design schema | head`: the reader left; nothing more to say
        return exits.broken_pipe()
    except OSError as exc:  # an output that cannot be written (disk full, permission, vanished folder)
        return exits.os_error(PROG, exc)


if __name__ == "__main__":
    sys.exit(main())
