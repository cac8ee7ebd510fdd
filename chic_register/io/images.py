"""Read image files into :class:`~chic_register.model.slices.Slice` objects (CONTRACT.md section 3).

- DICOM (pydicom): the scanner frame is LPS, from ImagePositionPatient (centre
  of the first pixel), ImageOrientationPatient (col_dir, then row_dir) and
  PixelSpacing (row spacing, col spacing); RescaleSlope / RescaleIntercept are
  applied. Enhanced (multi-frame) images give one slice per frame, placed by
  their functional groups.
- PNG / TIFF / other Pillow images and NPY arrays: no geometry of their own;
  ``pixel_spacing=(row, col)`` mm is required and the "scanner" frame is the
  image frame (origin at the centre of pixel (0, 0), x along columns, y
  along rows). Colour images become luminance (ITU-R 601 weights).

Every failure raises :class:`~chic_register.errors.ImageReadError` naming the
file and the fault in one line.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from chic_register.errors import ImageReadError, InputFileError
from chic_register.model.slices import Slice
from chic_register.util.atomic import atomic_path
from chic_register.util.safeload import open_regular_file

#: Volume files (read by :mod:`chic_register.io.volumes`, SimpleITK); a folder is read as a DICOM series.
VOLUME_SUFFIXES = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".mha", ".mhd")


def file_suffix(path: Path) -> str:
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


def is_volume_path(path) -> bool:
    """True for a NIfTI/NRRD/MetaImage file or a folder (read as a DICOM series): a volume, not a 2-D image.

    Decided here, by name, so that a one-shot solve of a 2-D file never imports the volume code."""
    path = Path(path)
    return path.is_dir() or file_suffix(path) in VOLUME_SUFFIXES

#: Physical range of a pixel spacing (mm): 10 um (microscopy-grade MRI) to 50 mm.
MIN_SPACING_MM = 0.01
MAX_SPACING_MM = 50.0
#: Largest slice read (pixels over all frames): 4096 x 4096 (128 MiB as float64; solving one took 0.5 GiB).
MAX_PIXELS = 4096 * 4096
#: Largest slice thickness taken from a file (mm); beyond it the value is refused.
MAX_THICKNESS_MM = 100.0

_LUMA = np.array([0.299, 0.587, 0.114])
_DICOM_SUFFIXES = {".dcm", ".dicom", ".ima", ""}


def _reason(exc: BaseException) -> str:
    text = str(exc).strip()
    first = text.splitlines()[0] if text else type(exc).__name__
    first = first.split(" - ")[0]
    return first if len(first) <= 120 else first[:117] + "..."


def spacing_fault(pixel_spacing) -> str | None:
    """Why ``pixel_spacing`` (row, col) mm is not a physical pixel spacing, or None when it is."""
    try:
        rs, cs = (float(v) for v in pixel_spacing)
    except (TypeError, ValueError):
        return f"pixel spacing must be two numbers (row, col), got {pixel_spacing!r}"
    if not all(math.isfinite(v) and MIN_SPACING_MM <= v <= MAX_SPACING_MM for v in (rs, cs)):
        return (f"pixel spacing must be two positive numbers in {MIN_SPACING_MM:g}..{MAX_SPACING_MM:g} mm, "
                f"got ({rs:g}, {cs:g})")
    return None


def _check_spacing(path, pixel_spacing, kind: str) -> tuple[float, float]:
    if pixel_spacing is None:
        raise ImageReadError(
            path, f"a {kind} image has no geometry: give the pixel spacing (--pixel-spacing ROW COL, mm)"
        )
    fault = spacing_fault(pixel_spacing)
    if fault:
        raise ImageReadError(path, fault)
    rs, cs = (float(v) for v in pixel_spacing)
    return rs, cs


def _check_size(path, shape, kind: str) -> None:
    """Refuse an image too large to be a slice before its pixels are decoded (memory bound)."""
    n = 1
    for v in shape:
        n *= max(int(v), 0)
    if n > MAX_PIXELS:
        raise ImageReadError(path, f"{kind} of shape {tuple(int(v) for v in shape)} is too large for a slice "
                                   f"(at most {MAX_PIXELS} pixels)")


def _as_2d(path, arr: np.ndarray, kind: str, rgb_ok: bool) -> np.ndarray:
    """A real 2-D float image from an array read from ``path``; colour to luminance."""
    a = np.asarray(arr)
    if a.dtype.kind == "c":
        a = np.abs(a)
    if a.dtype.kind not in "biuf":
        raise ImageReadError(path, f"{kind} holds {a.dtype} values, not numbers")
    while a.ndim > 2 and a.shape[0] == 1:
        a = a[0]
    if rgb_ok and a.ndim == 3 and a.shape[-1] in (3, 4):
        a = a[..., :3].astype(float) @ _LUMA
    if a.ndim != 2:
        raise ImageReadError(
            path, f"{kind} has shape {tuple(a.shape)}: a slice must be one 2-D image (rows, cols)"
        )
    if a.size == 0:
        raise ImageReadError(path, f"{kind} is empty (shape {tuple(a.shape)})")
    a = a.astype(float)
    if not np.all(np.isfinite(a)):
        raise ImageReadError(path, f"{kind} contains NaN or infinite pixel values")
    return a


def _plain_slice(path, pixels: np.ndarray, pixel_spacing, kind: str) -> Slice:
    spacing = _check_spacing(path, pixel_spacing, kind)
    return Slice(pixels, spacing, np.zeros(3), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), 0.0, str(path))


# --------------------------------------------------------------------------- plain arrays


def _read_npy(path) -> np.ndarray:
    try:
        with open(path, "rb") as fh:
            fmt = np.lib.format
            major = fmt.read_magic(fh)[0]
            shape = (fmt.read_array_header_1_0(fh) if major == 1 else fmt.read_array_header_2_0(fh))[0]
        _check_size(path, shape, "NPY array")
    except ImageReadError:
        raise
    except Exception as exc:
        raise ImageReadError(path, f"NPY file is damaged or truncated ({_reason(exc)})") from None
    try:
        arr = np.load(path, allow_pickle=False)
    except ValueError as exc:
        if "pickle" in str(exc).lower():
            raise ImageReadError(path, "NPY file holds Python objects, not a numeric array") from None
        raise ImageReadError(path, f"NPY file is damaged or truncated ({_reason(exc)})") from None
    except (OSError, EOFError) as exc:
        raise ImageReadError(path, f"NPY file is damaged or truncated ({_reason(exc)})") from None
    if not isinstance(arr, np.ndarray):
        raise ImageReadError(path, "NPY file does not hold a single array")
    return _as_2d(path, arr, "NPY array", rgb_ok=False)


def _read_tiff(path) -> np.ndarray:
    import tifffile  # deferred: loads tifffile only when used (one-shot start-up)

    try:
        with tifffile.TiffFile(path) as tif:
            if len(tif.pages) > 1:
                raise ImageReadError(path, f"TIFF holds {len(tif.pages)} pages: a slice must be one 2-D image")
            page = tif.pages[0]
            _check_size(path, page.shape, "TIFF image")
            rgb = page.photometric in (tifffile.PHOTOMETRIC.RGB, tifffile.PHOTOMETRIC.YCBCR)
            arr = page.asarray()
    except ImageReadError:
        raise
    except Exception as exc:  # tifffile raises many kinds on damaged files
        raise ImageReadError(path, f"TIFF cannot be decoded ({_reason(exc)})") from None
    return _as_2d(path, arr, "TIFF image", rgb_ok=rgb)


def _read_pillow(path, kind: str, known: bool = False) -> np.ndarray:
    """Any 2-D image Pillow reads; ``known``: the file has that format's magic bytes."""
    from PIL import Image, UnidentifiedImageError  # deferred: loads PIL only when used (one-shot start-up)

    try:
        with Image.open(path) as img:
            if getattr(img, "n_frames", 1) > 1:
                raise ImageReadError(path, f"{kind} holds {img.n_frames} frames: a slice must be one 2-D image")
            _check_size(path, img.size, kind)
            img.load()
            mode = img.mode
            if mode in ("P", "PA", "CMYK", "YCbCr", "HSV", "LAB"):
                img = img.convert("RGB")
            elif mode == "LA":
                img = img.getchannel("L")
            arr = np.array(img)
    except ImageReadError:
        raise
    except UnidentifiedImageError:
        if known:
            raise ImageReadError(path, f"{kind} cannot be decoded: truncated or damaged") from None
        raise ImageReadError(path, "not an image: unrecognised file format (expected DICOM, PNG, TIFF or NPY)") from None
    except Exception as exc:  # truncated or damaged image data
        raise ImageReadError(path, f"{kind} cannot be decoded ({_reason(exc)})") from None
    return _as_2d(path, arr, kind, rgb_ok=True)


