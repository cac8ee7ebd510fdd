"""Write a :class:`~chic_register.model.slices.Slice` as a DICOM MR Image Storage file.

The file carries the slice's place in the scanner (LPS) the DICOM way
(CONTRACT.md section 3): ImagePositionPatient = centre of pixel (0, 0),
ImageOrientationPatient = (col_dir, row_dir), PixelSpacing = (row spacing,
col spacing). Pixels are stored as unsigned 16-bit integers; the real values
come back through RescaleSlope / RescaleIntercept. It holds the modules of
the MR Image IOD with their type 1 and type 2 attributes and passes
``dciodvfy`` (dicom3tools) without errors.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, MRImageStorage, generate_uid

from chic_register.model.slices import Slice
from chic_register.util.atomic import atomic_path
from chic_register.version import __version__

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


def _pixel_scaling(pixels: np.ndarray) -> tuple[np.ndarray, float, float]:
    """uint16 stored values and (slope, intercept) with ``real = stored * slope + intercept``."""
    p = np.asarray(pixels, dtype=float)
    if not np.all(np.isfinite(p)):
        raise ValueError("slice pixels contain NaN or infinite values")
    lo = min(0.0, float(p.min()))
    hi = float(p.max())
    slope = (hi - lo) / STORED_MAX if hi > lo else 1.0
    # the slope is written as a 16-character DS: use the written value for scaling
    slope = float(_ds_number(slope))
    lo = float(_ds_number(lo))
    stored = np.clip(np.rint((p - lo) / slope), 0, STORED_MAX).astype(np.uint16)
    return stored, slope, lo


def dicom_dataset(
    sl: Slice,
    truth=None,
    series_uid: str | None = None,
    instance_number: int = 1,
    *,
    study_uid: str | None = None,
    frame_of_reference_uid: str | None = None,
    series_description: str = "CHIC simulated slice",
) -> Dataset:
    """The MR Image Storage dataset of a slice (file meta included), not yet written.

    ``truth``: an object with ``to_dict()`` (or a dict) stored as JSON in
    ImageComments when it fits. Slices sharing ``series_uid`` also share the
    study and frame of reference UIDs derived from it, unless given.
    """
    now = _dt.datetime.now()
    date, time = now.strftime("%Y%m%d"), now.strftime("%H%M%S")
    series_uid = series_uid or generate_uid()
    study_uid = study_uid or _derived_uid(series_uid, "study")
    for_uid = frame_of_reference_uid or _derived_uid(series_uid, "frame-of-reference")
    sop_uid = generate_uid()
    rows, cols = sl.pixels.shape
    stored, slope, intercept = _pixel_scaling(sl.pixels)
    col_dir = np.asarray(sl.col_dir, dtype=float)
    row_dir = np.asarray(sl.row_dir, dtype=float)
    origin = np.asarray(sl.origin_mm, dtype=float)

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = MRImageStorage
    meta.MediaStorageSOPInstanceUID = sop_uid
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationVersionName = f"CHIC_{__version__}"[:16]

    ds = Dataset()
    ds.file_meta = meta
    # SOP Common
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.SOPClassUID = MRImageStorage
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
    ds.Modality = "MR"
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
    ds.ImageType = ["DERIVED", "SECONDARY", "OTHER"]
    ds.DerivationDescription = "synthetic slice rendered from a CHIC geometry file"
    # Image Plane
    ds.PixelSpacing = [_ds_number(sl.pixel_spacing_mm[0]), _ds_number(sl.pixel_spacing_mm[1])]
    ds.ImageOrientationPatient = [_ds_number(v) for v in (*col_dir, *row_dir)]
    ds.ImagePositionPatient = [_ds_number(v) for v in origin]
    ds.SliceThickness = _ds_number(sl.slice_thickness_mm)
    ds.SliceLocation = _ds_number(float(origin @ np.cross(col_dir, row_dir)))
    # Image Pixel
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows = int(rows)
    ds.Columns = int(cols)
    ds.BitsAllocated = 16
    ds.BitsStored = 16
    ds.HighBit = 15
    ds.PixelRepresentation = 0
    ds.PixelData = stored.tobytes()
    ds.RescaleIntercept = _ds_number(intercept)
    ds.RescaleSlope = _ds_number(slope)
    ds.WindowCenter = _ds_number(intercept + 0.5 * slope * float(stored.max()))
    ds.WindowWidth = _ds_number(max(slope * float(stored.max()), slope))
    # MR Image
    ds.ScanningSequence = "SE"
    ds.SequenceVariant = "NONE"
    ds.ScanOptions = ""
    ds.MRAcquisitionType = "2D"
    ds.RepetitionTime = "3000"
    ds.EchoTime = "90"
    ds.EchoTrainLength = 1
    ds.MagneticFieldStrength = "3"
    ds.ImagedNucleus = "1H"
    ds.FlipAngle = "90"
    ds.NumberOfAverages = "1"
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
    """Write ``sl`` as an MR Image Storage file at ``path`` atomically; returns the path.

    Keyword arguments go to :func:`dicom_dataset` (``study_uid``,
    ``frame_of_reference_uid``, ``series_description``).
    """
    path = Path(path)
    ds = dicom_dataset(sl, truth, series_uid, instance_number, **kwargs)
    with atomic_path(path) as tmp:
        pydicom.dcmwrite(tmp, ds, enforce_file_format=True)
    return path
