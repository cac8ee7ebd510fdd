"""``chic-register``: register MRI slices of a CHIC fiducial, simulate slices, evaluate accuracy.

A thin layer over the library (:mod:`chic_register.solve`,
:mod:`chic_register.simulate`, :mod:`chic_register.evaluate`).
``main(argv) -> int`` is testable in-process. Exit codes (docs/interfaces.md section 4):
0 ok, 2 bad input, 3 no trustworthy pose (``no_lock``), 4 pose ok but an output (``--tfm``,
``--scene``, ``--overlay``, OpenIGTLink) failed: the pose is still printed.
"""

from __future__ import annotations

import argparse
import json
import math
import sys

from . import __version__, exits
from .errors import ChicRegisterError, NoLock

PROG = "chic-register"


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="chic-register", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"chic-register {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("solve", help="register one or more slices: one pose from all of them")
    s.add_argument("images", nargs="+", metavar="IMAGE", help="DICOM, PNG, TIFF or NPY slices")
    s.add_argument("--geometry", required=True, help="geometry.yaml written by chic-design build")
    s.add_argument("--json", action="store_true", help="print one JSON object (docs/interfaces.md section 4)")
    s.add_argument("--pixel-spacing", nargs=2, type=float, metavar=("ROW", "COL"),
                   help="pixel spacing (mm) for PNG/TIFF/NPY images")
    s.add_argument("--overlay", metavar="PNG", help="draw the slice with detections, ellipse and labels")
    s.add_argument("--slices", nargs="+", metavar="K",
                   help="for a volume IMAGE (.nii, .nii.gz, .nrrd, .mha or a DICOM series folder): "
                        "indices (5) or ranges (5-11) of its slices to register jointly; each must lock. "
                        "Default: every slice that shows the fiducial (the others are listed as skipped)")
    s.add_argument("--prior", metavar="FILE",
                   help="an approximate pose of the fiducial (JSON with T_scanner_from_fiducial, or .tfm): "
                        "only poses turned less than --prior-max-deg from it are considered. Needed for a "
                        "geometry that maps onto itself under a rotation (the classic Z-frame)")
    s.add_argument("--prior-max-deg", type=float, default=60.0, metavar="DEG",
                   help="largest rotation from --prior (default 60)")
    s.add_argument("--tfm", metavar="FILE", help="also write the pose as an ITK transform file for 3D Slicer "
                   "(holds T_fiducial_from_scanner, LPS; see docs/interfaces.md)")
    s.add_argument("--scene", metavar="DIR", help="also write a 3D Slicer scene (DIR/scene.mrml with the slices, "
                   "the fiducial and tool models under their transforms, detected and predicted tube centres)")
    _add_igtl_args(s)
    s.add_argument("--target", nargs=3, type=float, metavar=("X", "Y", "Z"),
                   help="point of F (mm) whose predicted TRE is reported (default: the tool tip, else the body centre)")
    s.add_argument("--max-tre", type=float, metavar="MM",
                   help="refuse (no_lock, reason 'imprecise') a pose whose predicted TRE exceeds MM")
    s.add_argument("--trust", nargs=2, type=float, metavar=("MM", "DEG"),
                   help="the verification's precision limits: refuse a pose whose 3-sigma predicted error exceeds "
                        "MM at the frame centre or DEG in rotation (default 1 0.75; a single near-normal slice "
                        "of a CHIC fiducial knows its tilt to ~0.2-0.25 deg at 1 sigma)")

    c = sub.add_parser("precision", help="the design's precision map: Cramer-Rao bound over depth and tilt")
    c.add_argument("--geometry", required=True, help="geometry.yaml")
    c.add_argument("--pixel-size", type=float, default=0.5, metavar="MM", help="square pixel size (default 0.5)")
    c.add_argument("--slice-thickness", type=float, default=2.0, metavar="MM", help="slice thickness (default 2)")
    c.add_argument("--snr", type=float, default=20.0, metavar="S", help="fluid SNR, Rician noise (default 20)")
    c.add_argument("--slices", type=int, default=1, metavar="N", help="parallel slices per pose (default 1)")
    c.add_argument("--slice-spacing", type=float, default=None, metavar="MM",
                   help="centre-to-centre slice spacing (default: the slice thickness)")
    c.add_argument("--target", nargs=3, type=float, metavar=("X", "Y", "Z"),
                   help="TRE point in F (mm; default: the tool tip, else the body centre)")
    c.add_argument("--depths", nargs="+", type=float, metavar="MM", help="depths (default: 10-90 %% of the body, 9)")
    c.add_argument("--tilts", nargs="+", type=float, default=[0.0, 15.0, 30.0, 45.0], metavar="DEG",
                   help="tilts (default 0 15 30 45)")
    c.add_argument("--azimuths", type=int, default=4, metavar="N", help="azimuths per cell (default 4)")
    c.add_argument("--json", action="store_true", help="print one JSON object")
    c.add_argument("--plot", metavar="PNG", help="write the precision map plot")

    m = sub.add_parser("simulate", help="write a synthetic slice at a known pose, with its truth")
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
    m.add_argument("--slice-thickness", type=float, default=2.0, metavar="MM", help="slice thickness (default 2)")
    m.add_argument("--pixel-size", type=float, default=0.5, metavar="MM", help="square pixel size (default 0.5)")
    m.add_argument("--size", type=int, default=256, metavar="N", help="image size N x N pixels (default 256)")
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
    m.add_argument("--volume-shape", nargs=3, type=int, metavar=("NX", "NY", "NZ"),
                   help="volume mode: write a 3-D volume of NX x NY x NZ voxels (--out .nii, .nii.gz, .nrrd, "
                        ".mha or a folder for a DICOM series); its middle k-plane cuts the fiducial at "
                        "--depth/--tilt/--azimuth/--twist")
    m.add_argument("--voxel-size", nargs="+", type=float, metavar="MM",
                   help="volume mode: voxel size, one value (isotropic) or three (i j k) (default 0.5 0.5 1)")

    e = sub.add_parser("evaluate", help="repeat the paper's simulation study and compare")
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

    r = sub.add_parser("reslice", help="reformat a volume into oblique slices at known poses, register each "
                       "(the paper's Table II)")
    r.add_argument("volume", metavar="VOLUME", help=".nii, .nii.gz, .nrrd, .mha or a DICOM series folder")
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

    t = sub.add_parser("track", help="register each new slice as it arrives (a watched folder or OpenIGTLink IMAGEs)")
    t.add_argument("folder", metavar="FOLDER", nargs="?", help="folder the scanner writes slices into "
                   "('-' or none with --igtl-images)")
    t.add_argument("--geometry", required=True, help="geometry.yaml")
    t.add_argument("--pixel-spacing", nargs=2, type=float, metavar=("ROW", "COL"),
                   help="pixel spacing (mm) for PNG/TIFF/NPY images")
    _add_igtl_args(t)
    t.add_argument("--igtl-images", metavar="HOST:PORT",
                   help="instead of watching FOLDER (give '-'), connect to a scanner bridge at HOST:PORT, register "
                        "every IMAGE message it sends and send the pose back on the same connection")
    t.add_argument("--igtl-images-listen", type=int, metavar="PORT",
                   help="as --igtl-images, but listen on PORT for the scanner bridge to connect")
    t.add_argument("--scene", metavar="DIR", help="write a 3D Slicer scene of each pose into DIR/<image name>/")
    t.add_argument("--existing", action="store_true", help="also register files already in the folder")
    t.add_argument("--poll", type=float, default=0.05, metavar="S", help="polling interval (default 0.05 s)")
    t.add_argument("--settle", type=float, default=0.2, metavar="S",
                   help="a file must keep its size this long before it is read (default 0.2 s)")
    t.add_argument("--max-files", type=int, metavar="N", help="stop after N files")
    t.add_argument("--timeout", type=float, metavar="S", help="stop after S seconds")
    t.add_argument("--json", action="store_true", help="print one JSON object per file, then a summary object")
    return p


