"""chic-register map: points between scanner coordinates and a stereotactic frame's, with their uncertainty.

The geometry names the frame (``frame_coordinates``), the pose file gives
``T_scanner_from_fiducial`` and its covariance (``solve --json``; a ``.tfm``
has no covariance, so its points have no uncertainty). Point files and their
coordinate systems: docs/interfaces.md section 4, ``map``.
Exit codes: 0, 2 bad input (nothing written).
"""

from __future__ import annotations

import json
import math

from chic_register.cli.console import wrote
from chic_register.errors import ChicRegisterError

HELP = "map points between scanner coordinates (LPS/RAS) and a stereotactic frame's, with their uncertainty"
DESCRIPTION = ("Map points between scanner coordinates (LPS, or RAS) and the stereotactic frame coordinates the "
               "geometry names (frame_coordinates), through a registered pose; each mapped point gets its 1-sigma "
               "per axis, RMS and 95 % radius from the pose's covariance. Exit codes: 0 ok, 2 bad input.")


def add_parser(subparsers) -> None:
    """The map subcommand and its flags."""
    m = subparsers.add_parser("map", help=HELP, description=DESCRIPTION)
    m.set_defaults(run=run)
    m.add_argument("--geometry", required=True, help="geometry.yaml with frame_coordinates")
    m.add_argument("--pose", required=True, metavar="FILE",
                   help="the pose: the JSON of chic-register solve --json (T_scanner_from_fiducial and its "
                        "covariance) or a .tfm written by solve --tfm (no covariance: no uncertainty)")
    m.add_argument("--to", required=True, choices=("frame", "scanner"),
                   help="frame: the points are scanner coordinates; scanner: they are frame coordinates")
    m.add_argument("--point", nargs=3, type=float, action="append", metavar=("X", "Y", "Z"),
                   help="a point (mm; repeatable)")
    m.add_argument("--points", metavar="FILE",
                   help="the points: 3D Slicer markups (.mrk.json), Slicer fiducial CSV (.fcsv) or .csv with "
                        "a header row label,x,y,z")
    m.add_argument("--ras", action="store_true",
                   help="scanner coordinates of --point, of a .csv that does not say, and of the output are RAS "
                        "(default LPS); Slicer files say their own")
    m.add_argument("--out", metavar="FILE", help="also write the mapped points (.mrk.json, .fcsv or .csv)")
    m.add_argument("--json", action="store_true", help="print one JSON object instead of the table")


def _check_args(args):
    """The output file's format and folder and the point sources, before any file is read."""
    from chic_register.io.markups import point_format  # here, not at the top: keeps start-up fast
    from chic_register.util.atomic import check_parent

    if args.out:
        point_format(args.out)
        check_parent(args.out)
    if bool(args.point) == bool(args.points):
        raise ChicRegisterError("give the points as --point X Y Z (repeatable) or --points FILE, one of the two")
    for p in args.point or ():
        if not all(math.isfinite(v) for v in p):
            raise ChicRegisterError(f"--point {' '.join(f'{v:g}' for v in p)}: three finite numbers (mm)")


def _check_pose_geometry(pose, geom, geometry_path) -> None:
    """A pose solved with another fiducial is refused; one solved before the geometry named its frame is not."""
    from chic_register.model.geometry import content_sha256  # here, not at the top: keeps start-up fast

    if not pose.geometry_sha256:
        return
    content = geom.content()
    shas = {content_sha256(content)}
    content.pop("frame_coordinates", None)
    shas.add(content_sha256(content))
    if pose.geometry_sha256 not in shas:
        raise ChicRegisterError(f"{pose.source}: geometry.sha256 {pose.geometry_sha256[:12]}... is not that of "
                                f"{geometry_path}: the pose was solved with another geometry")


def _input_points(args, frame_system: str):
    """(positions (N, 3) in the input's system, labels, the input's system): scanner points in LPS for
    ``--to frame``, frame coordinates for ``--to scanner``."""
    # here, not at the top: keeps start-up fast
    from chic_register.io.markups import SLICER_SYSTEMS, point_format, read_points

    scanner_default = "RAS" if args.ras else "LPS"
    if args.point:
        import numpy as np  # here, not at the top: keeps start-up fast

        P = np.array(args.point, dtype=float)
        labels = [f"P{i + 1}" for i in range(len(P))]
        if args.to == "frame":
            return (P * [-1.0, -1.0, 1.0] if args.ras else P), labels, scanner_default
        return P, labels, frame_system
    pts = read_points(args.points)
    kind, system = point_format(args.points), pts.coordinate_system
    if args.to == "frame":
        if system is not None and system not in SLICER_SYSTEMS:
            raise ChicRegisterError(f"{args.points}: column 'coordinates' says {system}; --to frame maps scanner "
                                    "coordinates (LPS or RAS)")
        return pts.positions_lps_mm(scanner_default), pts.labels, system or scanner_default
    if kind == "csv":
        if system is not None and system != frame_system:
            raise ChicRegisterError(f"{args.points}: column 'coordinates' says {system}; --to scanner maps "
                                    f"{frame_system} frame coordinates")
        return pts.positions_mm, pts.labels, frame_system
    # a Slicer file of frame coordinates: the frame's X, Y, Z stand in Slicer's R, A, S (what its table shows)
    return pts.positions_lps_mm() * [-1.0, -1.0, 1.0], pts.labels, frame_system


