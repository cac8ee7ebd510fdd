"""DICOM both ways: slices and series read into the solver's objects, simulated slices and volumes written.

Reading (:func:`read_dicom_file`, :func:`read_dicom_series`): the scanner frame is LPS, from ImagePositionPatient
(centre of the first pixel), ImageOrientationPatient (col_dir, then row_dir) and PixelSpacing (row spacing, col
spacing), docs/interfaces.md section 3; RescaleSlope / RescaleIntercept are applied. Enhanced (multi-frame) images give
one slice per frame, placed by their functional groups; compressed pixel data pydicom cannot decode goes to GDCM
(through SimpleITK).

Writing (:func:`write_dicom`, :func:`write_dicom_series`): MR Image Storage files that carry the same geometry;
pixels stored as unsigned 16-bit integers, the real values back through RescaleSlope / RescaleIntercept (one
scaling for a whole series). A file holds the modules of the MR Image IOD with their type 1 and type 2 attributes
and passes ``dciodvfy`` (dicom3tools) without errors. A CT slice (``Slice.modality == "CT"``, pixels in Hounsfield
units) is written as CT Image Storage the way scanners store it: whole HU, RescaleSlope 1 and RescaleIntercept
-1024, unsigned 16 bits, or signed when padding lies below -1024 HU.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import warnings
from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.errors import InvalidDicomError
from pydicom.uid import (
    UID,
    CTImageStorage,
    ExplicitVRBigEndian,
    ExplicitVRLittleEndian,
    ImplicitVRLittleEndian,
    MRImageStorage,
    generate_uid,
)

from chic_register.errors import ImageReadError
from chic_register.io.limits import (
    LUMA,
    MAX_SPACING_MM,
    MAX_THICKNESS_MM,
    MIN_SPACING_MM,
    check_size,
    check_voxels,
    last_line,
    short_reason,
    spacing_fault,
)
from chic_register.model.slices import Slice
from chic_register.util.atomic import atomic_path
from chic_register.version import __version__

# --------------------------------------------------------------------------- reading


def _fg_item(ds, frame: int, sequence: str):
    """First item of functional-group ``sequence`` for ``frame`` (per-frame first, then shared)."""
    for groups in ("PerFrameFunctionalGroupsSequence", "SharedFunctionalGroupsSequence"):
        seq = ds.get(groups)
        if not seq:
            continue
        item = seq[frame] if groups.startswith("PerFrame") and frame < len(seq) else seq[0]
        inner = item.get(sequence)
        if inner:
            return inner[0]
    return None


def _numbers(path, value, n: int, name: str) -> np.ndarray:
    try:
        arr = np.array([float(v) for v in value], dtype=float)
    except (TypeError, ValueError):
        raise ImageReadError(path, f"DICOM {name} is not a list of numbers: {value!r}") from None
    if arr.size != n or not np.all(np.isfinite(arr)):
        raise ImageReadError(path, f"DICOM {name} must hold {n} finite numbers, got {list(value)!r}")
    return arr


def _dicom_geometry(path, ds, frame: int | None):
    """(origin, col_dir, row_dir, (row, col) spacing, thickness) of one frame."""
    if frame is None:
        src = {k: ds.get(k) for k in ("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing", "SliceThickness")}
    else:
        pos = _fg_item(ds, frame, "PlanePositionSequence")
        ori = _fg_item(ds, frame, "PlaneOrientationSequence")
        meas = _fg_item(ds, frame, "PixelMeasuresSequence")
        src = {
            "ImagePositionPatient": pos.get("ImagePositionPatient") if pos else None,
            "ImageOrientationPatient": ori.get("ImageOrientationPatient") if ori else None,
            "PixelSpacing": meas.get("PixelSpacing") if meas else None,
            "SliceThickness": meas.get("SliceThickness") if meas else None,
        }
    missing = [k for k in ("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing") if src[k] in (None, "")]
    if missing:
        where = "" if frame is None else f" (frame {frame + 1})"
        raise ImageReadError(
            path, f"DICOM has no image geometry{where}: missing {', '.join(missing)}; cannot place the slice in the scanner"
        )
    origin = _numbers(path, src["ImagePositionPatient"], 3, "ImagePositionPatient")
    ori = _numbers(path, src["ImageOrientationPatient"], 6, "ImageOrientationPatient")
    spacing = _numbers(path, src["PixelSpacing"], 2, "PixelSpacing")
    col_dir, row_dir = ori[:3], ori[3:]
    nc, nr = np.linalg.norm(col_dir), np.linalg.norm(row_dir)
    if abs(nc - 1) > 1e-3 or abs(nr - 1) > 1e-3 or abs(float(col_dir @ row_dir)) > 1e-3:
        raise ImageReadError(path, f"DICOM ImageOrientationPatient is not two orthonormal vectors: {ori.tolist()}")
    row_dir = row_dir - (row_dir @ col_dir) / nc**2 * col_dir  # remove rounding in the DS strings
    col_dir, row_dir = col_dir / nc, row_dir / np.linalg.norm(row_dir)
    fault = spacing_fault(spacing)
    if fault:
        raise ImageReadError(path, f"DICOM PixelSpacing: {fault}")
    try:
        thickness = float(src["SliceThickness"]) if src["SliceThickness"] not in (None, "") else 0.0
    except (TypeError, ValueError):
        thickness = 0.0
    if not (math.isfinite(thickness) and 0.0 <= thickness <= MAX_THICKNESS_MM):
        raise ImageReadError(path, f"DICOM SliceThickness must be in 0..{MAX_THICKNESS_MM:g} mm, got {thickness:g}")
    if not np.all(np.abs(origin) <= 1e6):
        raise ImageReadError(path, f"DICOM ImagePositionPatient is not a position in a scanner: {origin.tolist()}")
    return origin, col_dir, row_dir, (float(spacing[0]), float(spacing[1])), thickness


def _rescale(path, ds, frame: int | None) -> tuple[float, float]:
    item = _fg_item(ds, frame, "PixelValueTransformationSequence") if frame is not None else None
    src = item if item is not None else ds
    slope = src.get("RescaleSlope", 1.0)
    intercept = src.get("RescaleIntercept", 0.0)
    try:
        slope = float(slope) if slope not in (None, "") else 1.0
        intercept = float(intercept) if intercept not in (None, "") else 0.0
    except (TypeError, ValueError):
        slope, intercept = 1.0, 0.0
    if not (math.isfinite(slope) and math.isfinite(intercept)) or slope == 0:
        raise ImageReadError(path, f"DICOM RescaleSlope/RescaleIntercept must be finite numbers (slope not 0), "
                             f"got {slope:g} / {intercept:g}")
    return slope, intercept


def _no_pixelsshort_reason(ds) -> str:
    """Why a DICOM data set without pixel data is not a slice: truncated image, or a non-image object."""

    meta = getattr(ds, "file_meta", None)
    sop = ds.get("SOPClassUID") or (meta.get("MediaStorageSOPClassUID") if meta is not None else None)
    if not sop:
        return "DICOM file is truncated or damaged: it ends before its SOP class and pixel data"
    name = UID(str(sop)).name
    if "Image" in name or "Rows" in ds:
        return f"DICOM file is truncated: the {name} object ends before its pixel data"
    return f"DICOM file has no pixel data ({name}: not an image object)"


def _guess_transfer_syntax(ds) -> None:
    """A raw data set (no file meta) is decoded with the encoding it was read in."""

    meta = getattr(ds, "file_meta", None)
    if meta is not None and "TransferSyntaxUID" in meta:
        return
    implicit, little = getattr(ds, "original_encoding", (True, True))
    if meta is None:
        ds.file_meta = meta = FileMetaDataset()
    if implicit is None:
        implicit, little = True, True
    meta.TransferSyntaxUID = (
        ImplicitVRLittleEndian if implicit else ExplicitVRLittleEndian if little else ExplicitVRBigEndian
    )


def _decode_with_gdcm(path, ds, frames: int, syntax: str, why: str) -> np.ndarray:
    """The stored pixel values of a single-frame compressed DICOM file that pydicom's own decoders cannot read
    (JPEG lossless, JPEG-LS and JPEG 2000 need plugins it does not carry), decoded by GDCM through SimpleITK,
    which returns them rescaled: the rescale is undone, as :func:`read_dicom_file` applies it."""
    fault = (f"DICOM pixel data compressed as {syntax} cannot be decoded ({why}); the file may be damaged, or "
             f"decompress it first (dcmdjpeg, gdcmconv --raw)")
    if frames != 1:
        raise ImageReadError(path, fault)
    import SimpleITK as sitk  # deferred: loads SimpleITK only when used (one-shot start-up)

    try:
        img = sitk.ReadImage(str(path))
    except RuntimeError:
        raise ImageReadError(path, fault) from None
    arr = sitk.GetArrayFromImage(img)
    if arr.ndim == 3 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.shape[:2] != (int(ds.Rows), int(ds.Columns)):
        raise ImageReadError(path, fault)
    slope, intercept = _rescale(path, ds, None)
    return (arr.astype(float) - intercept) / slope


def read_dicom_file(path, has_preamble: bool) -> list[Slice]:
    """Every slice of one DICOM file (a multi-frame one gives one per frame); ``has_preamble``: the file starts with
    the 128-byte preamble and "DICM" (else a raw data set, read as far as it parses)."""

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = pydicom.dcmread(path, force=not has_preamble)
    except InvalidDicomError:
        raise ImageReadError(path, "not an image: unrecognised file format (expected DICOM, PNG, TIFF or NPY)") from None
    except Exception as exc:  # truncated headers raise EOFError, struct.error, ValueError...
        if not has_preamble:
            raise ImageReadError(path, "not an image: unrecognised file format (expected DICOM, PNG, TIFF or NPY)") from None
        raise ImageReadError(path, f"DICOM file is truncated or damaged ({short_reason(exc)})") from None
    if not has_preamble and "Rows" not in ds and "PixelData" not in ds:
        raise ImageReadError(path, "not an image: unrecognised file format (expected DICOM, PNG, TIFF or NPY)")
    if not any(k in ds for k in ("PixelData", "FloatPixelData", "DoubleFloatPixelData")):
        raise ImageReadError(path, _no_pixelsshort_reason(ds))
    _guess_transfer_syntax(ds)
    try:
        check_size(path, (int(ds.get("NumberOfFrames", 1) or 1), int(ds.get("Rows", 0) or 0),
                           int(ds.get("Columns", 0) or 0), int(ds.get("SamplesPerPixel", 1) or 1)), "DICOM image")
    except (TypeError, ValueError):
        raise ImageReadError(path, "DICOM Rows/Columns/NumberOfFrames are not integers") from None
    frames = int(ds.get("NumberOfFrames", 1) or 1)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            arr = ds.pixel_array
    except Exception as exc:
        syntax = ds.file_meta.TransferSyntaxUID
        if not (syntax.is_transfer_syntax and syntax.is_compressed):
            raise ImageReadError(path, f"DICOM pixel data cannot be decoded; the file may be truncated "
                                       f"({short_reason(exc)})") from None
        arr = _decode_with_gdcm(path, ds, frames, syntax.name, short_reason(exc))
    spp = int(ds.get("SamplesPerPixel", 1) or 1)
    if frames == 1:
        arr = arr[None]
    if spp > 1 and arr.ndim == 4:
        arr = arr[..., :3].astype(float) @ LUMA
    if arr.ndim != 3:
        raise ImageReadError(path, f"DICOM pixel data has unexpected shape {tuple(arr.shape)}")
    per_frame = frames > 1 or "PerFrameFunctionalGroupsSequence" in ds
    if frames > 1 and "PerFrameFunctionalGroupsSequence" not in ds and "SharedFunctionalGroupsSequence" not in ds:
        raise ImageReadError(path, f"DICOM holds {frames} frames without per-frame geometry: cannot place them")
    invert = str(ds.get("PhotometricInterpretation", "MONOCHROME2")).strip() == "MONOCHROME1"
    modality = {"CT": "CT", "MR": "MR"}.get(str(ds.get("Modality", "")).strip().upper(), "auto")
    slices = []
    for k in range(arr.shape[0]):
        frame = k if per_frame else None
        origin, col_dir, row_dir, spacing, thickness = _dicom_geometry(path, ds, frame)
        slope, intercept = _rescale(path, ds, frame)
        with np.errstate(over="ignore", invalid="ignore"):
            pixels = arr[k].astype(float) * slope + intercept
        if not np.all(np.isfinite(pixels)):
            raise ImageReadError(path, "DICOM pixel values are not finite after RescaleSlope/RescaleIntercept")
        if invert:
            pixels = pixels.max() + pixels.min() - pixels
        source = str(path) if arr.shape[0] == 1 else f"{path}#{k + 1}"
        slices.append(Slice(pixels, spacing, origin, col_dir, row_dir, thickness, source, modality=modality))
    return slices


#: A refusal lists at most this many of a folder's series (an export folder may hold dozens).
LISTED_SERIES = 8


def _series_tags(reader, folder: Path, series_id: str) -> tuple[str, str, int]:
    """``(SeriesNumber, SeriesDescription, file count)`` of one DICOM series in ``folder`` (from its first file's
    header; empty strings where it has none)."""
    import SimpleITK as sitk  # deferred: loads SimpleITK only when used (one-shot start-up)

    files = reader.GetGDCMSeriesFileNames(str(folder), series_id)
    first = sitk.ImageFileReader()
    first.SetFileName(files[0])
    try:
        first.ReadImageInformation()
    except RuntimeError:
        return "", "", len(files)
    tag = lambda key: first.GetMetaData(key).strip() if first.HasMetaDataKey(key) else ""  # noqa: E731
    return tag("0020|0011"), tag("0008|103e"), len(files)


def _same_number(number: str, wanted) -> bool:
    """A SeriesNumber read from a header against the one a user gave ("05" is 5)."""
    try:
        return int(str(number).strip()) == int(str(wanted).strip())
    except ValueError:
        return False


def _series_list(tags: dict, ids) -> str:
    """One line naming each series (the first :data:`LISTED_SERIES`): number, description, file count and UID, from
    ``tags`` (:func:`_series_tags` by series UID)."""
    out = []
    for i in list(ids)[:LISTED_SERIES]:
        number, description, n = tags[i]
        name = " ".join(v for v in (f"#{number}" if number else "", f"'{description}'" if description else "") if v)
        out.append(f"{name + ' ' if name else ''}({n} file{'s' if n != 1 else ''}, {i})")
    more = len(ids) - LISTED_SERIES
    return "; ".join(out) + (f"; and {more} more" if more > 0 else "")


def _dicom_thickness_mm(reader, spacing_k_mm: float) -> float | None:
    """SliceThickness (0018,0050) of a series' first file when it differs from the slice spacing (gaps between
    slices, or overlapping slices) and is a plausible thickness; else None (the spacing serves)."""
    try:
        t = float(str(reader.GetMetaData("0018|0050")).strip()) if reader.HasMetaDataKey("0018|0050") else None
    except (ValueError, RuntimeError):
        return None
    if t is None or not (math.isfinite(t) and MIN_SPACING_MM <= t <= MAX_SPACING_MM):
        return None
    return None if abs(t - spacing_k_mm) <= 1e-3 * spacing_k_mm else t


def read_dicom_series(path: Path, series_id: str | None = None):
    """``(SimpleITK image, slice thickness mm or None)`` of the one DICOM series in folder ``path`` (or the one
    ``series_id`` names: a SeriesInstanceUID or a SeriesNumber); the thickness only where SliceThickness differs
    from the slices' spacing. :class:`ImageReadError` for no series, several without ``series_id``, or one slice."""
    import SimpleITK as sitk  # deferred: loads SimpleITK only when a series is read

    reader = sitk.ImageSeriesReader()
    ids = list(reader.GetGDCMSeriesIDs(str(path)))
    if not ids:
        raise ImageReadError(path, "folder holds no DICOM series")
    if series_id is None and len(ids) > 1:
        tags = {i: _series_tags(reader, path, i) for i in ids[:LISTED_SERIES]}
        raise ImageReadError(path, f"folder holds {len(ids)} DICOM series: {_series_list(tags, ids)}; "
                                   f"pick one with --series (its number or UID)")
    if series_id is None:
        series_id = ids[0]
    elif series_id not in ids:
        tags = {i: _series_tags(reader, path, i) for i in ids}  # each series' first header, read once
        by_number = [i for i in ids if _same_number(tags[i][0], series_id)]
        if len(by_number) > 1:
            raise ImageReadError(path, f"SeriesNumber {series_id} names {len(by_number)} DICOM series here; give "
                                       f"the SeriesInstanceUID: {_series_list(tags, by_number)}")
        if not by_number:
            raise ImageReadError(path, f"no DICOM series {series_id!r} (a SeriesNumber or SeriesInstanceUID); "
                                       f"found: {_series_list(tags, ids)}")
        series_id = by_number[0]
    files = reader.GetGDCMSeriesFileNames(str(path), series_id)
    if len(files) < 2:
        raise ImageReadError(path, "DICOM series has a single slice: read it as a slice, not a volume")
    reader.SetFileNames(files)
    try:
        first = sitk.ImageFileReader()
        first.SetFileName(files[0])
        first.ReadImageInformation()
        check_voxels(path, (*first.GetSize()[:2], len(files)), first.GetNumberOfComponents())
        img = reader.Execute()
    except RuntimeError as exc:
        raise ImageReadError(path, f"cannot read DICOM series: {last_line(exc)}") from None
    return img, _dicom_thickness_mm(first, float(img.GetSpacing()[2]))


