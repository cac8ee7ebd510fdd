"""What several chic-register commands share: the OpenIGTLink flags, the pixel-spacing check, a reference pose.

add_igtl_args gives solve and track the same OpenIGTLink flags;
check_spacing_flag runs before solve and track read a file; load_reference
reads the pose of reslice --reference, load_prior that of solve --prior.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

from chic_register.errors import ChicRegisterError, InputFileError

if TYPE_CHECKING:  # annotations only
    import numpy as np

#: ``--prior`` words that stand for a pose: the frame's axes along the scanner's LPS axes.
PRIOR_WORDS = ("identity",)


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
    """The pose of solve --prior: a JSON or .tfm file (load_reference), or the word identity
    (F's x, y, z along the scanner's LPS x, y, z; only a prior's rotation is used) when no file has that name."""
    import numpy as np  # here, not at the top: keeps start-up fast

    if str(value).strip().lower() in PRIOR_WORDS and not Path(value).exists():
        return np.eye(4)
    return load_reference(value, "--prior")
