"""chic-register simulate: a synthetic slice or volume at a known pose, and its truth file beside it."""

from __future__ import annotations

from pathlib import Path

from chic_register.cli.console import note, status
from chic_register.errors import ChicRegisterError

HELP = "write a synthetic slice at a known pose, with its truth"
DESCRIPTION = ("Write a synthetic slice (or volume) at a known pose and, beside it, its truth file (the pose, the "
               "tube crossings in pixels and, with a tool, the tool tip).")


def add_parser(subparsers) -> None:
    """The simulate subcommand and its flags."""
    m = subparsers.add_parser("simulate", help=HELP, description=DESCRIPTION)
    m.set_defaults(run=run)
    m.add_argument("--geometry", required=True, help="geometry.yaml")
    m.add_argument("--depth", type=float, required=True, metavar="MM", help="depth of the axis crossing (mm)")
    m.add_argument("--tilt", type=float, default=0.0, metavar="DEG", help="tilt (deg, default 0)")
    m.add_argument("--azimuth", type=float, default=0.0, metavar="DEG", help="azimuth (deg, default 0)")
    m.add_argument("--twist", type=float, default=0.0, metavar="DEG", help="twist (deg, default 0)")
    m.add_argument("--out", required=True, help="output file: .dcm (DICOM MR), .npy, .png or .tif")
    m.add_argument("--noise", default="none", choices=["none", "uniform", "rician"],
                   help="none, the paper's uniform white noise, or MRI magnitude (Rician) noise")
    m.add_argument("--noise-level", type=float, default=0.1, metavar="X",
                   help="uniform noise amplitude, fluid = 1 (default 0.1)")
    m.add_argument("--snr", type=float, default=20.0, metavar="S", help="Rician noise SNR of fluid (default 20)")
    m.add_argument("--slice-thickness", type=float, default=None, metavar="MM",
                   help="slice thickness (default 2; CT 1)")
    m.add_argument("--pixel-size", type=float, default=None, metavar="MM",
                   help="square pixel size (default 0.5; CT 0.6)")
    m.add_argument("--size", type=int, default=None, metavar="N", help="image size N x N pixels (default 256; CT 512)")
    m.add_argument("--modality", default="mr", choices=["mr", "ct"],
                   help="mr: fluid = 1 (default); ct: Hounsfield units (air -1000, plates, contrast rods, Gaussian "
                        "noise, -2048 outside the reconstruction circle; DICOM CT with RescaleIntercept -1024)")
    m.add_argument("--rod-hu", type=float, default=1500.0, metavar="HU", help="CT: the rods' fill (default 1500)")
    m.add_argument("--plate-hu", type=float, default=150.0, metavar="HU", help="CT: the plates (default 150)")
    m.add_argument("--plate-mm", type=float, default=4.0, metavar="MM",
                   help="CT: plate thickness around each plane of 3+ coplanar rods (default 4; 0: none)")
    m.add_argument("--noise-hu", type=float, default=18.0, metavar="HU", help="CT: Gaussian noise sigma (default 18)")
    m.add_argument("--skull", action="store_true", help="CT: a bone ring (+1000 HU) around brain inside the frame")
    m.add_argument("--metal", action="store_true", help="CT: a metal blob with bright and dark streaks through the image")
    m.add_argument("--seed", type=int, default=None, metavar="N", help="random seed (noise, distractors)")
    m.add_argument("--distractors", type=int, default=0, metavar="N",
                   help="N anatomy-like bright blobs outside the fiducial (default 0)")
    m.add_argument("--bore-signal", type=float, default=0.0, metavar="X",
                   help="brightness of a tool in the bore (default 0: none)")
    m.add_argument("--missing", nargs="+", default=[], metavar="ID", help="tube ids left unfilled")
    m.add_argument("--allow-empty", action="store_true",
                   help="write the slice even when no tube crosses it (a missed slice, to test refusals)")
    m.add_argument("--center-offset", nargs=2, type=float, default=(0.0, 0.0), metavar=("X", "Y"),
                   help="axis crossing from the image centre, mm along columns and rows (default 0 0)")
    m.add_argument("--image-position", nargs=3, type=float, metavar=("X", "Y", "Z"),
                   help="DICOM only: scanner (LPS) position of pixel (0, 0) (default: image centre at 0)")
    m.add_argument("--image-orientation", nargs=6, type=float, metavar="V",
                   help="DICOM only: col_dir and row_dir in the scanner (default 1 0 0 0 1 0)")
    m.add_argument("--blob-width", type=float, default=1.0, metavar="FACTOR",
                   help="draw each blob FACTOR x its tube's nominal width, as real images do (0.7-2.5; "
                        "> 1 blurs, < 1 narrows; default 1)")
    m.add_argument("--scanner-scale", nargs=2, type=float, default=(0.0, 0.0), metavar=("SX", "SY"),
                   help="scanner effect: the image larger than the world by SX %% along its columns and SY %% along "
                        "its rows, about the isocentre (a gradient calibration error; real scanners: within 1-2 %%)")
    m.add_argument("--nonlinearity", type=float, default=0.0, metavar="MM",
                   help="scanner effect: gradient non-linearity, a displacement growing with the cube of the distance "
                        "from the isocentre, MM at 100 mm (a few mm is typical; default 0)")
    m.add_argument("--shading", type=float, default=0.0, metavar="X",
                   help="scanner effect: a receive coil's smooth gain across the field, X peak to peak (0..1)")
    m.add_argument("--tissue", type=int, default=0, metavar="N",
                   help="scanner effect: N tissue-like bright regions 5-30 mm wide at 30-100 %% of the fluid's signal")
    m.add_argument("--volume-shape", nargs=3, type=int, metavar=("NX", "NY", "NZ"),
                   help="volume mode: write a 3-D volume of NX x NY x NZ voxels (--out .nii, .nii.gz, .nrrd, "
                        ".mha or a folder for a DICOM series); its middle k-plane cuts the fiducial at "
                        "--depth/--tilt/--azimuth/--twist")
    m.add_argument("--voxel-size", nargs="+", type=float, metavar="MM",
                   help="volume mode: voxel size, one value (isotropic) or three (i j k) (default 0.5 0.5 1)")