def _add_igtl_args(p) -> None:
    p.add_argument("--igtl", metavar="HOST:PORT", help="also send the pose over OpenIGTLink to a listening server, "
                   "e.g. 3D Slicer's OpenIGTLinkIF at 127.0.0.1:18944 (TRANSFORMs, quality STRING, STATUS)")
    p.add_argument("--igtl-listen", type=int, metavar="PORT", help="be the OpenIGTLink server instead: listen on "
                   "PORT and send to every peer that connects (0: any free port)")
    p.add_argument("--igtl-wait", type=float, default=10.0, metavar="S",
                   help="with --igtl-listen: wait this long for a first peer before sending (default 10 s)")
    p.add_argument("--igtl-name", default="CHIC", metavar="NAME",
                   help="OpenIGTLink device name (default CHIC; also NAMEToRAS, NAMETool, NAMEToolToRAS, NAMEQuality)")


def _report_failures(delivery) -> None:
    for note in delivery.failed:
        print(f"chic-register: output failed: {note}", file=sys.stderr, flush=True)


def _run_solve(args) -> int:
    from .geometry import load_geometry
    from .outputs import EXIT_OUTPUT_FAILED, Delivery, OutputPlan, deliver, deliver_no_lock
    from .solve import register

    plan = OutputPlan.from_args(args).check()
    geom = load_geometry(args.geometry)
    options = {}
    if args.prior:
        if not (0 < args.prior_max_deg <= 180):
            raise ChicRegisterError(f"--prior-max-deg must be in (0, 180] deg, got {args.prior_max_deg:g}")
        options = {"prior": _load_reference(args.prior, "--prior"), "prior_max_deg": args.prior_max_deg}
    slices, skip = _read_solve_inputs(args)
    extra = {}
    if args.target is not None:
        if not all(math.isfinite(v) for v in args.target):
            raise ChicRegisterError("--target must be three finite numbers (mm in F)")
        extra["target_F_mm"] = tuple(args.target)
    if args.max_tre is not None:
        if not (args.max_tre > 0 and math.isfinite(args.max_tre)):
            raise ChicRegisterError(f"--max-tre must be a positive number of mm, got {args.max_tre:g}")
        extra["max_tre_mm"] = args.max_tre
    if args.trust is not None:
        tre_mm, rot_deg = args.trust
        if not all(math.isfinite(v) and v > 0 for v in args.trust):
            raise ChicRegisterError(f"--trust takes two positive numbers (mm, deg), got {tre_mm:g} {rot_deg:g}")
        extra.update(trust_tre_mm=tre_mm, trust_rot_deg=rot_deg)
    early = Delivery()  # a server that cannot listen is an output failure: the pose still comes
    link = None
    try:
        link = plan.open_link()
    except ChicRegisterError as exc:
        early.failed.append(f"{plan.igtl_flag}: {exc}")
    if plan.igtl_listen is not None and link is not None:
        print(f"chic-register: OpenIGTLink server listening on port {link.port} (a peer may connect now; "
              f"the pose waits up to {plan.igtl_wait_s:g} s for one)", file=sys.stderr, flush=True)
    try:
        try:
            reg = register(slices, geom, skip_failed=skip, **options, **extra)
        except NoLock as exc:
            _report_failures(early)
            _report_failures(deliver_no_lock(plan, exc.reason, geom, slices, link))
            raise
        # the pose is printed first: a failing optional output (overlay, --tfm, --scene, --igtl) must not lose it
        _print_pose(args, reg, geom)
        out = deliver(plan, reg, geom, slices, link)
    finally:
        if link is not None:
            link.close()
    out.failed[:0] = early.failed
    for note in out.done:
        print(f"chic-register: {note}" if args.json else note, file=sys.stderr if args.json else sys.stdout)
    _report_failures(out)
    return EXIT_OUTPUT_FAILED if out.failed else 0