# --------------------------------------------------------------------------- writing

STORED_MAX = 65535  # 16 bits stored
_COMMENT_LIMIT = 10240  # LT maximum length


def _ds_number(value: float) -> str:
    """A DS (decimal string) of at most 16 characters that round-trips to ~1e-10 relative."""
    v = float(value)
    if v == 0.0 or not math.isfinite(v):
        return "0"
    for digits in range(16, 0, -1):
        text = f"{v:.{digits}g}"
        if len(text) <= 16:
            return text
    return f"{v:.6e}"


def _derived_uid(seed: str, what: str) -> str:
    return generate_uid(entropy_srcs=[seed, what])


def pixel_scaling(pixels: np.ndarray) -> tuple[float, float]:
    """``(slope, intercept)`` that store ``pixels`` (any shape: a slice, or a whole series for one scaling) in 16
    unsigned bits, ``real = stored * slope + intercept``, both as their written DS values; integer pixels whose
    range fits are stored exactly (slope 1)."""
    a = np.asarray(pixels)
    p = a.astype(float, copy=False)
    if not np.all(np.isfinite(p)):
        raise ValueError("slice pixels contain NaN or infinite values")
    lo = min(0.0, float(p.min()))
    hi = float(p.max())
    if np.issubdtype(a.dtype, np.integer) and hi - lo <= STORED_MAX:
        return 1.0, lo  # integers (CT's Hounsfield units, a scanner's stored values) kept exactly
    slope = (hi - lo) / STORED_MAX if hi > lo else 1.0
    # the slope is written as a 16-character DS: use the written value for scaling
    return float(_ds_number(slope)), float(_ds_number(lo))


