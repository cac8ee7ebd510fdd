"""chic-register track: register each new slice as it arrives, from a watched folder or as OpenIGTLink IMAGE
messages from a scanner bridge, with the same outputs as solve.

Exit codes as solve: 0, 2 bad input, 4 when an output (OpenIGTLink, a scene) failed for any image.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

from chic_register.cli.console import note, status
from chic_register.cli.inputs import add_igtl_args, check_spacing_flag
from chic_register.errors import ChicRegisterError

HELP = "register each new slice as it arrives (a watched folder or OpenIGTLink IMAGEs)"
DESCRIPTION = ("Register each new slice as it arrives (a watched folder or OpenIGTLink IMAGEs), with the outputs of "
               "solve. Exit code 4 when an output failed for any image.")


def add_parser(subparsers) -> None:
    """The track subcommand and its flags."""
    t = subparsers.add_parser("track", help=HELP, description=DESCRIPTION)
    t.set_defaults(run=run)
    t.add_argument("folder", metavar="FOLDER", nargs="?", help="folder the scanner writes slices into "
                   "('-' or none with --igtl-images)")
    t.add_argument("--geometry", required=True, help="geometry.yaml")
    t.add_argument("--pixel-spacing", nargs=2, type=float, metavar=("ROW", "COL"),
                   help="pixel spacing (mm) for PNG/TIFF/NPY images")
    add_igtl_args(t)
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
    t.add_argument("--scale-sd", type=float, default=None, metavar="PCT",
                   help="as solve --scale-sd: the in-plane scale known to PCT (1 SD per axis), held in each slice's "
                        "uncertainty and trust test (default: a calibrated geometry file's own SD, else 0)")


def run(args) -> int:
    """Watch the folder (or the scanner bridge) until stopped; one line (or JSON object) per image."""
    # here, not at the top: keeps chic-register's start-up fast (every command module is imported)
    from chic_register.io.igtl import IgtlServer, check_port, parse_address
    from chic_register.live.folder import track
    from chic_register.live.igtl_track import track_images
    from chic_register.model.geometry import load_geometry
    from chic_register.outputs.deliver import EXIT_OUTPUT_FAILED, OutputPlan

    images = args.igtl_images is not None or args.igtl_images_listen is not None
    if args.igtl_images is not None and args.igtl_images_listen is not None:
        raise ChicRegisterError("--igtl-images and --igtl-images-listen: give one (connect to the bridge, or listen)")
    if images and args.folder not in (None, "-"):
        raise ChicRegisterError(f"track {args.folder} with --igtl-images: images come over OpenIGTLink; give '-' "
                                "instead of a folder")
    if not images and args.folder in (None, "-"):
        raise ChicRegisterError("track: give the FOLDER to watch, or --igtl-images HOST:PORT")
    if not images and not Path(args.folder).is_dir():
        raise ChicRegisterError(f"{args.folder}: not a folder")
    if args.igtl_images is not None:
        parse_address(args.igtl_images, "--igtl-images")
    if args.igtl_images_listen is not None:
        check_port(args.igtl_images_listen, "--igtl-images-listen")
    plan = OutputPlan.from_args(args).check()
    if not (args.poll > 0 and args.settle >= 0):
        raise ChicRegisterError(f"--poll must be > 0 and --settle >= 0 s, got {args.poll:g} and {args.settle:g}")
    if args.max_files is not None and args.max_files < 1:
        raise ChicRegisterError(f"--max-files must be >= 1, got {args.max_files}")
    check_spacing_flag(args)
    if args.scale_sd is not None and not (0 <= args.scale_sd <= 5 and math.isfinite(args.scale_sd)):
        raise ChicRegisterError(f"--scale-sd takes a per cent in [0, 5], got {args.scale_sd:g}")
    geom = load_geometry(args.geometry)
    if args.scene and not Path(args.scene).is_dir():
        Path(args.scene).mkdir()  # its parent exists (checked above)

    count = 0

    def on_event(event):
        nonlocal count
        count += 1
        print(json.dumps(event.to_dict()) if args.json else event.text(), flush=True)
        if args.scene and event.status == "ok" and not any(f.startswith("--scene") for f in event.failed):
            # the scene of each image is DIR/<image name>/ (an IMAGE message's name: image_NNNNN, by arrival)
            mrml = Path(args.scene) / (f"image_{count:05d}" if images else Path(event.source).name) / "scene.mrml"
            if mrml.is_file():
                note(args, f"wrote {mrml}")

    def on_message(text):
        status(text)

    common = dict(scene_dir=args.scene, geometry_path=args.geometry, on_event=on_event, on_message=on_message)
    if args.scale_sd is not None:
        common["scale_sd"] = args.scale_sd / 100.0
    if images:
        listen = IgtlServer(args.igtl_images_listen) if args.igtl_images_listen is not None else None
        where = f"port {listen.port}" if listen else args.igtl_images
        on_message(f"registering IMAGE messages from the scanner bridge at {where} (Ctrl-C to stop)")
        try:
            summary = track_images(geom, connect=args.igtl_images, listen=listen, name=plan.igtl_name,
                                   max_images=args.max_files, timeout_s=args.timeout, **common)
        finally:
            if listen is not None:
                listen.close()
    else:
        link = plan.open_link()
        if plan.igtl_listen is not None:
            on_message(f"OpenIGTLink server listening on port {link.port}")
        if not args.json:
            print(f"watching {args.folder} (Ctrl-C to stop)", file=sys.stderr, flush=True)
        summary = track(args.folder, geom, pixel_spacing=args.pixel_spacing, poll_s=args.poll, settle_s=args.settle,
                        include_existing=args.existing, max_files=args.max_files, timeout_s=args.timeout,
                        igtl_name=plan.igtl_name, link=link, **common)
    if args.json:
        print(json.dumps(summary.to_dict()), flush=True)
    else:
        print(summary.text(), file=sys.stderr, flush=True)
    return EXIT_OUTPUT_FAILED if summary.outputs_failed else 0
