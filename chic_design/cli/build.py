"""``chic-design build SPEC``: the printable parts, geometry.yaml, pictures and report, in OUT/<name>/."""

from __future__ import annotations

from chic_design.progress import status


def add_parser(subparsers):
    b = subparsers.add_parser("build", help="make the printable parts, geometry.yaml, preview and report")
    b.add_argument("spec", help="design spec (YAML), e.g. designs/neuro.yaml")
    b.add_argument("--out", default="exports", help="export root; the design goes to OUT/<name>/ (default: exports)")
    b.add_argument("--force", action="store_true", help="build even if the feasibility checks find violations")
    b.add_argument("--printcheck", choices=("auto", "on", "off"), default="auto",
                   help="slice plate.3mf and check every channel in the toolpaths: auto (when prusa-slicer is on "
                        "the PATH; the default), on (required), off")
    b.add_argument("--quiet", action="store_true", help="no progress output")
    return b


def run(args) -> int:
    from chic_design.spec import load_spec  # the spec first: a bad one is one line, before the CAD kernel loads

    spec = load_spec(args.spec)
    progress = not args.quiet
    if progress:
        status(f"building {spec.name} from {args.spec} into {args.out}/{spec.name}/ (loading the CAD kernel)")
    from chic_design.build.pipeline import build_design  # the CAD kernel takes seconds to load

    printcheck = {"auto": None, "on": True, "off": False}[args.printcheck]
    result = build_design(args.spec, out_root=args.out, force=args.force, progress=progress, printcheck=printcheck)
    if progress:
        for name in result.files:
            status(f"wrote {result.folder / name}")
    print(result.summary_text())
    return 0