#: A CT's stored values: HU = stored + CT_INTERCEPT_HU (RescaleSlope 1).
CT_INTERCEPT_HU = -1024.0


def ct_stored(pixels_hu: np.ndarray) -> np.ndarray:
    """A CT slice's stored values (rows, cols): whole HU less :data:`CT_INTERCEPT_HU`, as uint16, or as int16 when
    some lie below the intercept (padding at -2048 or -3024 HU); clipped to the type's range."""
    v = np.rint(np.asarray(pixels_hu, dtype=float) - CT_INTERCEPT_HU)
    if v.min() >= 0:
        return np.clip(v, 0, STORED_MAX).astype(np.uint16)
    return np.clip(v, -32768, 32767).astype(np.int16)


def _mr_image_module(ds: Dataset, spacing_between_slices_mm) -> None:
    """The MR Image module's attributes of a simulated spin-echo slice."""
    ds.ScanningSequence = "SE"
    ds.SequenceVariant = "NONE"
    ds.ScanOptions = ""
    ds.MRAcquisitionType = "2D" if spacing_between_slices_mm is None else "3D"
    ds.RepetitionTime = "3000"
    ds.EchoTime = "90"
    ds.EchoTrainLength = 1
    ds.MagneticFieldStrength = "3"
    ds.ImagedNucleus = "1H"
    ds.FlipAngle = "90"
    ds.NumberOfAverages = "1"


