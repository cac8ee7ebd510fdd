"""3-D volumes: read NIfTI, NRRD and DICOM series, write them back, simulate one.

Everything is in the scanner frame LPS (docs/interfaces.md section 3). SimpleITK
reports every format's physical space in LPS: it converts NIfTI's RAS
(qform/sform) and NRRD's ``space`` field (``right-anterior-superior`` or
``left-posterior-superior``) itself, and reads DICOM's LPS as is
(tests/test_volume.py checks this against nibabel and pynrrd).

Index convention: ``voxels[k, j, i]`` (SimpleITK's array order, z slowest);
``affine_lps`` maps the voxel index ``(i, j, k, 1)`` to LPS mm, so column
``i`` is the direction of the fastest array axis.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from chic_register.errors import ChicRegisterError, ImageReadError, InputFileError
from chic_register.io.images import VOLUME_SUFFIXES as FILE_SUFFIXES
from chic_register.io.images import file_suffix
from chic_register.io.limits import MAX_SPACING_MM, MIN_SPACING_MM, check_voxels, last_line
from chic_register.io.nrrd import read_nrrd
from chic_register.model.slices import Slice
from chic_register.util.atomic import atomic_path
from chic_register.util.safeload import open_regular_file

if TYPE_CHECKING:  # annotations only: SimpleITK is imported where it is used
    import SimpleITK as sitk

WRITE_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".mha")


@dataclass(frozen=True, eq=False)
class Volume:
    """Voxels plus their place in the scanner.

    ``voxels``: shape (nk, nj, ni). ``spacing_mm``: (si, sj, sk), the voxel
    pitch along i, j, k. ``origin_mm``: LPS centre of voxel (0, 0, 0).
    ``direction``: 3x3, column c is the LPS unit direction of index axis c
    (i, j, k).
    """

    voxels: np.ndarray
    spacing_mm: tuple[float, float, float]
    origin_mm: np.ndarray = field(default_factory=lambda: np.zeros(3))
    direction: np.ndarray = field(default_factory=lambda: np.eye(3))
    source: str = "<array>"
    slice_thickness_mm: float | None = None  # when the file says (DICOM SliceThickness); else the k spacing
    modality: str = "auto"  # each native slice's (chic_register.model.slices.Slice.modality)

    def __post_init__(self):
        if np.ndim(self.voxels) != 3:
            raise ValueError(f"voxels must be 3-D (nk, nj, ni), got shape {np.shape(self.voxels)}")
        object.__setattr__(self, "spacing_mm", tuple(float(s) for s in self.spacing_mm))
        object.__setattr__(self, "origin_mm", np.asarray(self.origin_mm, dtype=float).reshape(3))
        object.__setattr__(self, "direction", np.asarray(self.direction, dtype=float).reshape(3, 3))

    @property
    def shape(self) -> tuple[int, int, int]:
        """Array shape (nk, nj, ni)."""
        return tuple(self.voxels.shape)

    @property
    def size_ijk(self) -> tuple[int, int, int]:
        """Number of voxels along i, j, k (NX, NY, NZ)."""
        nk, nj, ni = self.voxels.shape
        return (ni, nj, nk)

    @property
    def affine_lps(self) -> np.ndarray:
        """4x4 from voxel index (i, j, k, 1) to LPS mm."""
        A = np.eye(4)
        A[:3, :3] = self.direction * np.asarray(self.spacing_mm)[None, :]
        A[:3, 3] = self.origin_mm
        return A

    def index_to_lps(self, ijk) -> np.ndarray:
        """Voxel indices, shape (N, 3) as (i, j, k), to LPS points (mm), shape (N, 3)."""
        ijk = np.atleast_2d(np.asarray(ijk, dtype=float))
        A = self.affine_lps
        return ijk @ A[:3, :3].T + A[:3, 3]

    def native_slice(self, k: int) -> Slice:
        """The acquired slice ``k`` as a :class:`Slice`: rows along j, columns along i."""
        nk = self.voxels.shape[0]
        if not -nk <= int(k) < nk:
            raise ChicRegisterError(f"{self.source}: slice index {k} is outside 0..{nk - 1}")
        k = int(k) % nk
        si, sj, sk = self.spacing_mm
        return Slice(
            pixels=np.asarray(self.voxels[k], dtype=float),
            pixel_spacing_mm=(sj, si),
            origin_mm=self.origin_mm + k * sk * self.direction[:, 2],
            col_dir=self.direction[:, 0].copy(),
            row_dir=self.direction[:, 1].copy(),
            slice_thickness_mm=self.thickness_mm,
            source=f"{self.source}[k={k}]",
            modality=self.modality,
        )

    @property
    def thickness_mm(self) -> float:
        """Each k-slice's thickness: the file's own (DICOM SliceThickness: slices with gaps, or overlapping),
        else the k spacing."""
        t = self.slice_thickness_mm
        return float(t) if t is not None and math.isfinite(t) and t > 0 else float(self.spacing_mm[2])

    def to_sitk(self) -> sitk.Image:
        import SimpleITK as sitk  # (imported where used: a one-slice DICOM solve never needs it)

        img = sitk.GetImageFromArray(np.ascontiguousarray(self.voxels))
        img.SetSpacing(self.spacing_mm)
        img.SetOrigin(tuple(self.origin_mm))
        img.SetDirection(tuple(self.direction.ravel()))
        return img


def volume_from_sitk(img: sitk.Image, source: str = "<sitk>", slice_thickness_mm: float | None = None) -> Volume:
    """A :class:`Volume` from a 3-D scalar SimpleITK image."""
    import SimpleITK as sitk  # deferred: loads SimpleITK only when used (one-shot start-up)

    if img.GetDimension() != 3:
        raise ImageReadError(source, f"expected a 3-D volume, got {img.GetDimension()}-D")
    if img.GetNumberOfComponentsPerPixel() != 1:
        raise ImageReadError(source, f"expected scalar voxels, got {img.GetNumberOfComponentsPerPixel()} components")
    return checked_volume(sitk.GetArrayFromImage(img), img.GetSpacing(), np.array(img.GetOrigin()),
                          np.array(img.GetDirection()).reshape(3, 3), source, slice_thickness_mm)


def checked_volume(voxels: np.ndarray, spacing_mm, origin_mm: np.ndarray, direction: np.ndarray, source: str,
                   slice_thickness_mm: float | None = None) -> Volume:
    """A :class:`Volume` of voxels (nk, nj, ni) at a spacing (si, sj, sk) within the readable range, a finite origin
    and an orthonormal direction (3, 3); :class:`ImageReadError` naming ``source`` otherwise."""
    spacing, origin = np.asarray(spacing_mm, float), np.asarray(origin_mm, float)
    if not np.all(np.isfinite(spacing) & (spacing >= MIN_SPACING_MM) & (spacing <= MAX_SPACING_MM)):
        raise ImageReadError(source, f"voxel spacing must be three numbers in {MIN_SPACING_MM:g}..{MAX_SPACING_MM:g} "
                                     f"mm, got {spacing.tolist()}")
    if not (np.all(np.isfinite(origin)) and np.allclose(direction.T @ direction, np.eye(3), atol=1e-3)):
        raise ImageReadError(source, "volume origin/direction are not a finite position and an orthonormal frame")
    return Volume(voxels=voxels, spacing_mm=tuple(float(s) for s in spacing), origin_mm=origin, direction=direction,
                  source=source, slice_thickness_mm=slice_thickness_mm)


def read_volume(path, series_id: str | None = None) -> Volume:
    """Read a NIfTI / NRRD / MetaImage file, or a folder holding one DICOM series.

    Raises :class:`ImageReadError` naming the path for a missing, unreadable
    or non-3-D input, or a folder with no or several DICOM series (pass
    ``series_id``, a SeriesInstanceUID or a SeriesNumber, to pick one; the
    message lists them).
    """
    path = Path(path)
    if not path.exists():
        raise ImageReadError(path, "no such file or folder")
    if not path.is_dir():
        if series_id is not None:
            raise ImageReadError(path, "--series applies to a folder of DICOM files, not a volume file")
        if file_suffix(path) not in FILE_SUFFIXES:
            raise ImageReadError(path, f"not a volume file; allowed: {', '.join(FILE_SUFFIXES)} or a DICOM series folder")
        try:
            open_regular_file(path, "volume file").close()  # a FIFO or device is refused, not waited on
        except InputFileError as exc:
            raise ImageReadError(path, exc.detail) from None
        plain = read_nrrd(path) if file_suffix(path) in (".nrrd", ".nhdr") else None
        if plain is not None:
            return checked_volume(*plain, source=str(path))
    import SimpleITK as sitk  # deferred: loads SimpleITK only when used (one-shot start-up)

    if path.is_dir():
        from chic_register.io.dicom import read_dicom_series  # deferred: loads pydicom only for a DICOM folder

        img, thickness_mm = read_dicom_series(path, series_id)
        if img.GetDimension() == 3:
            return volume_from_sitk(img, source=str(path), slice_thickness_mm=thickness_mm)
    else:
        try:
            reader = sitk.ImageFileReader()
            reader.SetFileName(str(path))
            reader.ReadImageInformation()
            check_voxels(path, reader.GetSize(), reader.GetNumberOfComponents())
            img = reader.Execute()
        except RuntimeError as exc:
            raise ImageReadError(path, f"cannot read volume: {last_line(exc)}") from None
    if img.GetDimension() == 4 and img.GetSize()[3] == 1:
        img = img[:, :, :, 0]
    if img.GetDimension() == 2:
        img = single_slice_3d(img, reader if not path.is_dir() else None)
    return volume_from_sitk(img, source=str(path))


def _srow_lps(reader) -> np.ndarray | None:
    """A NIfTI header's sform (``srow_x/y/z``, RAS) as a 4x4 affine in LPS, or None without one."""
    try:
        if int(reader.GetMetaData("sform_code")) <= 0:
            return None
        rows = [[float(v) for v in reader.GetMetaData(f"srow_{a}").split()] for a in "xyz"]
    except (RuntimeError, ValueError):
        return None
    A = np.vstack([np.array(rows), [0.0, 0.0, 0.0, 1.0]])
    if A.shape != (4, 4) or not np.all(np.isfinite(A)):
        return None
    return np.diag([-1.0, -1.0, 1.0, 1.0]) @ A  # RAS -> LPS


