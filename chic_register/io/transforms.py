"""Frames for 3D Slicer and robots, and ITK transform files (``.tfm``) of a registration.

The frame convention (docs/interfaces.md section 5, stated in code here only):

- Every model we export (``body.stl``, the scene's tube and tool models) is
  written in F and declares ``SPACE=LPS``: Slicer reads its coordinates as
  LPS, i.e. F is taken to be an LPS-like frame ("F-as-LPS"), exactly as ITK
  takes the moving space of the ``.tfm``. Slicer then holds the model in
  ``diag(-1,-1,1) p_F`` and the matrix that puts it in place is
  :func:`slicer_matrix` = ``diag(-1,-1,1,1) T diag(-1,-1,1,1)``. The ``.tfm``
  yields that matrix in Slicer, and so does the OpenIGTLink TRANSFORM named
  ``CHIC``.
- A robot controller that works in F gets :func:`ras_matrix` =
  ``diag(-1,-1,1,1) T``: F (as designed) to RAS, under ``CHICToRAS``.

ITK direction convention:

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

from chic_register.errors import ChicRegisterError
from chic_register.model.pose import invert
from chic_register.util.atomic import atomic_path

SUFFIXES = (".tfm", ".txt", ".h5", ".hdf5")


LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
MODEL_SPACE = "LPS"  # the coordinate system every exported model declares (STL ``SPACE=`` header)


def _as_4x4(T) -> np.ndarray:
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"expected a 4x4 matrix, got shape {T.shape}")
    return T


def ras_matrix(T_scanner_from_frame) -> np.ndarray:
    """F (or the tool frame) as designed -> RAS: ``diag(-1,-1,1,1) @ T`` (for robots working in F)."""
    return LPS_TO_RAS @ _as_4x4(T_scanner_from_frame)


def slicer_matrix(T_scanner_from_frame) -> np.ndarray:
    """Slicer's "to parent" matrix (RAS) that places a ``SPACE=LPS`` model drawn in the frame.

    ``diag(-1,-1,1,1) @ T @ diag(-1,-1,1,1)``: what a ``.tfm`` holding
    ``inverse(T)`` becomes when Slicer loads it.
    """
    return LPS_TO_RAS @ _as_4x4(T_scanner_from_frame) @ LPS_TO_RAS


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
