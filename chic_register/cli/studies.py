"""``chic-register evaluate``, ``reslice`` and ``precision`` (the command layer): the accuracy studies.

``evaluate`` repeats the paper's simulation study, ``reslice`` registers oblique
slices reformatted from a volume at known poses (the paper's Table II), and
``precision`` prints the design's Cramer-Rao precision map.
"""

from __future__ import annotations

import json
import math
import sys

from chic_register.cli.inputs import load_reference
from chic_register.errors import ChicRegisterError, NoLock


def run_evaluate(args) -> int:
    import math

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
                           slice_thickness_mm=args.slice_thickness, progress=not args.json)
        studies[kind] = result
        if args.out:
            written = save_plots(result, args.out, tag=f"-{kind}")
            if not args.json:
                print("wrote " + ", ".join(str(p) for p in written), file=sys.stderr)
        if not args.json:
            print(format_summary(result))
            print()
    if args.json:
        print(json.dumps({k: v.to_dict() for k, v in studies.items()}, indent=1))
    return 0


def run_reslice(args) -> int:
    import math
    from pathlib import Path

    from chic_register.io.images import MAX_SPACING_MM, MIN_SPACING_MM
    from chic_register.io.volumes import read_volume
    from chic_register.model.geometry import load_geometry
    from chic_register.studies.reslice import default_depths, reslice, reslice_study

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
    study = reslice_study(vol, geom, T_ref, depths_mm=depths, tilt_deg=args.tilt, azimuth_deg=args.azimuth,
                          twist_deg=args.twist, shape=(args.size, args.size),
                          pixel_spacing_mm=(args.pixel_size, args.pixel_size), slice_thickness_mm=args.slice_thickness)
    if args.save_slices:
        from chic_register.io.dicom import write_dicom
        from chic_register.model.pose import slice_frame

        folder = Path(args.save_slices)
        if not folder.is_dir():
            from chic_register.util.atomic import check_parent

            check_parent(folder)  # the named folder is made; a missing parent is an error
            folder.mkdir()
        for n, d in enumerate(study.settings["depths_mm"]):
            S = T_ref @ slice_frame(d, args.tilt, args.azimuth, args.twist)
            sl = reslice(vol, S, (args.size, args.size), (args.pixel_size, args.pixel_size),
                         slice_thickness_mm=args.slice_thickness)
            write_dicom(sl, folder / f"reslice_{n:03d}_depth_{d:.2f}.dcm", instance_number=n + 1)
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


def run_precision(args) -> int:
    from chic_register.model.geometry import load_geometry
    from chic_register.precision.crlb import Protocol, precision_map
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
    pm = precision_map(geom, protocol, args.depths, args.tilts, args.target, n_azimuths=args.azimuths)
    if args.plot:
        plot_map(pm, args.plot, title=geom.name)
    if args.json:
        print(json.dumps({"geometry": geom.name, **pm.to_dict()}, indent=2))
    else:
        print(format_map(pm, geom.name))
        if args.plot:
            print(f"wrote {args.plot}")
    return 0