def _blob_width_check(factor: float) -> tuple[bool, str]:
    from chic_register.imaging.blob_width import BLOB_WIDTH_RANGE  # here, not at the top: keeps start-up fast

    lo, hi = BLOB_WIDTH_RANGE
    return lo <= factor <= hi, f"--blob-width must be {lo:g}..{hi:g} (x the nominal diameter), got {factor:g}"


def run(args) -> int:
    """Simulate one slice (or, with --volume-shape, a volume) and write it with its truth."""
    if args.volume_shape is not None:
        return _run_volume(args)
    import numpy as np  # here, not at the top: keeps chic-register's start-up fast (every command module is imported)

    from chic_register.imaging.ct import CT_PIXEL_MM, CT_SHAPE, CT_THICKNESS_MM, CTScene  # here: fast start-up
    from chic_register.imaging.simulate import DICOM_SUFFIXES, simulate_slice, write_simulated
    from chic_register.io.images import PLAIN_SUFFIXES
    from chic_register.io.limits import MAX_SPACING_MM, MIN_SPACING_MM
    from chic_register.model.geometry import load_geometry

    ct = args.modality == "ct"
    if args.size is None:
        args.size = CT_SHAPE[0] if ct else 256
    if args.pixel_size is None:
        args.pixel_size = CT_PIXEL_MM if ct else 0.5
    if args.slice_thickness is None:
        args.slice_thickness = CT_THICKNESS_MM if ct else 2.0
    out = Path(args.out)
    checks = [
        (not ct or args.noise == "none", "--noise applies to MR; a CT slice's noise is --noise-hu"),
        (not ct or out.suffix.lower() not in (".png", ".tif", ".tiff"),
         "--modality ct writes Hounsfield units: .dcm (DICOM CT) or .npy"),
        (all(np.isfinite(v) and abs(v) <= 1e4 for v in (args.rod_hu, args.plate_hu, args.noise_hu))
         and args.noise_hu >= 0 and 0 <= args.plate_mm <= 50,
         "--rod-hu, --plate-hu, --noise-hu must be finite within +-10000 (noise >= 0), --plate-mm 0..50"),
        (args.size >= 8 and args.size <= 4096, f"--size must be 8..4096 pixels, got {args.size}"),
        (np.isfinite(args.pixel_size) and MIN_SPACING_MM <= args.pixel_size <= MAX_SPACING_MM,
         f"--pixel-size must be {MIN_SPACING_MM:g}..{MAX_SPACING_MM:g} mm, got {args.pixel_size:g}"),
        (0 <= args.slice_thickness <= 100, f"--slice-thickness must be 0..100 mm, got {args.slice_thickness:g}"),
        (args.noise_level >= 0 and np.isfinite(args.noise_level), f"--noise-level must be >= 0, got {args.noise_level:g}"),
        (args.snr > 0 and np.isfinite(args.snr), f"--snr must be > 0, got {args.snr:g}"),
        _blob_width_check(args.blob_width),
        (0 <= args.distractors <= 1000, f"--distractors must be 0..1000, got {args.distractors}"),
        (all(np.isfinite(v) and abs(v) <= 1e4 for v in (*args.center_offset, *(args.image_position or ()),
                                                          *(args.image_orientation or ()))),
         "--center-offset, --image-position and --image-orientation must be finite numbers within +-10000 mm"),
        (args.bore_signal >= 0 and np.isfinite(args.bore_signal), f"--bore-signal must be >= 0, got {args.bore_signal:g}"),
        (all(np.isfinite(v) and abs(v) <= 1e4 for v in (args.depth, args.tilt, args.azimuth, args.twist)),
         "--depth, --tilt, --azimuth and --twist must be finite numbers within +-10000"),
        (out.suffix.lower() in DICOM_SUFFIXES or not (args.image_position or args.image_orientation),
         "--image-position/--image-orientation apply to DICOM output only (.dcm)"),
        (all(np.isfinite(v) and abs(v) <= 10 for v in args.scanner_scale),
         "--scanner-scale takes two per cent values within +-10"),
        (np.isfinite(args.nonlinearity) and 0 <= args.nonlinearity <= 20,
         f"--nonlinearity must be 0..20 mm, got {args.nonlinearity:g}"),
        (np.isfinite(args.shading) and 0 <= args.shading <= 1, f"--shading must be 0..1, got {args.shading:g}"),
        (0 <= args.tissue <= 100, f"--tissue must be 0..100 regions, got {args.tissue}"),
        (not ct or not _effects_asked(args), "--scanner-scale, --nonlinearity, --shading and --tissue apply to MR"),
        (not out.is_dir(), f"--out {out} is a directory; give a file name (.dcm, .npy, .png or .tif)"),
        (out.suffix.lower() in DICOM_SUFFIXES + PLAIN_SUFFIXES,
         f"--out {out}: unsupported suffix {out.suffix!r}; allowed: {', '.join(DICOM_SUFFIXES + PLAIN_SUFFIXES)}"),
    ]
    for ok, message in checks:
        if not ok:
            raise ChicRegisterError(message)
    geom = load_geometry(args.geometry)
    plain = out.suffix.lower() not in DICOM_SUFFIXES
    try:
        sim = simulate_slice(
            geom, args.depth, args.tilt, args.azimuth, args.twist,
            shape=(args.size, args.size),
            pixel_spacing_mm=(args.pixel_size, args.pixel_size),
            slice_thickness_mm=args.slice_thickness,
            center_offset_mm=tuple(args.center_offset),
            noise=args.noise, noise_level=args.noise_level, snr=args.snr,
            distractors=args.distractors, bore_signal=args.bore_signal,
            missing_tubes=tuple(args.missing),
            image_position=(0.0, 0.0, 0.0) if plain else args.image_position,
            image_orientation=args.image_orientation,
            rng=np.random.default_rng(args.seed), blob_width=args.blob_width,
            modality="CT" if ct else "MR",
            ct=CTScene(rod_hu=args.rod_hu, plate_hu=args.plate_hu, plate_mm=args.plate_mm, noise_hu=args.noise_hu,
                       skull=args.skull, metal=args.metal) if ct else None,
        )
        n_in_view = len(sim.truth.centres_px)
        effects_doc = {}
        if _effects_asked(args):
            sim, effects_doc = _with_scanner_effects(sim, geom, args, plain)
        if n_in_view == 0 and not args.allow_empty:  # an empty image is a mistake unless asked for
            raise ChicRegisterError(
                f"--depth {args.depth:g} --tilt {args.tilt:g}: no tube crosses the image (the body spans "
                f"z = 0..{geom.body.length:g} mm; check --depth, --tilt, --center-offset, or pass --allow-empty "
                "for a deliberately missed slice); nothing written")
        extra = {"geometry_file": str(args.geometry), "geometry_sha256": geom.to_dict()["sha256"], "seed": args.seed,
                 **effects_doc}
        image_path, truth_file = write_simulated(sim, out, extra)
    except ValueError as exc:
        raise ChicRegisterError(str(exc)) from None
    except OSError as exc:
        raise ChicRegisterError(f"{out}: cannot write ({exc.strerror or exc})") from None
    a = sim.truth.angles
    note(args, f"wrote {image_path} ({args.size}x{args.size}, {args.pixel_size:g} mm pixels, "
               f"depth {a.depth_mm:.3f} mm, tilt {a.tilt_deg:.3f}, azimuth {a.azimuth_deg:.3f}, "
               f"twist {a.twist_deg:.3f} deg, {n_in_view} tubes in view) and {truth_file}")
    if n_in_view < len(geom.tubes):
        status(f"warning: only {n_in_view} of {len(geom.tubes)} tubes in view")
    return 0


