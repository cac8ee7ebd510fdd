"""``chic-design check SPEC``: feasibility limits of a design (tilt, depth, walls, symmetry), without building."""

from __future__ import annotations

import json
import math

from chic_design.errors import ChicDesignError
from chic_design.progress import status


def add_parser(subparsers):
    c = subparsers.add_parser("check", help="feasibility limits of a design, without building")
    c.add_argument("spec", help="design spec (YAML)")
    c.add_argument("--json", action="store_true", help="print one JSON object (docs/interfaces.md section 4)")
    c.add_argument("--slice-thickness", type=float, metavar="MM", help="override imaging.slice_thickness")
    c.add_argument("--pixel-size", type=float, metavar="MM", help="override imaging.pixel_size")
    c.add_argument("--plot", metavar="PNG", help="also save the max-tilt-vs-depth plot here")
    c.add_argument("--precision", action="store_true",
                   help="add the precision map (Cramer-Rao bound over depth and tilt, one slice; a few seconds)")
    c.add_argument("--snr", type=float, default=20.0, metavar="S", help="fluid SNR for --precision (default 20)")
    c.add_argument("--precision-plot", metavar="PNG", help="with --precision: save the precision plot here")
    return c


def _check_flags(args) -> None:
    """The precision flags, before any work."""
    if not args.precision:
        return
    if not (args.snr > 0 and math.isfinite(args.snr)):
        raise ChicDesignError(f"--snr must be > 0, got {args.snr}")
    if args.precision_plot and not args.precision_plot.lower().endswith(".png"):
        raise ChicDesignError(f"--precision-plot {args.precision_plot}: the plot is a PNG file (name it *.png)")


def run(args) -> int:
    from chic_design.families import family_of  # the checks load here, so that --help starts fast
    from chic_design.feasibility.tilt_plot import save_tilt_plot
    from chic_design.spec import load_spec, parse_spec

    _check_flags(args)
    spec = load_spec(args.spec)
    overrides = {k: v for k, v in (("pixel_size", args.pixel_size), ("slice_thickness", args.slice_thickness))
                 if v is not None}
    if overrides:  # the flags meet the spec's own ranges (finite, physical)
        data = spec.model_dump()
        data["imaging"].update(overrides)
        spec = parse_spec(data, f"{args.spec} with --pixel-size/--slice-thickness")
    family = family_of(spec)
    status(f"checking {spec.name}: tilt limits at every depth and azimuth, walls, overhangs, symmetry")
    report = family.check(spec)
    if args.plot:
        save_tilt_plot(report, args.plot)
    pm = None
    if args.precision:
        from chic_register.precision.report import design_precision, format_map, plot_map  # loaded when asked

        status(f"precision map of {spec.name}: Cramer-Rao bound over depth and tilt (a few seconds)")
        pm = design_precision(family.geometry(spec), report.pixel_size_mm, report.slice_thickness_mm, args.snr)
        if pm is not None and args.precision_plot:
            plot_map(pm, args.precision_plot, title=spec.name)
    if args.json:
        doc = report.to_dict()
        if args.precision:
            doc["precision"] = pm.to_dict() if pm is not None else None
        print(json.dumps(doc, indent=2))
    else:
        print(report.summary_text())
        if args.precision:
            print(format_map(pm, spec.name) if pm is not None else
                  "precision: not computed (ideal 0 mm pixels have no noise model)")
    return 0 if report.feasible else 1
