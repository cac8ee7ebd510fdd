"""``chic-register simulate`` (the command layer): a synthetic slice or volume at a known pose, and its truth file."""

from __future__ import annotations

import sys

from chic_register.errors import ChicRegisterError


def _blob_width_check(factor: float) -> tuple[bool, str]:
    from chic_register.imaging.blob_width import BLOB_WIDTH_RANGE

    lo, hi = BLOB_WIDTH_RANGE
    return lo <= factor <= hi, f"--blob-width must be {lo:g}..{hi:g} (x the nominal diameter), got {factor:g}"


def run_simulate(args) -> int:
    if args.volume_shape is not None:
        return _run_simulate_volume(args)
    from pathlib import Path

    import numpy as np

    from chic_register.imaging.simulate import (
        DICOM_SUFFIXES,
        simulate_slice,
        write_simulated,
    )
    from chic_register.io.images import MAX_SPACING_MM, MIN_SPACING_MM, PLAIN_SUFFIXES
    from chic_register.model.geometry import load_geometry

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


def _run_simulate_volume(args) -> int:
    """simulate --volume-shape: a synthetic volume and <out>.truth.json."""
    from pathlib import Path

    import numpy as np

    from chic_register.imaging.simulate import simulate_volume, truth_path
    from chic_register.io.images import MAX_SPACING_MM, MIN_SPACING_MM
    from chic_register.io.volumes import MAX_VOXELS, write_volume
    from chic_register.model.geometry import load_geometry
    from chic_register.model.pose import invert, slice_frame
    from chic_register.util.atomic import write_json

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
