"""chic-register evaluate: repeat the paper's simulation study on a geometry and compare with the paper."""

from __future__ import annotations

import json
import math
import sys

from chic_register.errors import ChicRegisterError

HELP = "repeat the paper's simulation study and compare"
DESCRIPTION = "Repeat the paper's simulation study on the geometry and compare with the paper's errors."


def add_parser(subparsers) -> None:
    """The evaluate subcommand and its flags."""
    e = subparsers.add_parser("evaluate", help=HELP, description=DESCRIPTION)
    e.set_defaults(run=run)
    e.add_argument("--geometry", required=True, help="geometry.yaml")
    e.add_argument("--protocol", default="paper", choices=["paper"], help="study protocol (default: paper)")
    e.add_argument("--draws", type=int, default=20, metavar="N", help="noise draws per case (default 20)")
    e.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
    e.add_argument("--out", metavar="DIR", help="write fig7/fig8 plots and study JSON into DIR")
    e.add_argument("--noise", default="both", choices=["uniform", "rician", "both", "none"],
                   help="the paper's uniform white noise, Rician MRI noise, both (default) or none")
    e.add_argument("--noise-level", type=float, default=0.1, metavar="X",
                   help="uniform noise amplitude, fluid = 1: U(-X, X) (default 0.1)")
    e.add_argument("--snr", type=float, default=20.0, metavar="S", help="Rician SNR of fluid (default 20)")
    e.add_argument("--slice-thickness", type=float, default=0.0, metavar="MM",
                   help="slice thickness (default 0: thin sections, as the paper's CAD cross-sections)")
    e.add_argument("--json", action="store_true", help="print one JSON object with every study")


def run(args) -> int:
    """Run the study for each noise kind; print the summaries (or one JSON object); write the plots."""
    # here, not at the top: keeps chic-register's start-up fast (every command module is imported)
    from chic_register.model.geometry import load_geometry
    from chic_register.studies.evaluate import format_summary, run_study, save_plots

    if args.draws < 1:
        raise ChicRegisterError(f"--draws must be >= 1, got {args.draws}")
    if not (args.noise_level >= 0 and math.isfinite(args.noise_level)):
        raise ChicRegisterError(f"--noise-level must be >= 0, got {args.noise_level:g}")
    if not (args.snr > 0 and math.isfinite(args.snr)):
        raise ChicRegisterError(f"--snr must be > 0, got {args.snr:g}")
    if not (args.slice_thickness >= 0 and math.isfinite(args.slice_thickness)):
        raise ChicRegisterError(f"--slice-thickness must be >= 0 mm, got {args.slice_thickness:g}")
    geom = load_geometry(args.geometry)
    kinds = ["uniform", "rician"] if args.noise == "both" else [args.noise]
    studies = {}
    for kind in kinds:
        result = run_study(geom, args.draws, args.seed, noise=kind, noise_level=args.noise_level, snr=args.snr,
                           slice_thickness_mm=args.slice_thickness, progress=True)  # the bar is on stderr
        studies[kind] = result
        if args.out:
            written = save_plots(result, args.out, tag=f"-{kind}")
            # on stderr either way: stdout holds the summaries (or the JSON object)
            print(("chic-register: " if args.json else "") + "wrote " + ", ".join(str(p) for p in written),
                  file=sys.stderr, flush=True)
        if not args.json:
            print(format_summary(result))
            print()
    if args.json:
        print(json.dumps({k: v.to_dict() for k, v in studies.items()}, indent=1))
    return 0
