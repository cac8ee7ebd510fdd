"""Inputs that several ``chic-register`` commands share: the ``--pixel-spacing`` check, a reference pose.

:func:`check_spacing_flag` runs before ``solve`` and ``track`` read a file;
:func:`load_reference` reads the pose of ``solve --prior`` and ``reslice --reference``.
"""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

from chic_register.errors import ChicRegisterError

if TYPE_CHECKING:  # annotations only: numpy is imported where it is used
    import numpy as np


def check_spacing_flag(args) -> None:
    """A --pixel-spacing outside the physical range is refused before any file is read."""
    from chic_register.io.images import spacing_fault

    if getattr(args, "pixel_spacing", None) is not None:
        fault = spacing_fault(args.pixel_spacing)
        if fault:
            raise ChicRegisterError(f"--pixel-spacing: {fault}")


def load_reference(path, flag: str = "--reference") -> "np.ndarray":
    """T_scanner_from_fiducial from a JSON file (any object with that key) or a .tfm file."""
    from pathlib import Path

    import numpy as np

    from chic_register.io.transforms import SUFFIXES, read_tfm

    p = Path(path)
    if p.suffix.lower() in SUFFIXES:
        return read_tfm(p)
    from chic_register.errors import InputFileError
    from chic_register.util.safeload import read_regular_file

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


#: ``--prior`` words that stand for a pose: the frame's axes along the scanner's LPS axes.
PRIOR_WORDS = ("identity",)


def load_prior(value) -> "np.ndarray":
    """The pose of ``solve --prior``: a JSON or .tfm file (:func:`load_reference`), or the word ``identity``
    (F's x, y, z along the scanner's LPS x, y, z; only a prior's rotation is used) when no file has that name."""
    from pathlib import Path

    import numpy as np

    if str(value).strip().lower() in PRIOR_WORDS and not Path(value).exists():
        return np.eye(4)
    return load_reference(value, "--prior")
