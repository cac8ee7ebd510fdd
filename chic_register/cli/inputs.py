"""What several chic-register commands share: the OpenIGTLink flags, the pixel-spacing check, a reference pose.

add_igtl_args gives solve and track the same OpenIGTLink flags;
check_spacing_flag runs before solve and track read a file; load_reference
reads the pose of reslice --reference, load_prior that of solve --prior.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import TYPE_CHECKING

from chic_register.errors import ChicRegisterError, InputFileError

if TYPE_CHECKING:  # annotations only
    import numpy as np

#: ``--prior`` words that stand for a pose: ``identity`` (the frame's axes along the scanner's LPS axes), or three
#: letters naming the scanner direction each of the frame's x, y, z points along, one of each pair R/L, A/P, S/I
#: (``RAS``: x to the patient's right, y anterior, z superior; ``LPS`` is ``identity``).
PRIOR_WORDS = ("identity",)
#: The scanner's (LPS) unit vector each orientation letter names.
ORIENTATION_LETTERS = {"L": (1, 0, 0), "R": (-1, 0, 0), "P": (0, 1, 0), "A": (0, -1, 0), "S": (0, 0, 1),
                       "I": (0, 0, -1)}


def orientation_rotation(code: str):
    """The rotation (3x3, scanner LPS from frame) of an orientation code such as ``RAS``; None when ``code`` is
    not three letters naming each axis pair once; :class:`ChicRegisterError` for a left-handed code."""
    import numpy as np  # here, not at the top: keeps start-up fast

    letters = str(code).strip().upper()
    if len(letters) != 3 or any(c not in ORIENTATION_LETTERS for c in letters):
        return None
    R = np.array([ORIENTATION_LETTERS[c] for c in letters], dtype=float).T
    if sorted(int(np.argmax(np.abs(R[:, j]))) for j in range(3)) != [0, 1, 2]:
        return None  # an axis pair named twice (RLS)
    if np.linalg.det(R) < 0:
        raise ChicRegisterError(f"--prior {code}: a left-handed set of directions; the frame's z follows from its "
                                "x and y by the right-hand rule (e.g. RAS, LPS, LAI)")
    return R


def add_igtl_args(p) -> None:
    """The OpenIGTLink output flags of solve and track."""
    p.add_argument("--igtl", metavar="HOST:PORT", help="also send the pose over OpenIGTLink to a listening server, "
                   "e.g. 3D Slicer's OpenIGTLinkIF at 127.0.0.1:18944 (TRANSFORMs, quality STRING, STATUS)")
    p.add_argument("--igtl-listen", type=int, metavar="PORT", help="be the OpenIGTLink server instead: listen on "
                   "PORT and send to every peer that connects (0: any free port)")
    p.add_argument("--igtl-wait", type=float, default=10.0, metavar="S",
                   help="with --igtl-listen: wait this long for a first peer before sending (default 10 s)")
    p.add_argument("--igtl-name", default="CHIC", metavar="NAME",
                   help="OpenIGTLink device name (default CHIC; also NAMEToRAS, NAMETool, NAMEToolToRAS, NAMEQuality)")


def check_spacing_flag(args) -> None:
    """A --pixel-spacing outside the physical range is refused before any file is read."""
    from chic_register.io.limits import spacing_fault  # here, not at the top: keeps start-up fast

    if getattr(args, "pixel_spacing", None) is not None:
        fault = spacing_fault(args.pixel_spacing)
        if fault:
            raise ChicRegisterError(f"--pixel-spacing: {fault}")


def load_reference(path, flag: str = "--reference") -> "np.ndarray":
    """T_scanner_from_fiducial from a JSON file (any object with that key) or a .tfm file."""
    import numpy as np  # here, not at the top: keeps start-up fast

    from chic_register.io.transforms import SUFFIXES, read_tfm
    from chic_register.util.safeload import read_regular_file

    p = Path(path)
    if p.suffix.lower() in SUFFIXES:
        return read_tfm(p)
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


def load_prior(value) -> "np.ndarray":
    """The pose of solve --prior: a JSON or .tfm file (load_reference), or, when no file has that name, the word
    identity (F's x, y, z along the scanner's LPS x, y, z) or an orientation code such as RAS
    (:func:`orientation_rotation`); only a prior's rotation is used."""
    import numpy as np  # here, not at the top: keeps start-up fast

    if not Path(value).exists():
        if str(value).strip().lower() in PRIOR_WORDS:
            return np.eye(4)
        R = orientation_rotation(value)
        if R is not None:
            T = np.eye(4)
            T[:3, :3] = R
            return T
    return load_reference(value, "--prior")


