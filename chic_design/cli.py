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

    sc = sub.add_parser("schema", help="print the spec's JSON Schema")
    sc.add_argument("--family", default="chic", choices=["chic", "zframe"],
                    help="which spec family's schema (default chic)")
    return p


def _non_negative(value, flag: str) -> float | None:
    if value is not None and (value < 0 or value != value):
        raise ChicDesignError(f"{flag} must be >= 0 mm, got {value}")
    return value


def _run(args) -> int:
    if args.command == "schema":
        from .spec import json_schema

        print(json.dumps(json_schema(args.family), indent=2))
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
    if args.command == "build":
        from .build import build_design

        result = build_design(args.spec, out_root=args.out, force=args.force, progress=not args.quiet)
        print(result.summary_text())
        return 0
    raise AssertionError(args.command)


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    try:
        return _run(args)
    except ChicDesignError as exc:
        print(f"chic-design: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("chic-design: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