def _effects_asked(args) -> bool:
    return bool(any(args.scanner_scale) or args.nonlinearity or args.shading or args.tissue)


def _with_scanner_effects(sim, geom, args, plain: bool):
    """``sim`` as a scanner with the asked effects shows it, and the truth file's record of them: the effects and
    the pose the distorted image shows (``T_scanner_from_fiducial_shown``), which is what a solve can find."""
    import numpy as np  # here, not at the top: keeps start-up fast

    from chic_register.imaging.scanner import ScannerEffects, image_centre_mm  # here: fast start-up
    from chic_register.imaging.simulate import SimulatedSlice  # here: fast start-up
    from chic_register.studies.distortion import distort  # here: fast start-up

    # a plain image has no placement: its isocentre is taken at the image centre
    iso = image_centre_mm(sim.slice) if plain else np.zeros(3)
    effects = ScannerEffects((args.scanner_scale[0] / 100.0, args.scanner_scale[1] / 100.0), args.nonlinearity,
                             args.shading, args.tissue, tuple(float(v) for v in iso))
    rng = np.random.default_rng(None if args.seed is None else args.seed + 1)
    shown_slice, shown = distort(sim.slice, sim.truth.T_scanner_from_fiducial, geom, effects, rng)
    doc = {"scanner_effects": {"scale_percent": [float(v) for v in args.scanner_scale],
                               "nonlinearity_mm_at_100mm": float(args.nonlinearity), "shading": float(args.shading),
                               "tissue": int(args.tissue), "isocentre_mm": [float(v) for v in iso]},
           "T_scanner_from_fiducial_shown": np.asarray(shown).tolist()}
    return SimulatedSlice(shown_slice, sim.truth), doc