def read_image_inputs(args) -> tuple[list, bool, tuple | None]:
    """The slices of solve, whether failing ones may be skipped, and ``(volume, indices)`` when the input is one
    volume (registered by :func:`~chic_register.pipeline.volume.register_volume`, as the library does; indices
    None: every native slice, those that do not lock skipped and reported).

    2-D image files as they are; a volume by its --slices indices and
    ranges, or, without them, every native slice; a volume file of one
    slice (a 2-D NIfTI) as a slice.
    """
    from chic_register.io.images import is_volume_path, read_slices  # here, not at the top: keeps start-up fast

    check_spacing_flag(args)
    volumes = [p for p in args.images if is_volume_path(p)]
    if args.slices and not volumes:
        raise ChicRegisterError("--slices applies to volume inputs (.nii, .nii.gz, .nrrd, .mha, DICOM series folder)")
    if args.series is not None and not any(Path(p).is_dir() for p in args.images):
        raise ChicRegisterError("--series applies to a folder of DICOM files (the series to read from it)")
    slices, volume, single = [], None, []
    for path in args.images:
        if is_volume_path(path):
            # here, not in run: a one-shot solve of 2-D slices stays fast without the volume readers (SimpleITK)
            from chic_register.io.volumes import read_volume
            from chic_register.pipeline.volume import parse_slice_indices

            vol = read_volume(path, args.series)
            if getattr(args, "modality", "auto") != "auto":
                vol = dataclasses.replace(vol, modality=args.modality)
            nk = vol.shape[0]
            if nk == 1:  # a one-slice file (a 2-D NIfTI): a slice, registered as one
                single.append(path)
                slices.append(vol.native_slice(0))
                continue
            ks = parse_slice_indices(args.slices, nk) if args.slices else range(nk)
            slices.extend(vol.native_slice(k) for k in ks)
            volume = (vol, list(ks) if args.slices else None)
        else:
            read = read_slices([path], args.pixel_spacing)
            if getattr(args, "modality", "auto") != "auto":
                read = [dataclasses.replace(sl, modality=args.modality) for sl in read]
            slices.extend(read)
    skip = bool(set(volumes) - set(single)) and not args.slices
    return slices, skip, volume if len(args.images) == 1 else None


def prior_options(args) -> dict:
    """The ``SolveOptions`` fields of ``--prior`` and ``--prior-max-deg`` (none without a prior)."""
    if not args.prior:
        return {}
    if not (0 < args.prior_max_deg <= 180):
        raise ChicRegisterError(f"--prior-max-deg must be in (0, 180] deg, got {args.prior_max_deg:g}")
    return {"prior": load_prior(args.prior), "prior_max_deg": args.prior_max_deg}


def register_inputs(slices, skip: bool, volume, geom, **options):
    """Register what :func:`read_image_inputs` read: one volume through the library's volume registration (wide
    blobs and all), else the slices (``skip``: those that do not lock are left out)."""
    if volume is not None:
        from chic_register.pipeline.volume import register_volume  # here: a 2-D solve never loads it

        return register_volume(volume[0], geom, volume[1], **options)
    from chic_register.pipeline.register import register  # here, not at the top: keeps start-up fast

    return register(slices, geom, skip_failed=skip, **options)