def _print_pose(args, reg, geom) -> None:
    """The pose of ``solve``: one JSON object (``--json``) or the human summary."""
    from .outputs import registration_json, tool_pose

    if args.json:
        print(json.dumps(registration_json(reg, geom), indent=2), flush=True)
        return
    t = reg.timing_ms
    print(f"status: ok ({len(reg.slices)} slice{'s' if len(reg.slices) > 1 else ''} of '{geom.name}'"
          + (f" used, {len(reg.skipped)} skipped" if reg.skipped else "")
          + f", {t['total']:.1f} ms: detect {t['detect']:.1f}, pose {t['pose']:.1f})")
    print("T_scanner_from_fiducial (mm):")
    for row in reg.T_scanner_from_fiducial:
        print("  " + "  ".join(f"{v:11.5f}" for v in row))
    T_tool = tool_pose(reg, geom)
    if T_tool is not None:
        print("T_scanner_from_tool (mm):")
        for row in T_tool:
            print("  " + "  ".join(f"{v:11.5f}" for v in row))
        print("tool tip (scanner, mm): " + ", ".join(f"{v:.3f}" for v in T_tool[:3, 3]))
    for s in reg.slices:
        print(f"{s.source}: depth {s.depth_mm:.3f} mm, tilt {s.tilt_deg:.3f}, azimuth {s.azimuth_deg:.3f}, "
              f"twist {s.twist_deg:.3f} deg; residual RMS {s.residual_rms_mm:.3f} mm over {s.n_tubes} tubes")
        print("  residuals (mm): " + ", ".join(f"{k} {v:.3f}" for k, v in s.residuals_mm.items()))
    for s in reg.skipped:
        print(f"skipped {s.source}: {s.reason}")
    u = reg.uncertainty
    if u is not None:
        sd = [math.sqrt(max(0.0, float(u.covariance[i, i]))) for i in range(6)]
        print(f"predicted TRE {u.predicted_tre_mm:.3f} mm at ({', '.join(f'{v:g}' for v in u.target_F_mm)}) in F; "
              f"SD rotation {max(sd[:3]):.3f} deg, translation {max(sd[3:]):.3f} mm (largest axis); "
              f"image noise sigma {', '.join(f'{n.sigma:.4g}' for n in u.noise)}")
    sys.stdout.flush()


