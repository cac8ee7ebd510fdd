"""NRRD volumes read through pynrrd: a one-shot volume solve without SimpleITK's import (a quarter of a second).

Only the plain form a scanner export or 3D Slicer writes is read here: three spatial axes in an LPS or RAS space,
orthogonal ``space directions`` (in mm, when ``space units`` says), scalar voxels. Any other header, and any file
pynrrd cannot read, gives None, and :func:`chic_register.io.volumes.read_volume` reads it through SimpleITK as it
reads every other format (its message names what is wrong).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from chic_register.io.limits import check_voxels

#: The NRRD ``space`` values read here, and the sign that takes each axis of that space to LPS.
SPACES = {"left-posterior-superior": (1.0, 1.0, 1.0), "lps": (1.0, 1.0, 1.0),
          "right-anterior-superior": (-1.0, -1.0, 1.0), "ras": (-1.0, -1.0, 1.0)}
#: Largest ``|D^T D - I|`` of the unit ``space directions`` read here (ITK's NRRD reader orthonormalises others).
ORTHOGONAL_TOL = 1e-6


def read_nrrd(path: Path):
    """``(voxels (nk, nj, ni), spacing (si, sj, sk) mm, origin (3,) LPS mm, direction (3, 3) columns i, j, k in LPS)``
    of a plain NRRD volume (see the module docstring), or None for SimpleITK to read. :class:`ImageReadError` for a
    volume too large to read, from its header."""
    import nrrd  # deferred: only a volume solve of an NRRD file needs it

    try:
        with open(path, "rb") as fh:
            header = nrrd.read_header(fh)
            geometry = _geometry(header)
            if geometry is None:
                return None
            check_voxels(path, header["sizes"], 1)
            data = nrrd.read_data(header, fh, str(path), index_order="C")
    except (nrrd.NRRDError, OSError, ValueError, KeyError, TypeError, EOFError):
        return None
    if data.ndim != 3 or data.dtype.kind not in "biuf":
        return None
    return (np.ascontiguousarray(data.astype(data.dtype.newbyteorder("="), copy=False)), *geometry)


def _geometry(header: dict):
    """``(spacing, origin, direction)`` in LPS from a plain header, None for any other."""
    sign = SPACES.get(str(header.get("space", "")).strip().lower())
    if sign is None or int(header.get("dimension", 0)) != 3 or len(header.get("sizes", ())) != 3:
        return None
    kinds = header.get("kinds")
    if kinds is not None and any(str(k).lower() not in ("domain", "space") for k in kinds):
        return None
    units = header.get("space units")
    if units is not None and any(str(u).strip().lower() not in ("mm", "") for u in units):
        return None
    D = np.asarray(header.get("space directions"), dtype=float)  # rows: the steps along i, j, k
    origin = np.asarray(header.get("space origin", np.zeros(3)), dtype=float).reshape(-1)
    if D.shape != (3, 3) or origin.shape != (3,) or not (np.all(np.isfinite(D)) and np.all(np.isfinite(origin))):
        return None
    spacing = np.linalg.norm(D, axis=1)
    if not np.all(spacing > 0):
        return None
    direction = (D / spacing[:, None]).T * np.asarray(sign)[:, None]
    if not np.allclose(direction.T @ direction, np.eye(3), atol=ORTHOGONAL_TOL):
        return None
    return tuple(float(s) for s in spacing), origin * np.asarray(sign), direction