# --------------------------------------------------------------------------- DICOM


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


def _no_pixels_reason(ds) -> str:
    """Why a DICOM data set without pixel data is not a slice: truncated image, or a non-image object."""
    from pydicom.uid import UID  # deferred: loads pydicom only when used (one-shot start-up)

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
    from pydicom.dataset import FileMetaDataset  # deferred: loads pydicom only when used (one-shot start-up)
    from pydicom.uid import (
        ExplicitVRBigEndian,
        ExplicitVRLittleEndian,
        ImplicitVRLittleEndian,
    )  # deferred: loads pydicom only when used (one-shot start-up)

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
    which returns them rescaled: the rescale is undone, as :func:`_read_dicom` applies it."""
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


def _read_dicom(path, has_preamble: bool) -> list[Slice]:
    import pydicom  # deferred: loads pydicom only when used (one-shot start-up)
    from pydicom.errors import InvalidDicomError  # deferred: loads pydicom only when used (one-shot start-up)

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ds = pydicom.dcmread(path, force=not has_preamble)
    except InvalidDicomError:
        raise ImageReadError(path, "not an image: unrecognised file format (expected DICOM, PNG, TIFF or NPY)") from None
    except Exception as exc:  # truncated headers raise EOFError, struct.error, ValueError...
        if not has_preamble:
            raise ImageReadError(path, "not an image: unrecognised file format (expected DICOM, PNG, TIFF or NPY)") from None
        raise ImageReadError(path, f"DICOM file is truncated or damaged ({_reason(exc)})") from None
    if not has_preamble and "Rows" not in ds and "PixelData" not in ds:
        raise ImageReadError(path, "not an image: unrecognised file format (expected DICOM, PNG, TIFF or NPY)")
    if not any(k in ds for k in ("PixelData", "FloatPixelData", "DoubleFloatPixelData")):
        raise ImageReadError(path, _no_pixels_reason(ds))
    _guess_transfer_syntax(ds)
    try:
        _check_size(path, (int(ds.get("NumberOfFrames", 1) or 1), int(ds.get("Rows", 0) or 0),
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
                                       f"({_reason(exc)})") from None
        arr = _decode_with_gdcm(path, ds, frames, syntax.name, _reason(exc))
    spp = int(ds.get("SamplesPerPixel", 1) or 1)
    if frames == 1:
        arr = arr[None]
    if spp > 1 and arr.ndim == 4:
        arr = arr[..., :3].astype(float) @ _LUMA
    if arr.ndim != 3:
        raise ImageReadError(path, f"DICOM pixel data has unexpected shape {tuple(arr.shape)}")
    per_frame = frames > 1 or "PerFrameFunctionalGroupsSequence" in ds
    if frames > 1 and "PerFrameFunctionalGroupsSequence" not in ds and "SharedFunctionalGroupsSequence" not in ds:
        raise ImageReadError(path, f"DICOM holds {frames} frames without per-frame geometry: cannot place them")
    invert = str(ds.get("PhotometricInterpretation", "MONOCHROME2")).strip() == "MONOCHROME1"
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
        slices.append(Slice(pixels, spacing, origin, col_dir, row_dir, thickness, source))
    return slices


# --------------------------------------------------------------------------- dispatch


def _sniff(head: bytes) -> str | None:
    if len(head) >= 132 and head[128:132] == b"DICM":
        return "dicom"
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "png"
    if head[:4] in (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+"):
        return "tiff"
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    return None


def read_slice(path, pixel_spacing=None) -> list[Slice]:
    """Every slice in one file (a multi-frame DICOM gives several); raises :class:`ImageReadError`."""
    p = Path(path)
    try:
        with open_regular_file(p, "image file") as fh:  # a FIFO or device is refused, not waited on
            head = fh.read(132)
    except InputFileError as exc:
        raise ImageReadError(p, exc.detail) from None
    except OSError as exc:
        raise ImageReadError(p, f"cannot be read ({exc.strerror or _reason(exc)})") from None
    if not head:
        raise ImageReadError(p, "empty file, not an image")
    kind = _sniff(head)
    if kind == "dicom":
        return _read_dicom(p, has_preamble=True)
    if kind == "npy":
        return [_plain_slice(p, _read_npy(p), pixel_spacing, "NPY")]
    if kind == "tiff":
        return [_plain_slice(p, _read_tiff(p), pixel_spacing, "TIFF")]
    if kind == "png":
        return [_plain_slice(p, _read_pillow(p, "PNG image", known=True), pixel_spacing, "PNG")]
    if p.suffix.lower() in _DICOM_SUFFIXES:
        # DICOM without the 128-byte preamble (raw data set), as some scanners export
        return _read_dicom(p, has_preamble=False)
    return [_plain_slice(p, _read_pillow(p, "image"), pixel_spacing, p.suffix.lstrip(".").upper() or "plain")]


def read_slices(paths, pixel_spacing=None) -> list[Slice]:
    """Read image files into slices, in order; ``pixel_spacing=(row, col)`` mm for plain images.

    ``paths``: one path or a sequence of paths. DICOM files carry their own
    geometry (``pixel_spacing`` is then ignored). Raises
    :class:`~chic_register.errors.ImageReadError` (one line: file and fault)
    on the first file that cannot be read as a 2-D slice.
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    out: list[Slice] = []
    for path in paths:
        out.extend(read_slice(path, pixel_spacing))
    if not out:
        raise ImageReadError("<none>", "no image files given")
    return out