def _blob_width_check(factor: float) -> tuple[bool, str]:
    from .blob_width import BLOB_WIDTH_RANGE

    lo, hi = BLOB_WIDTH_RANGE
    return lo <= factor <= hi, f"--blob-width must be {lo:g}..{hi:g} (x the nominal diameter), got {factor:g}"


def _run_simulate(args) -> int:
    if args.volume_shape is not None:
        return _run_simulate_volume(args)
    from pathlib import Path

    import numpy as np

    from .geometry import load_geometry
    from .imageio import MAX_SPACING_MM, MIN_SPACING_MM, PLAIN_SUFFIXES
    from .simulate import DICOM_SUFFIXES, simulate_slice, write_simulated

    out = Path(args.out)
    checks = [
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
        )
        n_in_view = len(sim.truth.centres_px)
        if n_in_view == 0 and not args.allow_empty:  # issue 10: an empty image was written with exit 0 in silence
            raise ChicRegisterError(
                f"--depth {args.depth:g} --tilt {args.tilt:g}: no tube crosses the image (the body spans "
                f"z = 0..{geom.body.length:g} mm; check --depth, --tilt, --center-offset, or pass --allow-empty "
                "for a deliberately missed slice); nothing written")
        extra = {"geometry_file": str(args.geometry), "geometry_sha256": geom.to_dict()["sha256"], "seed": args.seed}
        image_path, truth_file = write_simulated(sim, out, extra)
    except ValueError as exc:
        raise ChicRegisterError(str(exc)) from None
    except OSError as exc:
        raise ChicRegisterError(f"{out}: cannot write ({exc.strerror or exc})") from None
    a = sim.truth.angles
    print(
        f"wrote {image_path} ({args.size}x{args.size}, {args.pixel_size:g} mm pixels, "
        f"depth {a.depth_mm:.3f} mm, tilt {a.tilt_deg:.3f}, azimuth {a.azimuth_deg:.3f}, twist {a.twist_deg:.3f} deg, "
        f"{n_in_view} tubes in view) and {truth_file}"
    )
    if n_in_view < len(geom.tubes):
        print(f"chic-register: warning: only {n_in_view} of {len(geom.tubes)} tubes in view", file=sys.stderr)
    return 0


def _run_evaluate(args) -> int:
    import math

    from .evaluate import format_summary, run_study, save_plots
    from .geometry import load_geometry

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


# --------------------------------------------------------------------------- volumes, outputs, reslice, track


def _check_spacing_flag(args) -> None:
    """A --pixel-spacing outside the physical range is refused before any file is read."""
    from .imageio import spacing_fault

    if getattr(args, "pixel_spacing", None) is not None:
        fault = spacing_fault(args.pixel_spacing)
        if fault:
            raise ChicRegisterError(f"--pixel-spacing: {fault}")


def _read_solve_inputs(args) -> tuple[list, bool]:
    """The slices of ``solve`` and whether failing ones may be skipped.

    2-D image files as they are; a volume by its ``--slices`` indices and
    ranges, or, without them, every native slice (those that do not lock are
    then skipped and reported).
    """
    from .imageio import read_slices
    from .volume import is_volume_path, read_volume
    from .volume_register import parse_slice_indices

    _check_spacing_flag(args)
    volumes = [p for p in args.images if is_volume_path(p)]
    if args.slices and not volumes:
        raise ChicRegisterError("--slices applies to volume inputs (.nii, .nii.gz, .nrrd, .mha, DICOM series folder)")
    slices = []
    for path in args.images:
        if is_volume_path(path):
            vol = read_volume(path)
            nk = vol.shape[0]
            ks = parse_slice_indices(args.slices, nk) if args.slices else range(nk)
            slices.extend(vol.native_slice(k) for k in ks)
        else:
            slices.extend(read_slices([path], args.pixel_spacing))
    return slices, bool(volumes) and not args.slices


