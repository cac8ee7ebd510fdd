"""chic-register precision: the design's Cramer-Rao precision map over depth and tilt, cell by cell with a progress bar."""

from __future__ import annotations

import json
import math

from chic_register.cli.console import note, progress_bar
from chic_register.errors import ChicRegisterError

HELP = "the design's precision map: Cramer-Rao bound over depth and tilt"
DESCRIPTION = ("The design's precision map: the Cramer-Rao bound over depth and tilt, for a protocol (pixel size, "
               "slice thickness, SNR, slices per pose).")
#: default depths: this many, evenly from 10 % to 90 % of the body length (as the --depths help says)
DEFAULT_DEPTHS = 9


def add_parser(subparsers) -> None:
    """The precision subcommand and its flags."""
    c = subparsers.add_parser("precision", help=HELP, description=DESCRIPTION)
    c.set_defaults(run=run)
    c.add_argument("--geometry", required=True, help="geometry.yaml")
    c.add_argument("--pixel-size", type=float, default=0.5, metavar="MM", help="square pixel size (default 0.5)")
    c.add_argument("--slice-thickness", type=float, default=2.0, metavar="MM", help="slice thickness (default 2)")
    c.add_argument("--snr", type=float, default=20.0, metavar="S", help="fluid SNR, Rician noise (default 20)")
    c.add_argument("--slices", type=int, default=1, metavar="N", help="parallel slices per pose (default 1)")
    c.add_argument("--slice-spacing", type=float, default=None, metavar="MM",
                   help="centre-to-centre slice spacing (default: the slice thickness)")
    c.add_argument("--target", nargs=3, type=float, metavar=("X", "Y", "Z"),
                   help="TRE point in F (mm; default: the tool tip, else the body centre)")
    c.add_argument("--depths", nargs="+", type=float, metavar="MM",
                   help=f"depths (default: 10-90 %% of the body, {DEFAULT_DEPTHS})")
    c.add_argument("--tilts", nargs="+", type=float, default=[0.0, 15.0, 30.0, 45.0], metavar="DEG",
                   help="tilts (default 0 15 30 45)")
    c.add_argument("--azimuths", type=int, default=4, metavar="N", help="azimuths per cell (default 4)")
    c.add_argument("--json", action="store_true", help="print one JSON object")
    c.add_argument("--plot", metavar="PNG", help="write the precision map plot")


def run(args) -> int:
    """Compute the map one (depth, tilt) cell at a time, so a progress bar on stderr can follow it."""
    # here, not at the top: keeps chic-register's start-up fast (every command module is imported)
    import numpy as np

    from chic_register.model.geometry import load_geometry
    from chic_register.precision.crlb import PrecisionMap, Protocol, precision_map
    from chic_register.precision.report import format_map, plot_map

    geom = load_geometry(args.geometry)
    spacing = args.slice_thickness if args.slice_spacing is None else args.slice_spacing
    try:
        protocol = Protocol(args.pixel_size, args.slice_thickness, args.snr, args.slices, spacing)
    except ValueError as exc:
        raise ChicRegisterError(f"precision: {exc}") from None
    for name, vals in (("--depths", args.depths or []), ("--tilts", args.tilts), ("--target", args.target or [])):
        if not all(math.isfinite(v) for v in vals):
            raise ChicRegisterError(f"{name} must be finite numbers")
    if not all(0.0 <= t < 90.0 for t in args.tilts):
        raise ChicRegisterError("--tilts must be in [0, 90) degrees")
    if args.azimuths < 1:
        raise ChicRegisterError(f"--azimuths must be >= 1, got {args.azimuths}")
    if args.plot and not args.plot.lower().endswith(".png"):
        raise ChicRegisterError(f"--plot {args.plot}: the plot is a PNG file (name it *.png)")
    L = float(geom.body.length)
    depths = args.depths if args.depths else np.linspace(0.1 * L, 0.9 * L, DEFAULT_DEPTHS).tolist()
    cells = [(float(d), float(t)) for d in depths for t in args.tilts]
    rows, part = [], None
    with progress_bar(len(cells), f"precision map ({args.azimuths} azimuths a cell)", "cell") as bar:
        for d, t in cells:
            part = precision_map(geom, protocol, [d], [t], args.target, n_azimuths=args.azimuths)
            rows.extend(part.rows)
            bar.update(1)
    pm = PrecisionMap(tuple(rows), part.protocol, part.target_F_mm, part.azimuths_deg)
    if args.plot:
        plot_map(pm, args.plot, title=geom.name)
    if args.json:
        print(json.dumps({"geometry": geom.name, **pm.to_dict()}, indent=2))
    else:
        print(format_map(pm, geom.name))
    if args.plot:
        note(args, f"wrote {args.plot}")
    return 0