# --------------------------------------------------------------------------- plain writers

PLAIN_SUFFIXES = (".npy", ".png", ".tif", ".tiff")


def write_plain_image(pixels: np.ndarray, path) -> dict:
    """Write a 2-D image as NPY (float64), TIFF (float32) or PNG (16-bit, scaled to its maximum), atomically.

    Returns ``{"format": ..., "scale": s}``: file value = pixel value * s
    (1 except for PNG). Raises ``ValueError`` for another suffix.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix not in PLAIN_SUFFIXES:
        raise ValueError(f"{p}: unsupported image suffix {p.suffix!r}; allowed: {', '.join(PLAIN_SUFFIXES)}")
    a = np.asarray(pixels, dtype=float)
    if a.ndim != 2:
        raise ValueError(f"image must be 2-D, got shape {a.shape}")
    scale = 1.0
    with atomic_path(p, suffix=suffix) as tmp:
        if suffix == ".npy":
            with open(tmp, "wb") as fh:
                np.save(fh, a)
        elif suffix == ".png":
            from PIL import Image  # deferred: loads PIL only when used (one-shot start-up)

            peak = float(a.max())
            scale = 65535.0 / peak if peak > 0 else 1.0
            stored = np.clip(np.rint(a * scale), 0, 65535).astype(np.uint16)
            Image.fromarray(stored).save(tmp, format="PNG")
        else:
            import tifffile  # deferred: loads tifffile only when used (one-shot start-up)

            tifffile.imwrite(tmp, a.astype(np.float32))
    return {"format": suffix.lstrip("."), "scale": scale}