def _run_volume(args) -> int:
    """simulate --volume-shape: a synthetic volume and <out>.truth.json."""
    import numpy as np  # here, not at the top: keeps chic-register's start-up fast (every command module is imported)

    from chic_register.imaging.simulate import simulate_volume, tool_truth, truth_path
    from chic_register.io.limits import MAX_SPACING_MM, MAX_VOXELS, MIN_SPACING_MM
    from chic_register.io.volumes import write_volume
    from chic_register.model.geometry import load_geometry
    from chic_register.model.pose import invert, slice_frame
    from chic_register.util.atomic import write_json

    nx, ny, nz = args.volume_shape
    given = args.voxel_size or [0.5, 0.5, 1.0]
    vs = given * 3 if len(given) == 1 else given
    unsupported = [flag for flag, on in (("--distractors", args.distractors), ("--bore-signal", args.bore_signal),
                                         ("--missing", args.missing), ("--image-position", args.image_position),
                                         ("--image-orientation", args.image_orientation),
                                         ("--modality ct", args.modality == "ct"),
                                         ("--scanner-scale, --nonlinearity, --shading, --tissue",
                                          _effects_asked(args))) if on]
    checks = [
        (min(nx, ny, nz) >= 2 and max(nx, ny, nz) <= 1024, f"--volume-shape must be 2..1024 voxels each, got {nx} {ny} {nz}"),
        (nx * ny * nz <= MAX_VOXELS, f"--volume-shape {nx} {ny} {nz} is {nx * ny * nz} voxels; at most {MAX_VOXELS}"),
        (len(vs) == 3 and all(np.isfinite(v) and MIN_SPACING_MM <= v <= MAX_SPACING_MM for v in vs),
         f"--voxel-size takes one or three sizes in {MIN_SPACING_MM:g}..{MAX_SPACING_MM:g} mm, "
         f"got {' '.join(f'{v:g}' for v in given)}"),
        (not unsupported, f"{', '.join(unsupported)}: not available in volume mode"),
        _blob_width_check(args.blob_width),
        (all(np.isfinite(v) and abs(v) <= 1e4 for v in (args.depth, args.tilt, args.azimuth, args.twist)),
         "--depth, --tilt, --azimuth and --twist must be finite numbers within +-10000"),
    ]
    for ok, message in checks:
        if not ok:
            raise ChicRegisterError(message)
    geom = load_geometry(args.geometry)
    # axis-aligned volume centred on the scanner origin: the middle k-plane's frame is the identity
    T = invert(slice_frame(args.depth, args.tilt, args.azimuth, args.twist))
    status(f"simulating {nx}x{ny}x{nz} voxels")  # seconds for a large volume
    try:
        sv = simulate_volume(geom, T, (nx, ny, nz), vs, noise=args.noise, noise_level=args.noise_level,
                             snr=args.snr, rng=np.random.default_rng(args.seed), blob_width=args.blob_width)
    except ValueError as exc:
        raise ChicRegisterError(str(exc)) from None
    out = write_volume(sv.volume, args.out)
    doc = {**sv.truth_dict(), "middle_plane": {"depth_mm": args.depth, "tilt_deg": args.tilt,
                                               "azimuth_deg": args.azimuth, "twist_deg": args.twist},
           "volume": Path(out).name, "geometry_file": str(args.geometry),
           "geometry_sha256": geom.to_dict()["sha256"], "seed": args.seed}
    if geom.tool is not None:
        doc.update(tool_truth(geom.tool.T_fiducial_from_tool, sv.T_scanner_from_fiducial))
    tp = write_json(truth_path(out), doc)
    note(args, f"wrote {out} ({nx}x{ny}x{nz} voxels of {' x '.join(f'{v:g}' for v in vs)} mm; middle plane at "
               f"depth {args.depth:g} mm, tilt {args.tilt:g} deg) and {tp}")
    return 0
