"""Read image files into :class:`~chic_register.model.slices.Slice` objects (docs/interfaces.md section 3).

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

from pathlib import Path

import numpy as np

from chic_register.errors import ImageReadError, InputFileError
from chic_register.io.limits import LUMA, check_size, check_spacing, short_reason
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

_DICOM_SUFFIXES = {".dcm", ".dicom", ".ima", ""}


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
        a = a[..., :3].astype(float) @ LUMA
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
    spacing = check_spacing(path, pixel_spacing, kind)
    return Slice(pixels, spacing, np.zeros(3), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), 0.0, str(path))


# --------------------------------------------------------------------------- plain arrays


def _read_npy(path) -> np.ndarray:
    try:
        with open(path, "rb") as fh:
            fmt = np.lib.format
            major = fmt.read_magic(fh)[0]
            shape = (fmt.read_array_header_1_0(fh) if major == 1 else fmt.read_array_header_2_0(fh))[0]
        check_size(path, shape, "NPY array")
    except ImageReadError:
        raise
    except Exception as exc:
        raise ImageReadError(path, f"NPY file is damaged or truncated ({short_reason(exc)})") from None
    try:
        arr = np.load(path, allow_pickle=False)
    except ValueError as exc:
        if "pickle" in str(exc).lower():
            raise ImageReadError(path, "NPY file holds Python objects, not a numeric array") from None
        raise ImageReadError(path, f"NPY file is damaged or truncated ({short_reason(exc)})") from None
    except (OSError, EOFError) as exc:
        raise ImageReadError(path, f"NPY file is damaged or truncated ({short_reason(exc)})") from None
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
            check_size(path, page.shape, "TIFF image")
            rgb = page.photometric in (tifffile.PHOTOMETRIC.RGB, tifffile.PHOTOMETRIC.YCBCR)
            arr = page.asarray()
    except ImageReadError:
        raise
    except Exception as exc:  # tifffile raises many kinds on damaged files
        raise ImageReadError(path, f"TIFF cannot be decoded ({short_reason(exc)})") from None
    return _as_2d(path, arr, "TIFF image", rgb_ok=rgb)


def _read_pillow(path, kind: str, known: bool = False) -> np.ndarray:
    """Any 2-D image Pillow reads; ``known``: the file has that format's magic bytes."""
    from PIL import Image, UnidentifiedImageError  # deferred: loads PIL only when used (one-shot start-up)

    try:
        with Image.open(path) as img:
            if getattr(img, "n_frames", 1) > 1:
                raise ImageReadError(path, f"{kind} holds {img.n_frames} frames: a slice must be one 2-D image")
            check_size(path, img.size, kind)
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
        raise ImageReadError(path, f"{kind} cannot be decoded ({short_reason(exc)})") from None
    return _as_2d(path, arr, kind, rgb_ok=True)


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
        raise ImageReadError(p, f"cannot be read ({exc.strerror or short_reason(exc)})") from None
    if not head:
        raise ImageReadError(p, "empty file, not an image")
    kind = _sniff(head)
    if kind == "dicom" or (kind is None and p.suffix.lower() in _DICOM_SUFFIXES):
        from chic_register.io.dicom import read_dicom_file  # deferred: loads pydicom only for a DICOM file

    if kind == "dicom":
        return read_dicom_file(p, has_preamble=True)
    if kind == "npy":
        return [_plain_slice(p, _read_npy(p), pixel_spacing, "NPY")]
    if kind == "tiff":
        return [_plain_slice(p, _read_tiff(p), pixel_spacing, "TIFF")]
    if kind == "png":
        return [_plain_slice(p, _read_pillow(p, "PNG image", known=True), pixel_spacing, "PNG")]
    if p.suffix.lower() in _DICOM_SUFFIXES:
        # DICOM without the 128-byte preamble (raw data set), as some scanners export
        return read_dicom_file(p, has_preamble=False)
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