def _load_reference(path, flag: str = "--reference") -> "np.ndarray":
    """T_scanner_from_fiducial from a JSON file (any object with that key) or a .tfm file."""
    from pathlib import Path

    import numpy as np

    from .transforms import SUFFIXES, read_tfm

    p = Path(path)
    if p.suffix.lower() in SUFFIXES:
        return read_tfm(p)
    from .errors import InputFileError
    from .safeload import read_regular_file

    try:
        doc = json.loads(read_regular_file(p, "reference file", max_bytes=1 << 20).decode("utf-8"))
    except InputFileError as exc:
        raise ChicRegisterError(f"{flag} {exc}") from None
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise ChicRegisterError(f"{flag} {p}: not a JSON file ({str(exc).splitlines()[0][:100]})") from None
    T = doc.get("T_scanner_from_fiducial") if isinstance(doc, dict) else None
    try:
        T = np.asarray(T, dtype=float)
    except (TypeError, ValueError):
        T = np.zeros(0)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-5):
        raise ChicRegisterError(f"{flag} {p}: needs key 'T_scanner_from_fiducial' holding a rigid 4x4 matrix")
    return T


def _run_simulate_volume(args) -> int:
    """simulate --volume-shape: a synthetic volume and <out>.truth.json."""
    from pathlib import Path

    import numpy as np

    from .atomic import write_json
    from .geometry import load_geometry
    from .imageio import MAX_SPACING_MM, MIN_SPACING_MM
    from .pose import invert, slice_frame
    from .simulate import truth_path
    from .volume import MAX_VOXELS, simulate_volume, write_volume

    nx, ny, nz = args.volume_shape
    given = args.voxel_size or [0.5, 0.5, 1.0]
    vs = given * 3 if len(given) == 1 else given
    unsupported = [flag for flag, on in (("--distractors", args.distractors), ("--bore-signal", args.bore_signal),
                                         ("--missing", args.missing), ("--image-position", args.image_position),
                                         ("--image-orientation", args.image_orientation)) if on]
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
    tp = write_json(truth_path(out), doc)
    print(f"wrote {out} ({nx}x{ny}x{nz} voxels of {' x '.join(f'{v:g}' for v in vs)} mm; middle plane at depth "
          f"{args.depth:g} mm, tilt {args.tilt:g} deg) and {tp}")
    return 0


def _run_reslice(args) -> int:
    import math
    from pathlib import Path

    from .geometry import load_geometry
    from .imageio import MAX_SPACING_MM, MIN_SPACING_MM
    from .reslice import default_depths, reslice, reslice_study
    from .volume import read_volume

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
    T_ref = _load_reference(args.reference)
    vol = read_volume(args.volume)
    depths = args.depths if args.depths else default_depths(geom, args.tilt, args.depth_step)
    study = reslice_study(vol, geom, T_ref, depths_mm=depths, tilt_deg=args.tilt, azimuth_deg=args.azimuth,
                          twist_deg=args.twist, shape=(args.size, args.size),
                          pixel_spacing_mm=(args.pixel_size, args.pixel_size), slice_thickness_mm=args.slice_thickness)
    if args.save_slices:
        from .dicomio import write_dicom
        from .pose import slice_frame

        folder = Path(args.save_slices)
        if not folder.is_dir():
            from .atomic import check_parent

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


def _run_track(args) -> int:
    from .cli_track import run_track

    return run_track(args)


def _run_precision(args) -> int:
    from .crlb import Protocol, precision_map
    from .geometry import load_geometry
    from .precision_report import format_map, plot_map

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


def _run(args) -> int:
    commands = {"precision": _run_precision, "solve": _run_solve, "simulate": _run_simulate, "evaluate": _run_evaluate,
                "reslice": _run_reslice, "track": _run_track}
    return commands[args.command](args)


def main(argv=None) -> int:
    args = None
    try:
        args = _parser().parse_args(argv)  # inside: `--help | head` must not traceback either
        return _run(args)
    except NoLock as exc:
        if getattr(args, "json", False):
            print(json.dumps({"status": "no_lock", "reason": exc.reason, **exc.detail}, indent=2))
        else:
            print(f"chic-register: no lock: {exc.reason}", file=sys.stderr)
        return exc.exit_code
    except ChicRegisterError as exc:
        return exits.report(PROG, f"error: {exc}", exc.exit_code)
    except KeyboardInterrupt:
        return exits.report(PROG, "interrupted", 130)
    except BrokenPipeError:  # e.g. `chic-register ... | head`: the reader left; nothing more to say
        return exits.broken_pipe()
    except OSError as exc:  # an output that cannot be written (disk full, permission, vanished folder)
        return exits.os_error(PROG, exc)


if __name__ == "__main__":
    sys.exit(main())