def single_slice_3d(img: sitk.Image, reader=None) -> sitk.Image:
    """A 2-D image (one slice, as a 2-D NIfTI or NRRD) as a one-slice 3-D image.

    A NIfTI file keeps its full 3-D place from the sform (SimpleITK drops the
    third row and column when it reads a 2-D file); otherwise the slice lies
    in the plane z = 0 of its own frame, its normal +z, and its third spacing
    is 1 mm (the slice's thickness is not known from a 2-D file).
    """
    import SimpleITK as sitk  # deferred: loads SimpleITK only when used (one-shot start-up)

    out = sitk.JoinSeries(img)
    A = _srow_lps(reader) if reader is not None else None
    if A is not None:
        spacing = np.linalg.norm(A[:3, :3], axis=0)
        if np.all(spacing > 0):
            direction = A[:3, :3] / spacing
            if np.allclose(direction.T @ direction, np.eye(3), atol=1e-3):
                out.SetSpacing(tuple(float(v) for v in spacing))
                out.SetOrigin(tuple(float(v) for v in A[:3, 3]))
                out.SetDirection(tuple(float(v) for v in direction.ravel()))
                return out
    d2 = np.array(img.GetDirection()).reshape(2, 2)
    direction = np.eye(3)
    direction[:2, :2] = d2
    out.SetDirection(tuple(direction.ravel()))
    out.SetOrigin((*img.GetOrigin(), 0.0))
    return out


