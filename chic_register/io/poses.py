"""A registered pose read back from a file: the JSON that ``solve --json`` prints, or a ``.tfm`` of ``solve --tfm``.

The JSON gives ``T_scanner_from_fiducial`` and, when the solver measured it,
``covariance`` (``{"parameters", "frame", "matrix"}``, docs/interfaces.md
section 4) and ``geometry`` (``{"name", "sha256"}``); a ``.tfm`` holds only the
transform. Faults are one :class:`~chic_register.errors.InputFileError`
naming the file and the key.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from chic_register.errors import ChicRegisterError, InputFileError
from chic_register.model.body import rigid_4x4
from chic_register.model.pose_params import PARAMETER_ORDER
from chic_register.util.safeload import read_regular_file

MAX_POSE_FILE_BYTES = 32 << 20  # a solve --json of a whole volume, with every slice's candidates
TRANSFORM_SUFFIXES = (".tfm", ".txt", ".h5", ".hdf5")  # as chic_register.io.transforms (which loads SimpleITK)


@dataclass(frozen=True, eq=False)
class PoseRecord:
    """A pose from a file: ``T_scanner_from_fiducial`` (4x4, mm), its ``covariance_deg_mm`` (6x6, order
    :data:`~chic_register.model.pose_params.PARAMETER_ORDER`) or None, the ``geometry_sha256`` it was solved
    with (or ""), and the ``source`` file."""

    T_scanner_from_fiducial: np.ndarray
    covariance_deg_mm: np.ndarray | None
    geometry_sha256: str
    source: str


def _covariance(path, value) -> np.ndarray:
    if not isinstance(value, dict) or "matrix" not in value:
        raise InputFileError(path, "covariance must be an object with key 'matrix' (6x6)")
    params = value.get("parameters", list(PARAMETER_ORDER))
    if list(params) != list(PARAMETER_ORDER):
        raise InputFileError(path, f"covariance.parameters must be {', '.join(PARAMETER_ORDER)}")
    try:
        C = np.asarray(value["matrix"], dtype=float)
    except (TypeError, ValueError):
        C = np.zeros(0)
    if C.shape != (6, 6) or not np.all(np.isfinite(C)) or not np.allclose(C, C.T, rtol=1e-6, atol=1e-12):
        raise InputFileError(path, "covariance.matrix must be a finite symmetric 6x6 matrix")
    if np.linalg.eigvalsh(0.5 * (C + C.T))[0] < -1e-9 * max(1.0, float(np.abs(C).max())):
        raise InputFileError(path, "covariance.matrix is not positive semi-definite")
    return 0.5 * (C + C.T)


def read_pose(path) -> PoseRecord:
    """The pose in ``path``: a ``solve --json`` object (``T_scanner_from_fiducial``, optional ``covariance``) or
    an ITK transform file written by ``solve --tfm`` (no covariance)."""
    p = Path(path)
    if p.suffix.lower() in TRANSFORM_SUFFIXES:
        from chic_register.io.transforms import read_tfm  # deferred: loads SimpleITK only when used

        try:
            T = read_tfm(p)
        except ChicRegisterError as exc:
            raise InputFileError(p, str(exc).split(": ", 1)[-1]) from None
        if rigid_4x4(T) is None:
            raise InputFileError(p, "the transform is not rigid (rotation and translation)")
        return PoseRecord(T, None, "", str(p))
    data = read_regular_file(p, "pose file", max_bytes=MAX_POSE_FILE_BYTES)
    try:
        doc = json.loads(data.decode("utf-8-sig"))
    except (UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        raise InputFileError(p, f"not a JSON file ({str(exc).splitlines()[0][:100]})") from None
    if not isinstance(doc, dict) or "T_scanner_from_fiducial" not in doc:
        status = doc.get("status") if isinstance(doc, dict) else None
        why = f" (status {status!r}: no pose)" if status not in (None, "ok") else ""
        raise InputFileError(p, f"needs key 'T_scanner_from_fiducial' (the JSON of chic-register solve --json){why}")
    T = rigid_4x4(doc["T_scanner_from_fiducial"])
    if T is None:
        raise InputFileError(p, "T_scanner_from_fiducial must be a rigid 4x4 matrix (rotation, translation, 0 0 0 1)")
    cov = _covariance(p, doc["covariance"]) if doc.get("covariance") is not None else None
    geometry = doc.get("geometry")
    sha = str(geometry.get("sha256", "")) if isinstance(geometry, dict) else ""
    return PoseRecord(T, cov, sha, str(p))
