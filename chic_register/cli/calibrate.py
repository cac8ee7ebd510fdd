"""chic-register calibrate: a geometry file scaled to one printed fiducial on one scanner, from a volume of it."""

from __future__ import annotations

import json

from chic_register.cli.console import note
from chic_register.cli.inputs import prior_options, read_image_inputs, register_inputs

HELP = "scale a geometry file to a printed fiducial on a scanner, from a volume of it"
DESCRIPTION = ("Register a volume (or several slices) of one printed fiducial, measure the image's scale (the "
               "print's size against its geometry file, times the scanner's calibration) and write a geometry "
               "file scaled by it, with the calibration recorded in its source. Single slices registered with it "
               "need no scale of their own. Exit code 3 when the scans do not register.")


def add_parser(subparsers) -> None:
    """The calibrate subcommand and its flags."""
    c = subparsers.add_parser("calibrate", help=HELP, description=DESCRIPTION)
    c.set_defaults(run=run)
    c.add_argument("images", nargs="+", metavar="SCAN", help="a volume, or several slices of one fiducial")
    c.add_argument("--geometry", required=True, help="geometry.yaml written by chic-design build")
    c.add_argument("--out", required=True, metavar="FILE", help="the calibrated geometry file to write")
    c.add_argument("--slices", nargs="+", metavar="K", help="for a volume: the slice indices or ranges to use")
    c.add_argument("--series", metavar="ID", default=None, help="the DICOM series of a folder holding several")
    c.add_argument("--pixel-spacing", nargs=2, type=float, metavar=("ROW", "COL"),
                   help="pixel spacing (mm) for PNG/TIFF/NPY images")
    c.add_argument("--prior", metavar="FILE", help="as for solve: a pose file, or RAS, LPS, ...")
    c.add_argument("--prior-max-deg", type=float, default=60.0, metavar="DEG", help="as for solve (default 60)")
    c.add_argument("--json", action="store_true", help="print the calibration record as one JSON object")


def run(args) -> int:
    """Register the scans, scale the geometry, write it atomically."""
    # here, not at the top: keeps chic-register's start-up fast (every command module is imported)
    from chic_register.model.geometry import load_geometry, write_geometry
    from chic_register.studies.scale_calibration import calibrated_geometry

    geom = load_geometry(args.geometry)
    slices, skip, volume = read_image_inputs(args)
    reg = register_inputs(slices, skip, volume, geom, **prior_options(args))
    out = calibrated_geometry(geom, reg, args.images)
    path = write_geometry(out, args.out)
    record = out.source["calibration"]
    if args.json:
        print(json.dumps(record, indent=2))
    else:
        print(f"calibration factor {record['factor']:.5f} (SD {record['factor_sd']:.5f}) from "
              f"{record['slices_used']} slices: lengths in F x {record['factor']:.5f}")
    note(args, f"wrote {path}")
    return 0
