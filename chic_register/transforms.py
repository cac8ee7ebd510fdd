"""ITK transform files (``.tfm``) of a registration, for 3D Slicer and SimpleITK.

Direction convention (stated once, here and in the README):

- ITK stores a transform in the *resampling* convention: it maps points of
  the fixed (output) space to the moving (input) space. Files are in LPS.
- 3D Slicer loads an ITK file as the node's "transform from parent" and
  converts LPS to RAS itself, so the node's "to parent" transform is the
  inverse of the file's.
- So that a model drawn in the fiducial frame F, placed under the loaded
  transform in Slicer, lands where the fiducial is in the scanner, the file
  holds ``T_fiducial_from_scanner = inverse(T_scanner_from_fiducial)`` in LPS
  (fixed space = scanner, moving space = F). ``sitk.ReadTransform(path)``
  therefore maps scanner points (LPS mm) to F points (mm);
  ``.GetInverse()`` maps F to scanner, i.e. equals ``T_scanner_from_fiducial``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import SimpleITK as sitk

from .atomic import atomic_path
from .errors import ChicRegisterError
from .pose import invert

SUFFIXES = (".tfm", ".txt", ".h5", ".hdf5")


def _check_rigid(T: np.ndarray) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"expected a finite 4x4 matrix, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError("T_scanner_from_fiducial is not a proper rigid transform")
    return T


def matrix_to_sitk(T: np.ndarray) -> sitk.AffineTransform:
    """A 4x4 homogeneous matrix as a SimpleITK ``AffineTransform`` (centre 0)."""
    T = np.asarray(T, dtype=float)
    tx = sitk.AffineTransform(3)
    tx.SetMatrix(T[:3, :3].ravel().tolist())
    tx.SetTranslation(T[:3, 3].tolist())
    return tx


def sitk_to_matrix(tx: sitk.Transform) -> np.ndarray:
    """4x4 matrix of a SimpleITK linear transform (affine, Euler, versor, composite of one)."""
    if tx.GetName() == "CompositeTransform":
        comp = sitk.CompositeTransform(tx)
        if comp.GetNumberOfTransforms() != 1:
            raise ValueError("composite transform with more than one member")
        tx = comp.GetNthTransform(0)
    # Probe with points: works for every linear transform class without
    # depending on its parameterisation (centre, versor, ...).
    o = np.array(tx.TransformPoint((0.0, 0.0, 0.0)))
    T = np.eye(4)
    for i in range(3):
        e = [0.0, 0.0, 0.0]
        e[i] = 1.0
        T[:3, i] = np.array(tx.TransformPoint(tuple(e))) - o
    T[:3, 3] = o
    return T


def write_tfm(T_scanner_from_fiducial, path) -> Path:
    """Write the registration as an ITK transform file, atomically.

    ``T_scanner_from_fiducial``: 4x4, F (mm) -> scanner LPS (mm). The file
    holds its inverse (resampling convention, see the module docstring);
    ``.tfm``/``.txt`` give ITK's text format, ``.h5`` HDF5.
    """
    path = Path(path)
    if path.suffix.lower() not in SUFFIXES:
        raise ChicRegisterError(f"{path}: transform file must end in {', '.join(SUFFIXES)}")
    T = _check_rigid(T_scanner_from_fiducial)
    tx = matrix_to_sitk(invert(T))
    try:
        with atomic_path(path) as tmp:
            sitk.WriteTransform(tx, str(tmp))
    except RuntimeError as exc:
        raise ChicRegisterError(f"{path}: cannot write transform: {str(exc).strip().splitlines()[-1]}") from None
    return path


def read_tfm(path) -> np.ndarray:
    """``T_scanner_from_fiducial`` (4x4) from a file written by :func:`write_tfm`."""
    path = Path(path)
    if not path.is_file():
        raise ChicRegisterError(f"{path}: no such transform file")
    try:
        tx = sitk.ReadTransform(str(path))
    except RuntimeError:
        raise ChicRegisterError(f"{path}: not an ITK transform file") from None
    return np.linalg.inv(sitk_to_matrix(tx))
