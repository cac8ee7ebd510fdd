"""chic-register reslice: reformat a volume into oblique slices at known poses and register each (the paper's Table II)."""

from __future__ import annotations

import json
import math
from pathlib import Path

from chic_register.cli.console import note, progress_bar
from chic_register.cli.inputs import load_reference
from chic_register.errors import ChicRegisterError, NoLock

HELP = "reformat a volume into oblique slices at known poses, register each (the paper's Table II)"
DESCRIPTION = ("Reformat a volume into oblique slices at known poses and register each (the paper's Table II). Exit "
               "code 3 when no slice locks.")


def add_parser(subparsers) -> None:
    """The reslice subcommand and its flags."""
    r = subparsers.add_parser("reslice", help=HELP, description=DESCRIPTION)
    r.set_defaults(run=run)
    r.add_argument("volume", metavar="VOLUME", help=".nii, .nii.gz, .nrrd, .mha or a DICOM series folder")
    r.add_argument("--series", metavar="ID", default=None,
                   help="the DICOM series to read from a folder holding several (its SeriesNumber or SeriesInstanceUID)")
    r.add_argument("--geometry", required=True, help="geometry.yaml")
    r.add_argument("--reference", required=True, metavar="FILE",
                   help="the fiducial's pose in the volume: a JSON file with T_scanner_from_fiducial "
                        "(simulate's .truth.json or solve --json output) or a .tfm written by solve --tfm")
    r.add_argument("--tilt", type=float, default=15.0, metavar="DEG", help="tilt of every slice (default 15)")
    r.add_argument("--azimuth", type=float, default=0.0, metavar="DEG", help="azimuth (deg, default 0)")
    r.add_argument("--twist", type=float, default=0.0, metavar="DEG", help="twist (deg, default 0)")
    r.add_argument("--depths", nargs="+", type=float, metavar="MM",
                   help="depths of the slices (default: every --depth-step mm across the body)")
    r.add_argument("--depth-step", type=float, default=2.0, metavar="MM", help="default depth spacing (default 2)")
    r.add_argument("--size", type=int, default=256, metavar="N", help="slice size N x N pixels (default 256)")
    r.add_argument("--pixel-size", type=float, default=0.5, metavar="MM", help="square pixel size (default 0.5)")
    r.add_argument("--slice-thickness", type=float, default=0.0, metavar="MM",
                   help="average a slab this thick (default 0: one plane)")
    r.add_argument("--save-slices", metavar="DIR", help="also write the reformatted slices as DICOM files")
    r.add_argument("--json", action="store_true", help="print one JSON object: settings, summary, every slice")


def run(args) -> int:
    """Reslice, register every slice (with a progress bar on stderr), print the table or the JSON."""
    # here, not at the top: keeps chic-register's start-up fast (every command module is imported)
    from chic_register.io.limits import MAX_SPACING_MM, MIN_SPACING_MM
    from chic_register.io.volumes import read_volume
    from chic_register.model.geometry import load_geometry
    from chic_register.pipeline.register import register
    from chic_register.studies.reslice import default_depths, reslice_study

    checks = [
        (8 <= args.size <= 4096, f"--size must be 8..4096 pixels, got {args.size}"),
        (MIN_SPACING_MM <= args.pixel_size <= MAX_SPACING_MM,
         f"--pixel-size must be {MIN_SPACING_MM:g}..{MAX_SPACING_MM:g} mm, got {args.pixel_size:g}"),
        (args.slice_thickness >= 0, f"--slice-thickness must be >= 0 mm, got {args.slice_thickness:g}"),
        (0 <= args.tilt < 90, f"--tilt must be in [0, 90) deg, got {args.tilt:g}"),
        (0.01 <= args.depth_step <= 1000, f"--depth-step must be 0.01..1000 mm, got {args.depth_step:g}"),
        (args.depths is None or (len(args.depths) <= 10000 and all(math.isfinite(d) for d in args.depths)),
         "--depths takes at most 10000 finite depths (mm)"),
        (all(math.isfinite(v) for v in (args.azimuth, args.twist, args.pixel_size, args.slice_thickness)),
         "--azimuth, --twist, --pixel-size and --slice-thickness must be finite numbers"),
        (args.slice_thickness <= 100, f"--slice-thickness must be at most 100 mm, got {args.slice_thickness:g}"),
    ]
    for ok, message in checks:
        if not ok:
            raise ChicRegisterError(message)
    geom = load_geometry(args.geometry)
    T_ref = load_reference(args.reference)
    vol = read_volume(args.volume, args.series)
    depths = args.depths if args.depths else default_depths(geom, args.tilt, args.depth_step)
    with progress_bar(len(depths), "reslice and register", "slice") as bar:
        def register_one(slices, geometry, **options):
            try:
                return register(slices, geometry, **options)
            finally:
                bar.update(1)

        study = reslice_study(vol, geom, T_ref, depths_mm=depths, tilt_deg=args.tilt, azimuth_deg=args.azimuth,
                              twist_deg=args.twist, shape=(args.size, args.size),
                              pixel_spacing_mm=(args.pixel_size, args.pixel_size),
                              slice_thickness_mm=args.slice_thickness, register=register_one)
    if args.save_slices:
        _save_slices(args, vol, T_ref, study.settings["depths_mm"])
    if args.json:
        print(json.dumps({"status": "ok" if study.locked else "no_lock", "volume": str(args.volume),
                          "reference": str(args.reference), **study.to_dict()}, indent=2, default=float))
    else:
        print(f"{args.volume}: {len(study.results)} slices resliced at tilt {args.tilt:g} deg, "
              f"depths {depths[0]:.1f}..{depths[-1]:.1f} mm")
        print(study.table())
        for r in study.results:
            if r.status != "ok":
                print(f"  depth {r.depth_mm:.2f} mm: no lock: {r.reason}")
    return 0 if study.locked else NoLock.exit_code


def _save_slices(args, vol, T_ref, depths) -> None:
    """--save-slices DIR: each reformatted slice as a DICOM file, one "wrote" line each."""
    # here, not at the top: keeps chic-register's start-up fast (every command module is imported)
    from chic_register.io.dicom import write_dicom
    from chic_register.model.pose import slice_frame
    from chic_register.studies.reslice import reslice
    from chic_register.util.atomic import check_parent

    folder = Path(args.save_slices)
    if not folder.is_dir():
        check_parent(folder)  # the named folder is made; a missing parent is an error
        folder.mkdir()
    for n, d in enumerate(depths):
        S = T_ref @ slice_frame(d, args.tilt, args.azimuth, args.twist)
        sl = reslice(vol, S, (args.size, args.size), (args.pixel_size, args.pixel_size),
                     slice_thickness_mm=args.slice_thickness)
        path = write_dicom(sl, folder / f"reslice_{n:03d}_depth_{d:.2f}.dcm", instance_number=n + 1)
        note(args, f"wrote {path}")