def _stored(pixels: np.ndarray, slope: float, intercept: float) -> np.ndarray:
    """uint16 stored values of ``pixels`` at ``(slope, intercept)``."""
    p = np.asarray(pixels, dtype=float)
    return np.clip(np.rint((p - intercept) / slope), 0, STORED_MAX).astype(np.uint16)


def dicom_dataset(
    sl: Slice,
    truth=None,
    series_uid: str | None = None,
    instance_number: int = 1,
    *,
    study_uid: str | None = None,
    frame_of_reference_uid: str | None = None,
    series_description: str = "CHIC simulated slice",
    scaling: tuple[float, float] | None = None,
    spacing_between_slices_mm: float | None = None,
) -> Dataset:
    """The MR Image Storage dataset of a slice (file meta included), not yet written; CT Image Storage for a CT
    slice (stored as :func:`ct_stored` says; ``scaling`` does not apply).

    ``truth``: an object with ``to_dict()`` (or a dict) stored as JSON in
    ImageComments when it fits. Slices sharing ``series_uid`` also share the
    study and frame of reference UIDs derived from it, unless given.
    ``scaling``: the ``(slope, intercept)`` of :func:`pixel_scaling` (default:
    the slice's own); ``spacing_between_slices_mm``: a slice of a 3-D series.
    """
    now = _dt.datetime.now()
    date, time = now.strftime("%Y%m%d"), now.strftime("%H%M%S")
    series_uid = series_uid or generate_uid()
    study_uid = study_uid or _derived_uid(series_uid, "study")
    for_uid = frame_of_reference_uid or _derived_uid(series_uid, "frame-of-reference")
    sop_uid = generate_uid()
    rows, cols = sl.pixels.shape
    ct = sl.modality == "CT"
    if ct:
        slope, intercept = 1.0, CT_INTERCEPT_HU
        stored = ct_stored(sl.pixels)
    else:
        slope, intercept = scaling or pixel_scaling(sl.pixels)
        stored = _stored(sl.pixels, slope, intercept)
    sop_class = CTImageStorage if ct else MRImageStorage
    col_dir = np.asarray(sl.col_dir, dtype=float)
    row_dir = np.asarray(sl.row_dir, dtype=float)
    origin = np.asarray(sl.origin_mm, dtype=float)

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = sop_class
    meta.MediaStorageSOPInstanceUID = sop_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationVersionName = f"CHIC_{__version__}"[:16]

    ds = Dataset()
    ds.file_meta = meta
    # SOP Common
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.SOPClassUID = sop_class
    ds.SOPInstanceUID = sop_uid
    ds.InstanceCreationDate = date
    ds.InstanceCreationTime = time
    # Patient
    ds.PatientName = "CHIC^Phantom"
    ds.PatientID = "CHIC-PHANTOM"
    ds.PatientBirthDate = ""
    ds.PatientSex = "O"
    # General Study
    ds.StudyInstanceUID = study_uid
    ds.StudyDate = date
    ds.StudyTime = time
    ds.ReferringPhysicianName = ""
    ds.StudyID = "1"
    ds.AccessionNumber = ""
    ds.StudyDescription = "CHIC fiducial registration"
    # General Series
    ds.Modality = "CT" if ct else "MR"
    ds.SeriesInstanceUID = series_uid
    ds.SeriesNumber = 1
    ds.SeriesDescription = series_description
    ds.PatientPosition = "HFS"
    ds.BodyPartExamined = "HEAD"
    # Frame of Reference
    ds.FrameOfReferenceUID = for_uid
    ds.PositionReferenceIndicator = ""
    # General Equipment
    ds.Manufacturer = "CHIC"
    ds.ManufacturerModelName = "chic-register simulate"
    ds.SoftwareVersions = __version__
    # General Image
    ds.InstanceNumber = int(instance_number)
    ds.ContentDate = date
    ds.ContentTime = time
    ds.ImageType = ["DERIVED", "SECONDARY", "AXIAL" if ct else "OTHER"]
    ds.DerivationDescription = "synthetic slice rendered from a CHIC geometry file"
    # Image Plane
    ds.PixelSpacing = [_ds_number(sl.pixel_spacing_mm[0]), _ds_number(sl.pixel_spacing_mm[1])]
    ds.ImageOrientationPatient = [_ds_number(v) for v in (*col_dir, *row_dir)]
    ds.ImagePositionPatient = [_ds_number(v) for v in origin]
    ds.SliceThickness = _ds_number(sl.slice_thickness_mm)
    if spacing_between_slices_mm is not None:
        ds.SpacingBetweenSlices = _ds_number(spacing_between_slices_mm)
    ds.SliceLocation = _ds_number(float(origin @ np.cross(col_dir, row_dir)))
    # Image Pixel
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows = int(rows)
    ds.Columns = int(cols)
    ds.BitsAllocated = 16
    ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 1 if stored.dtype == np.int16 else 0
    ds.PixelData = stored.tobytes()
    ds.RescaleIntercept = _ds_number(intercept)
    ds.RescaleSlope = _ds_number(slope)
    if ct:
        ds.RescaleType = "HU"
        ds.WindowCenter = "400"
        ds.WindowWidth = "2000"
        # CT Image
        ds.KVP = "120"
        ds.AcquisitionNumber = 1
        ds.ConvolutionKernel = "STANDARD"
    else:
        ds.WindowCenter = _ds_number(intercept + 0.5 * slope * float(stored.max()))
        ds.WindowWidth = _ds_number(max(slope * float(stored.max()), slope))
        _mr_image_module(ds, spacing_between_slices_mm)
    if truth is not None:
        data = truth.to_dict() if hasattr(truth, "to_dict") else dict(truth)
        text = "chic-truth " + json.dumps(data, separators=(",", ":"))
        if len(text) <= _COMMENT_LIMIT:
            ds.ImageComments = text
    return ds


