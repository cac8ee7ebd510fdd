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

    e = sub.add_parser("evaluate", help="repeat the paper's simulation study and compare")
    e.add_argument("--geometry", required=True, help="geometry.yaml")
    e.add_argument("--protocol", default="paper", choices=["paper"], help="study protocol (default: paper)")
    return p


def _run_solve(args) -> int:
    raise ChicRegisterError("'solve' is not implemented yet")


def _run_simulate(args) -> int:
    raise ChicRegisterError("'simulate' is not implemented yet")


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
