"""``chic-register``: register MRI slices of a CHIC fiducial, simulate slices, evaluate accuracy.

The argument parser and ``main``; the commands are in :mod:`~chic_register.cli.solve`,
:mod:`~chic_register.cli.simulate`, :mod:`~chic_register.cli.studies` (evaluate, reslice,
precision) and :mod:`~chic_register.cli.track`, a thin layer over the library
(:mod:`chic_register.pipeline.register`, :mod:`chic_register.imaging.simulate`, :mod:`chic_register.studies.evaluate`).
``main(argv) -> int`` is testable in-process. Exit codes (docs/interfaces.md section 4):
0 ok, 2 bad input, 3 no trustworthy pose (``no_lock``), 4 pose ok but an output (``--tfm``,
``--scene``, ``--overlay``, OpenIGTLink) failed: the pose is still printed.
"""

from __future__ import annotations

import argparse
import json
import sys

from chic_register.cli import exits
from chic_register.cli.simulate import run_simulate
from chic_register.cli.solve import run_solve
from chic_register.cli.studies import run_evaluate, run_precision, run_reslice
from chic_register.cli.track import run_track
from chic_register.errors import ChicRegisterError, NoLock
from chic_register.version import __version__

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
    s.add_argument("--series", metavar="ID", default=None,
                   help="the DICOM series to read from a folder holding several (its SeriesNumber or SeriesInstanceUID)")
    s.add_argument("--slices", nargs="+", metavar="K",
                   help="for a volume IMAGE (.nii, .nii.gz, .nrrd, .mha or a DICOM series folder): "
                        "indices (5) or ranges (5-11) of its slices to register jointly; each must lock. "
                        "Default: every slice that shows the fiducial (the others are listed as skipped)")
    s.add_argument("--prior", metavar="FILE",
                   help="an approximate pose of the fiducial (JSON with T_scanner_from_fiducial, or .tfm), or "
                        "'identity' (the frame's x, y, z roughly along the scanner's LPS axes): only poses turned "
                        "less than --prior-max-deg from it are considered. Needed for a geometry that maps onto "
                        "itself under a rotation (the classic Z-frame)")
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


def _run(args) -> int:
    commands = {"precision": run_precision, "solve": run_solve, "simulate": run_simulate, "evaluate": run_evaluate,
                "reslice": run_reslice, "track": run_track}
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