def _describe(u) -> str:
    if u is None:
        return "no uncertainty (the pose file has no covariance)"
    return (f"1-sigma {' '.join(f'{v:.4f}' for v in u.sigma_mm)} mm, RMS {u.rms_mm:.4f} mm, "
            f"95 % radius {u.radius95_mm:.4f} mm")


def run(args) -> int:
    """Read the geometry, the pose and the points; map them; print the table or JSON; write --out."""
    # here, not at the top: keeps chic-register's start-up fast (every command module is imported)
    from chic_register.io.markups import MarkupPoint, PointList, point_file_text, point_format
    from chic_register.io.poses import read_pose
    from chic_register.model.geometry import load_geometry
    from chic_register.outputs.frame import FramePose, map_points, point_uncertainty
    from chic_register.util.atomic import write_text

    _check_args(args)
    geom = load_geometry(args.geometry)
    frame = geom.frame_coordinates
    if frame is None:
        raise ChicRegisterError(f"{args.geometry}: no key 'frame_coordinates' (map needs the stereotactic frame's "
                                "coordinate system in the geometry file)")
    pose = read_pose(args.pose)
    _check_pose_geometry(pose, geom, args.geometry)
    P, labels, in_system = _input_points(args, frame.system)
    mapped = map_points(P, args.to, pose.T_scanner_from_fiducial, frame, pose.covariance_deg_mm, labels)
    scanner_system = "RAS" if args.ras else "LPS"
    out_system = frame.system if args.to == "frame" else scanner_system
    rows = []
    for m in mapped:
        u = point_uncertainty(m, out_system, frame, pose.T_scanner_from_fiducial)
        rows.append((m, m.position_mm(out_system, frame.system), u))
    doc = {"to": args.to, "frame_system": frame.system, "input_coordinates": in_system,
           "output_coordinates": out_system, "scanner_coordinates": scanner_system,
           "pose": {"source": pose.source, "covariance": pose.covariance_deg_mm is not None},
           **{k: v for k, v in FramePose(frame, pose.T_scanner_from_fiducial).to_dict().items()
              if k in ("T_frame_from_scanner", "T_scanner_from_frame", "axes")},
           "points": [{"label": m.label, "output_mm": [float(v) for v in pos],
                       "frame_mm": [float(v) for v in m.frame_mm],
                       "scanner_mm": [float(v) for v in m.position_mm(scanner_system, frame.system)],
                       "uncertainty": None if u is None else u.to_dict()} for m, pos, u in rows]}
    text = None
    if args.out:
        kind = point_format(args.out)
        slicer_system = out_system if out_system in ("LPS", "RAS") else "RAS"  # frame X, Y, Z as Slicer's R, A, S
        points = []
        for m, pos, u in rows:
            what = (f"{frame.system} frame coordinates (mm)" if args.to == "frame"
                    else f"scanner {scanner_system} (mm) of {frame.system} frame coordinates")
            columns = {} if kind != "csv" else (
                {"sigma_x_mm": "", "sigma_y_mm": "", "sigma_z_mm": "", "rms_mm": "", "radius95_mm": ""} if u is None
                else {"sigma_x_mm": float(u.sigma_mm[0]), "sigma_y_mm": float(u.sigma_mm[1]),
                      "sigma_z_mm": float(u.sigma_mm[2]), "rms_mm": u.rms_mm, "radius95_mm": u.radius95_mm})
            points.append(MarkupPoint(m.label, tuple(float(v) for v in pos), f"{what}; {_describe(u)}", columns))
        text = point_file_text(PointList(tuple(points), out_system if kind == "csv" else slicer_system), args.out)
    if args.json:
        print(json.dumps(doc, indent=2), flush=True)
    else:
        _print_table(doc)
    if text is not None:
        wrote(args, write_text(args.out, text), f"{len(rows)} points, {out_system}")
    return 0


def _print_table(doc: dict) -> None:
    """The mapped points as a table (mm): label, the output's coordinates, 1-sigma per axis, RMS, 95 % radius."""
    out = doc["output_coordinates"]
    print(f"{doc['input_coordinates']} -> {out} (mm; pose {doc['pose']['source']}"
          + ("" if doc["pose"]["covariance"] else ", no covariance: no uncertainty") + ")")
    names = ("X", "Y", "Z") if out not in ("LPS", "RAS") else tuple(out)
    print(f"{'label':<12} {names[0]:>11} {names[1]:>11} {names[2]:>11}   {'sd_x':>7} {'sd_y':>7} {'sd_z':>7} "
          f"{'rms':>7} {'r95':>7}")
    for p in doc["points"]:
        x, y, z = p["output_mm"]
        u = p["uncertainty"]
        tail = "" if u is None else (" ".join(f"{v:7.4f}" for v in u["sigma_mm"])
                                     + f" {u['rms_mm']:7.4f} {u['radius95_mm']:7.4f}")
        print(f"{p['label'][:12]:<12} {x:11.4f} {y:11.4f} {z:11.4f}   {tail}".rstrip())
