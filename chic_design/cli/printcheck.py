"""``chic-design printcheck EXPORT``: slice an export's plate.3mf with PrusaSlicer and check every channel in the toolpaths."""

from __future__ import annotations

import json

from chic_design.errors import ChannelsNotPrintable
from chic_design.progress import status


def add_parser(subparsers):
    p = subparsers.add_parser(
        "printcheck", help="slice an export's plate.3mf with prusa-slicer and check every channel in the toolpaths")
    p.add_argument("export", help="export folder written by `chic-design build` (e.g. exports/neuro)")
    p.add_argument("--slicer", metavar="EXE", help="PrusaSlicer executable (default: prusa-slicer on the PATH)")
    p.add_argument("--calibration", metavar="G2",
                   help="geometry file from `chic-register calibrate` of a scan of this print: its scale is "
                        "compared with the toolpaths' in the report")
    p.add_argument("--out", metavar="DIR", help="write printcheck.json, .png and .md here (default: the export folder)")
    p.add_argument("--json", action="store_true", help="print the check as one JSON object (as printcheck.json)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    return p


def run(args) -> int:
    """Exit 0 when every channel is open, 6 when one is closed, narrowed or overhung (named with its layer)."""
    from chic_design.printing.export import run_printcheck  # shapely and trimesh: loaded only when it runs

    say = None if args.quiet else (lambda text: status(text))
    result = run_printcheck(args.export, exe=args.slicer, progress=say, calibration=args.calibration, out=args.out)
    if args.json:
        print(json.dumps(result.to_dict(), indent=2))
    else:
        for c in result.channels:
            verdict = "ok" if c.ok else "FAIL: " + "; ".join(c.problems)
            print(f"{c.id:>7} {c.part:<8} {c.diameter_mm:g} mm: clear >= {c.min_clear_mm:.2f} mm "
                  f"(z {c.worst_z_mm:g}), open >= {c.min_open_share:.0%}, offset <= {c.max_offset_mm:.3f} mm, "
                  f"overhang {c.overhang_mm:.2f} mm  {verdict}")
        print(f"toolpath scale about the axis {result.toolpath_scale:.5f} (SD {result.toolpath_scale_sd:.5f})")
        out = args.out or args.export
        for name in ("printcheck.json", "printcheck.png", "printcheck.md"):
            print(f"wrote {out}/{name}")
    if not result.ok:
        raise ChannelsNotPrintable(f"{args.export}: {result.failure_text()}")
    return 0