def _replace_dir(tmp: Path, path: Path) -> None:
    """Move folder ``tmp`` to ``path``, replacing an earlier folder there."""
    if path.exists():
        old = path.with_name(f".{path.name}.old-{os.getpid()}")
        os.replace(path, old)
        os.replace(tmp, path)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, path)


def write_volume(volume: Volume, path) -> Path:
    """Write ``volume`` atomically: ``.nii``, ``.nii.gz``, ``.nrrd`` or ``.mha`` file, or a DICOM series folder.

    A path without one of those suffixes is a folder: one DICOM file per
    k-slice (MR Image Storage, int16 with rescale slope/intercept when the
    voxels are not already int16-representable integers).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    suffix = file_suffix(path)
    if suffix in WRITE_SUFFIXES:
        import SimpleITK as sitk  # deferred: loads SimpleITK only when used (one-shot start-up)

        try:
            with atomic_path(path, suffix=suffix) as tmp:
                sitk.WriteImage(volume.to_sitk(), str(tmp))
        except RuntimeError as exc:
            raise ChicRegisterError(f"{path}: cannot write volume: {last_line(exc)}") from None
        return path
    if suffix in (".dcm", ".gz", ".nhdr", ".mhd", ".png", ".tif", ".tiff", ".npy", ".json"):
        raise ChicRegisterError(
            f"{path}: volume output must end in {', '.join(WRITE_SUFFIXES)}, or be a folder name (DICOM series)"
        )
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}-", dir=path.parent))
    try:
        from chic_register.io.dicom import write_dicom_series  # deferred: loads pydicom only for a DICOM folder

        write_dicom_series(volume, tmp)
        _replace_dir(tmp, path)
    except RuntimeError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        raise ChicRegisterError(f"{path}: cannot write DICOM series: {last_line(exc)}") from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return path


# --------------------------------------------------------------------------- simulated volumes


def plane_frame(volume_or_grid, k: float) -> np.ndarray:
    """``T_scanner_from_plane`` (4x4) of the k-plane: origin at voxel (0, 0, k), x along i, y along j."""
    v = volume_or_grid
    x, y = v.direction[:, 0], v.direction[:, 1]
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2] = x, y, np.cross(x, y)
    T[:3, 3] = v.origin_mm + k * v.spacing_mm[2] * v.direction[:, 2]
    return T