def write_dicom(
    sl: Slice,
    path,
    truth=None,
    series_uid: str | None = None,
    instance_number: int = 1,
    **kwargs,
) -> Path:
    """Write ``sl`` as an MR (a CT slice: CT) Image Storage file at ``path`` atomically; returns the path.

    Keyword arguments go to :func:`dicom_dataset` (``study_uid``,
    ``frame_of_reference_uid``, ``series_description``).
    """
    path = Path(path)
    ds = dicom_dataset(sl, truth, series_uid, instance_number, **kwargs)
    with atomic_path(path) as tmp:
        pydicom.dcmwrite(tmp, ds, enforce_file_format=True)
    return path


def write_dicom_series(volume, folder) -> Path:
    """Write a volume (a :class:`~chic_register.io.volumes.Volume`) as one MR Image Storage file per k-slice in
    ``folder`` (``slice_0000.dcm``, ...): one series, one scaling, each file's geometry that of its native slice."""
    folder = Path(folder)
    series_uid = generate_uid()
    scaling = pixel_scaling(volume.voxels)
    description = f"CHIC volume {Path(volume.source).name}"[:64]
    for k in range(volume.shape[0]):
        write_dicom(volume.native_slice(k), folder / f"slice_{k:04d}.dcm", series_uid=series_uid,
                    instance_number=k + 1, series_description=description, scaling=scaling,
                    spacing_between_slices_mm=float(volume.spacing_mm[2]))
    return folder
