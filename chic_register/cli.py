"""``chic-register``: register MRI slices of a CHIC fiducial, simulate slices, evaluate accuracy.

A thin layer over the library (:mod:`chic_register.solve`,
:mod:`chic_register.simulate`, :mod:`chic_register.evaluate`).
``main(argv) -> int`` is testable in-process. Exit codes (CONTRACT.md section 4):
0 ok, 2 bad input, 3 no trustworthy pose (``no_lock``).
"""

from __future__ import annotations

import argparse
import json
import sys

from . import __version__
from .errors import ChicRegisterError, NoLock


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="chic-register", description=__doc__.splitlines()[0])
    p.add_argument("--version", action="version", version=f"chic-register {__version__}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    s = sub.add_parser("solve", help="register one or more slices: one pose from all of them")
    s.add_argument("images", nargs="+", metavar="IMAGE", help="DICOM, PNG, TIFF or NPY slices")
    s.add_argument("--geometry", required=True, help="geometry.yaml written by chic-design build")
    s.add_argument("--json", action="store_true", help="print one JSON object (CONTRACT.md section 4)")
    s.add_argument("--pixel-spacing", nargs=2, type=float, metavar=("ROW", "COL"),
                   help="pixel spacing (mm) for PNG/TIFF/NPY images")
    s.add_argument("--overlay", metavar="PNG", help="draw the slice with detections, ellipse and labels")

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
    m.add_argument("--center-offset", nargs=2, type=float, default=(0.0, 0.0), metavar=("X", "Y"),
                   help="axis crossing from the image centre, mm along columns and rows (default 0 0)")
    m.add_argument("--image-position", nargs=3, type=float, metavar=("X", "Y", "Z"),
                   help="DICOM only: scanner (LPS) position of pixel (0, 0) (default: image centre at 0)")
    m.add_argument("--image-orientation", nargs=6, type=float, metavar="V",
                   help="DICOM only: col_dir and row_dir in the scanner (default 1 0 0 0 1 0)")

    e = sub.add_parser("evaluate", help="repeat the paper's simulation study and compare")
    e.add_argument("--geometry", required=True, help="geometry.yaml")
    e.add_argument("--protocol", default="paper", choices=["paper"], help="study protocol (default: paper)")
    return p


def _run_solve(args) -> int:
    raise ChicRegisterError("'solve' is not implemented yet")


def _run_simulate(args) -> int:
    from pathlib import Path

    import numpy as np

    from .geometry import load_geometry
    from .imageio import PLAIN_SUFFIXES
    from .simulate import DICOM_SUFFIXES, simulate_slice, write_simulated

    out = Path(args.out)
    checks = [
        (args.size >= 8 and args.size <= 4096, f"--size must be 8..4096 pixels, got {args.size}"),
        (args.pixel_size > 0 and np.isfinite(args.pixel_size), f"--pixel-size must be > 0 mm, got {args.pixel_size:g}"),
        (args.slice_thickness >= 0 and np.isfinite(args.slice_thickness),
         f"--slice-thickness must be >= 0 mm, got {args.slice_thickness:g}"),
        (args.noise_level >= 0 and np.isfinite(args.noise_level), f"--noise-level must be >= 0, got {args.noise_level:g}"),
        (args.snr > 0 and np.isfinite(args.snr), f"--snr must be > 0, got {args.snr:g}"),
        (args.distractors >= 0, f"--distractors must be >= 0, got {args.distractors}"),
        (args.bore_signal >= 0 and np.isfinite(args.bore_signal), f"--bore-signal must be >= 0, got {args.bore_signal:g}"),
        (all(np.isfinite(v) for v in (args.depth, args.tilt, args.azimuth, args.twist)),
         "--depth, --tilt, --azimuth and --twist must be finite numbers"),
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
            rng=np.random.default_rng(args.seed),
        )
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
        f"{len(sim.truth.centres_px)} tubes in view) and {truth_file}"
    )
    return 0


def _run_evaluate(args) -> int:
    raise ChicRegisterError("'evaluate' is not implemented yet")


def _run(args) -> int:
    commands = {"solve": _run_solve, "simulate": _run_simulate, "evaluate": _run_evaluate}
    return commands[args.command](args)


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    try:
        return _run(args)
    except NoLock as exc:
        if getattr(args, "json", False):
            print(json.dumps({"status": "no_lock", "reason": exc.reason, **exc.detail}, indent=2))
        else:
            print(f"chic-register: no lock: {exc.reason}", file=sys.stderr)
        return exc.exit_code
    except ChicRegisterError as exc:
        print(f"chic-register: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("chic-register: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
