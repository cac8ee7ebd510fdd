"""chic-register solve: read the slices, register them, print the pose, then write or send the outputs.

Exit codes: 0, 2 bad input, 3 no lock, 4 when an output (--tfm, --scene,
--overlay, OpenIGTLink) failed after the pose was printed.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

from chic_register.cli.console import note, status
from chic_register.cli.inputs import add_igtl_args, prior_options, read_image_inputs, register_inputs
from chic_register.errors import ChicRegisterError, NoLock

HELP = "register one or more slices: one pose from all of them"
DESCRIPTION = ("Register one or more slices: one pose from all of them. Exit codes: 0 ok, 2 bad input, 3 no_lock (no "
               "trustworthy pose), 4 the pose is printed but an output failed.")


def add_parser(subparsers) -> None:
    """The solve subcommand and its flags."""
    s = subparsers.add_parser("solve", help=HELP, description=DESCRIPTION)
    s.set_defaults(run=run)
    s.add_argument("images", nargs="+", metavar="IMAGE", help="DICOM, PNG, TIFF or NPY slices")
    s.add_argument("--geometry", required=True, help="geometry.yaml written by chic-design build")
    s.add_argument("--json", action="store_true", help="print one JSON object (docs/interfaces.md section 4)")
    s.add_argument("--pixel-spacing", nargs=2, type=float, metavar=("ROW", "COL"),
                   help="pixel spacing (mm) for PNG/TIFF/NPY images")
    s.add_argument("--overlay", metavar="PNG", help="draw the slice with detections, ellipse and labels")
    s.add_argument("--series", metavar="ID", default=None,
                   help="the DICOM series to read from a folder holding several (its SeriesNumber or SeriesInstanceUID)")
    s.add_argument("--slices", nargs="+", metavar="K",
                   help="for a volume IMAGE (.nii, .nii.gz, .nrrd, .mha or a DICOM series folder): "
                        "indices (5) or ranges (5-11) of its slices to register jointly; each must lock. "
                        "Default: every slice that shows the fiducial (the others are listed as skipped)")
    s.add_argument("--modality", choices=("auto", "MR", "CT"), default="auto",
                   type=lambda v: "auto" if v.lower() == "auto" else v.upper(),
                   help="what the images are: MR (magnitude, Rician noise), CT (Hounsfield units) or auto (default: "
                        "DICOM's Modality, else CT when the pixels hold air near -1000 HU)")
    s.add_argument("--prior", metavar="FILE",
                   help="an approximate pose of the fiducial (JSON with T_scanner_from_fiducial, or .tfm), or "
                        "the scanner directions the frame's x, y, z point along: RAS, LPS (also 'identity'), LAI, "
                        "...: only poses turned "
                        "less than --prior-max-deg from it are considered. Needed for a geometry that maps onto "
                        "itself under a rotation (the classic Z-frame)")
    s.add_argument("--prior-max-deg", type=float, default=60.0, metavar="DEG",
                   help="largest rotation from --prior (default 60)")
    s.add_argument("--tfm", metavar="FILE", help="also write the pose as an ITK transform file for 3D Slicer "
                   "(holds T_fiducial_from_scanner, LPS; see docs/interfaces.md)")
    s.add_argument("--scene", metavar="DIR", help="also write a 3D Slicer scene (DIR/scene.mrml with the slices, "
                   "the fiducial and tool models under their transforms, detected and predicted tube centres)")
    add_igtl_args(s)
    s.add_argument("--frame", metavar="GEOMETRY",
                   help="a second fiducial in the same images, as a stereotactic frame around the first: both are "
                        "registered without each other's sections, and the first (its --target, tool tip or body "
                        "centre) is reported in the frame's coordinates with its uncertainty")
    s.add_argument("--frame-prior", metavar="FILE",
                   help="--prior for the --frame fiducial (a frame that maps onto itself, as the Leksell box, "
                        "needs one: LPS for a head-first supine patient)")
    s.add_argument("--target", nargs=3, type=float, metavar=("X", "Y", "Z"),
                   help="point of F (mm) whose predicted TRE is reported (default: the tool tip, else the body centre)")
    s.add_argument("--max-tre", type=float, metavar="MM",
                   help="refuse (no_lock, reason 'imprecise') a pose whose predicted TRE exceeds MM")
    s.add_argument("--trust", nargs=2, type=float, metavar=("MM", "DEG"),
                   help="the verification's precision limits: refuse a pose whose 3-sigma predicted error exceeds "
                        "MM at the frame centre or DEG in rotation (default 1 0.75; a single near-normal slice "
                        "of a CHIC fiducial knows its tilt to ~0.2-0.25 deg at 1 sigma)")
    s.add_argument("--max-scale-error", type=float, nargs="+", default=None, metavar="PCT",
                   help="largest scale of the image fitted with the pose of several slices rather than refused as "
                        "a wrong spacing: PCT in the image plane and, if a second value is given, across a volume's "
                        "slices (one value: both; default 2 5: gradient calibration is good to 1-2 %%, a print to "
                        "0.1-0.5 %%, and the slice direction, left uncorrected for the gradients' non-linearity, is "
                        "off by several %% 100-150 mm from the isocentre)")
    s.add_argument("--scale-sd", type=float, default=None, metavar="PCT",
                   help="the image's in-plane scale is known to PCT (1 SD per axis: an uncalibrated print and "
                        "scanner, 0.2-0.5; a file from chic-register calibrate, its own SD); one slice cannot "
                        "measure its scale, so what PCT would move the pose joins its uncertainty and the trust "
                        "test (default 0: the geometry file and the pixel spacing are exact)")


def _report_failures(delivery) -> None:
    for failure in delivery.failed:
        status(f"output failed: {failure}")


def run(args) -> int:
    """Register the slices; print the pose before any output is written or sent."""
    # here, not at the top: keeps chic-register's start-up fast (every command module is imported)
    from chic_register.io.images import is_volume_path
    from chic_register.model.geometry import load_geometry
    from chic_register.outputs.deliver import EXIT_OUTPUT_FAILED, Delivery, OutputPlan, deliver, deliver_no_lock

    plan = OutputPlan.from_args(args).check()
    geom = load_geometry(args.geometry)
    options = prior_options(args)
    slices, skip, volume = read_image_inputs(args)
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
    if args.max_scale_error is not None:
        pcts = args.max_scale_error
        if len(pcts) > 2 or not all(0 < v <= 20 and math.isfinite(v) for v in pcts):
            raise ChicRegisterError("--max-scale-error takes one or two per cents in (0, 20] (the image plane, then "
                                    f"across the slices), got {' '.join(f'{v:g}' for v in pcts)}")
        extra["max_scale_error"] = pcts[0] / 100.0
        extra["max_slice_scale_error"] = pcts[-1] / 100.0
    if args.scale_sd is not None:
        if not (0 <= args.scale_sd <= 5 and math.isfinite(args.scale_sd)):
            raise ChicRegisterError(f"--scale-sd takes a per cent in [0, 5], got {args.scale_sd:g}")
        extra["scale_sd"] = args.scale_sd / 100.0
    early = Delivery()  # a server that cannot listen is an output failure: the pose still comes
    link = None
    try:
        link = plan.open_link()
    except ChicRegisterError as exc:
        early.failed.append(f"{plan.igtl_flag}: {exc}")
    if plan.igtl_listen is not None and link is not None:
        status(f"OpenIGTLink server listening on port {link.port} (a peer may connect now; "
               f"the pose waits up to {plan.igtl_wait_s:g} s for one)")
    if skip and len(slices) > 1:  # a whole volume: one register call over every slice, seconds without a word
        status(f"registering {len(slices)} slices of {', '.join(p for p in args.images if is_volume_path(p))} "
               "(those that do not show the fiducial are skipped)")
    if args.frame is not None:
        return _run_with_frame(args, plan, geom, slices, skip, options, extra, early, link)
    try:
        try:
            reg = register_inputs(slices, skip, volume, geom, **options, **extra)
        except NoLock as exc:
            hint = _series_hint(args, slices, skip)
            if hint and hint not in exc.reason:
                exc.reason += hint
                exc.args = (exc.reason,)
            _report_failures(early)
            refused = deliver_no_lock(plan, exc.reason, geom, slices, link,
                                      exc.detail.get("refused_T_scanner_from_fiducial"))
            for done in refused.done:
                note(args, done)
            _report_failures(refused)
            raise
        # the pose is printed first: a failing optional output (overlay, --tfm, --scene, --igtl) must not lose it
        _print_pose(args, reg, geom)
        out = deliver(plan, reg, geom, slices, link)
    finally:
        if link is not None:
            link.close()
    out.failed[:0] = early.failed
    for done in out.done:
        note(args, done)
    _report_failures(out)
    return EXIT_OUTPUT_FAILED if out.failed else 0


def _run_with_frame(args, plan, geom, slices, skip, options, extra, early, link) -> int:
    """``solve --frame``: both fiducials from the same slices (:func:`~chic_register.pipeline.frames.register_frames`),
    the first printed as a plain solve, then the frame's pose and the first in the frame's coordinates. Exit 3
    when either does not lock (the one that did is still printed)."""
    # here, not at the top: as in run
    from chic_register.model.geometry import load_geometry
    from chic_register.options import SolveOptions
    from chic_register.outputs.deliver import registration_json
    from chic_register.pipeline.frames import register_frames, relative_pose

    frame_geom = load_geometry(args.frame)
    frame_options = {}
    if args.frame_prior:
        frame_options = prior_options(argparse_namespace(prior=args.frame_prior, prior_max_deg=args.prior_max_deg))
    shared = {k: v for k, v in extra.items() if k != "target_F_mm"}
    opts = [dataclasses.replace(SolveOptions(), **options, **shared),
            dataclasses.replace(SolveOptions(), **frame_options, **shared)]
    try:
        results = register_frames(slices, [geom, frame_geom], options_for=lambda i: opts[i], skip_failed=skip)
    finally:
        if link is not None:
            link.close()
    _report_failures(early)
    main, frame = results
    rel = relative_pose(main.registration, geom, frame.registration, frame_geom, args.target) \
        if main.ok and frame.ok else None
    if args.json:
        doc = registration_json(main.registration, geom, args.target) if main.ok else \
            {"status": "no_lock", "reason": main.reason}
        doc["frame"] = (registration_json(frame.registration, frame_geom) if frame.ok
                        else {"status": "no_lock", "reason": frame.reason})
        if rel is not None:
            doc["frame"]["fiducial_in_frame"] = rel.to_dict()
        print(json.dumps(doc, indent=2), flush=True)
    else:
        if main.ok:
            _print_pose(args, main.registration, geom)
        else:
            print(f"{geom.name}: no lock: {main.reason}")
        if frame.ok:
            print(f"frame '{frame_geom.name}':")
            _print_pose(args, frame.registration, frame_geom)
        else:
            print(f"frame '{frame_geom.name}': no lock: {frame.reason}")
        if rel is not None:
            p, q, sd = rel.target_a_mm, rel.target_b_mm, rel.sigma_mm
            print(f"'{geom.name}' at ({', '.join(f'{v:g}' for v in p)}) mm of its F in {rel.frame} coordinates: "
                  + ", ".join(f"{a} {v:.3f} (SD {d:.3f})" for a, v, d in zip("XYZ", q, sd))
                  + f" mm; predicted error {rel.tre_mm:.3f} mm RMS")
    if not (main.ok and frame.ok):
        failed = [f"{g.name}: {r.reason}" for g, r in ((geom, main), (frame_geom, frame)) if not r.ok]
        raise NoLock("; ".join(failed))
    return 0


def argparse_namespace(**kw):
    """A namespace of ``kw`` (the flags :func:`~chic_register.cli.inputs.prior_options` reads)."""
    return argparse.Namespace(**kw)


def _print_pose(args, reg, geom) -> None:
    """The pose of solve: one JSON object (--json) or the human summary."""
    from chic_register.outputs.deliver import registration_json, tool_pose  # here, not at the top: as in run
    from chic_register.outputs.frame import frame_report

    if args.json:
        print(json.dumps(registration_json(reg, geom, args.target), indent=2), flush=True)
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
    frame = frame_report(reg, geom, args.target)
    if frame is not None:
        print(_frame_line(frame))
    for s in reg.slices:
        print(f"{s.source}: depth {s.depth_mm:.3f} mm, tilt {s.tilt_deg:.3f}, azimuth {s.azimuth_deg:.3f}, "
              f"twist {s.twist_deg:.3f} deg; residual RMS {s.residual_rms_mm:.3f} mm over {s.n_tubes} tubes")
        print("  residuals (mm): " + ", ".join(f"{k} {v:.3f}" for k, v in s.residuals_mm.items()))
    for s in reg.skipped:
        print(f"skipped {s.source}: {s.reason}")
    if reg.scale is not None:
        e = reg.scale
        print("image scale: " + ", ".join(f"{a} {100 * v:+.2f} % (SD {100 * d:.2f})" for a, v, d in
                                          zip(e.axes, e.scale, e.scale_sd))
              + ("; the pose is fitted with it" if e.fitted
                 else "; measured, not fitted: one slice cannot tell a stretch from a tilt (several slices or a "
                      "volume fit it)" if len(reg.slices) == 1
                 else "; not shown by the data: the pose is rigid"))
        if e.pose_sd_per_pct is not None:
            rot, tre = e.pose_sd_per_pct
            held = (f"--scale-sd {100 * e.prior_sd:g} % is in the uncertainty below" if e.prior_sd > 0 else
                    "not in the uncertainty below: --scale-sd PCT adds it, chic-register calibrate measures it")
            print(f"  an unmeasured scale of 0.1 % (SD per axis) would add SD {rot / 10:.3f} deg, {tre / 10:.3f} mm at "
                  f"the frame centre to this pose ({held})")
    u = reg.uncertainty
    if u is not None:
        sd = [math.sqrt(max(0.0, float(u.covariance[i, i]))) for i in range(6)]
        print(f"predicted TRE {u.predicted_tre_mm:.3f} mm at ({', '.join(f'{v:g}' for v in u.target_F_mm)}) in F; "
              f"SD rotation {max(sd[:3]):.3f} deg, translation {max(sd[3:]):.3f} mm (largest axis); "
              f"image noise sigma {', '.join(f'{n.sigma:.4g}' for n in u.noise)}")
    sys.stdout.flush()


def _frame_line(frame: dict) -> str:
    """The human line of a pose in a stereotactic frame's coordinates: where the scanner's origin and axes lie."""
    import numpy as np  # here, not at the top: as in run

    T = np.asarray(frame["T_frame_from_scanner"])
    axes = "; ".join(f"{a} ({', '.join(f'{v:.4f}' for v in T[:3, i])})" for i, a in enumerate("LPS"))
    line = (f"{frame['system']} frame coordinates: scanner origin at ({', '.join(f'{v:.3f}' for v in T[:3, 3])}) mm, "
            f"scanner axes {axes} (T_frame_from_scanner in the JSON)")
    if "target_frame_mm" in frame:
        line += f"; target at ({', '.join(f'{v:.3f}' for v in frame['target_frame_mm'])}) mm"
    return line


def _series_hint(args, slices, skip: bool) -> str:
    """What to do when the files of one series were given one by one and one of them does not show the frame:
    every slice given as a file must lock; a volume's slices that do not are skipped."""

    files = [p for p in args.images if Path(p).is_file()]
    if skip or len(slices) < 3 or len(files) < 3:
        return ""
    folders = {str(Path(p).resolve().parent) for p in files}
    if len(folders) != 1:
        return ""
    return (f" (every one of the {len(slices)} slices given must lock; to register only those that show the frame, "
            f"give the series' folder as one volume: chic-register solve {Path(files[0]).parent} ...)")


