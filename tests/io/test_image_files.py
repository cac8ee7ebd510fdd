"""Image readers and the DICOM writer: geometry round trips, dciodvfy, and every bad input."""

import json
import math
import shutil
import subprocess

import numpy as np
import pydicom
import pytest
import tifffile
from PIL import Image
from pydicom.dataset import Dataset
from pydicom.sequence import Sequence

from chic_register.errors import ImageReadError
from chic_register.imaging.simulate import simulate_slice
from chic_register.io.dicom import dicom_dataset, write_dicom
from chic_register.io.images import read_slices, write_plain_image
from chic_register.model.pose import apply
from chic_register.model.slices import Slice


def oblique_orientation():
    """col_dir, row_dir of an oblique image (rotations about two axes)."""
    a, b = math.radians(35), math.radians(-20)
    Rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    Rz = np.array([[math.cos(b), -math.sin(b), 0], [math.sin(b), math.cos(b), 0], [0, 0, 1]])
    R = Rz @ Rx
    return R[:, 0], R[:, 1]


@pytest.fixture(scope="module")
def oblique_sim(neuro_geometry):
    col, row = oblique_orientation()
    return simulate_slice(
        neuro_geometry, 18.0, 35.0, 250.0, 33.0, noise="rician", snr=25, rng=5, distractors=3,
        center_offset_mm=(-6.0, 9.0), image_position=(-70.5, 40.25, 12.0), image_orientation=np.r_[col, row],
    )


@pytest.fixture()
def dicom_file(tmp_path, oblique_sim):
    return write_dicom(oblique_sim.slice, tmp_path / "slice.dcm", truth=oblique_sim.truth)


# --------------------------------------------------------------------------- DICOM round trip


def test_dicom_round_trip_preserves_geometry_and_pixels(dicom_file, oblique_sim, neuro_geometry):
    (sl,) = read_slices([dicom_file])
    ref = oblique_sim.slice
    assert sl.source == str(dicom_file)
    assert sl.shape == ref.shape
    assert np.allclose(sl.origin_mm, ref.origin_mm, atol=1e-9)
    assert np.allclose(sl.col_dir, ref.col_dir, atol=1e-12) and np.allclose(sl.row_dir, ref.row_dir, atol=1e-12)
    assert sl.pixel_spacing_mm == pytest.approx(ref.pixel_spacing_mm)
    assert sl.slice_thickness_mm == pytest.approx(2.0)
    step = ref.pixels.max() / 65535
    assert np.abs(sl.pixels - ref.pixels).max() <= 0.51 * step + 1e-12  # rescale applied
    t = oblique_sim.truth
    for tid, (row, col) in t.centres_px.items():
        crossing_F = neuro_geometry.tube(tid).intersect_plane(t.T_F_from_S[:3, 3], t.T_F_from_S[:3, 2])[0]
        assert np.allclose(sl.pixel_to_scanner(row, col)[0], apply(t.T_scanner_from_fiducial, crossing_F), atol=1e-6)


def test_dicom_carries_the_mr_attributes_and_truth(dicom_file, oblique_sim):
    ds = pydicom.dcmread(dicom_file)
    assert ds.file_meta.MediaStorageSOPClassUID == pydicom.uid.MRImageStorage
    assert ds.SOPClassUID == pydicom.uid.MRImageStorage
    assert ds.Modality == "MR" and ds.PhotometricInterpretation == "MONOCHROME2"
    assert ds.BitsAllocated == 16 and ds.pixel_array.dtype == np.uint16
    for key in ("ScanningSequence", "SequenceVariant", "MRAcquisitionType", "RepetitionTime", "EchoTime",
                "EchoTrainLength", "ImageType", "SliceLocation", "FrameOfReferenceUID", "RescaleSlope"):
        assert key in ds, key
    truth = json.loads(ds.ImageComments.removeprefix("chic-truth "))
    assert np.allclose(truth["T_scanner_from_fiducial"], oblique_sim.truth.T_scanner_from_fiducial)


def test_dicom_series_share_frame_of_reference(tmp_path, oblique_sim):
    a = write_dicom(oblique_sim.slice, tmp_path / "a.dcm", series_uid="1.2.3.4", instance_number=1)
    b = write_dicom(oblique_sim.slice, tmp_path / "b.dcm", series_uid="1.2.3.4", instance_number=2)
    da, db = pydicom.dcmread(a), pydicom.dcmread(b)
    assert da.FrameOfReferenceUID == db.FrameOfReferenceUID and da.StudyInstanceUID == db.StudyInstanceUID
    assert da.SOPInstanceUID != db.SOPInstanceUID and db.InstanceNumber == 2


@pytest.mark.skipif(shutil.which("dciodvfy") is None, reason="dciodvfy (dicom3tools) is not installed")
def test_dicom_passes_dciodvfy(dicom_file):
    run = subprocess.run(["dciodvfy", str(dicom_file)], capture_output=True, text=True, encoding="utf-8", errors="replace", timeout=60)
    report = run.stdout + run.stderr
    assert "MRImage" in report
    errors = [line for line in report.splitlines() if line.startswith("Error")]
    assert not errors, report


def test_dicom_write_is_atomic(tmp_path, oblique_sim):
    target = tmp_path / "keep.dcm"
    target.write_bytes(b"earlier")
    bad = Slice(np.full((4, 4), np.nan), (0.5, 0.5))
    with pytest.raises(ValueError):
        write_dicom(bad, target)
    assert target.read_bytes() == b"earlier"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.dcm"]


def test_raw_dicom_without_preamble_or_file_meta(tmp_path):
    """Some scanners export bare data sets: read them with the encoding they were written in."""
    pixels = np.arange(48.0).reshape(6, 8)
    ds = dicom_dataset(Slice(pixels, (0.5, 0.7), np.array([1.0, 2.0, 3.0])))
    del ds.file_meta
    path = tmp_path / "IM0001"
    pydicom.dcmwrite(path, ds, enforce_file_format=False, implicit_vr=True, little_endian=True)
    assert path.read_bytes()[128:132] != b"DICM"
    (sl,) = read_slices(path)
    assert sl.pixel_spacing_mm == (0.5, 0.7) and np.allclose(sl.origin_mm, (1, 2, 3))
    assert np.allclose(sl.pixels, pixels, atol=0.51 * 47 / 65535)  # 16-bit rescaled


def _enhanced_mr(tmp_path, positions):
    """A minimal enhanced (multi-frame) MR file: geometry in functional groups."""
    sl = Slice(np.arange(2 * 16.0).reshape(2, 16) % 7, (0.5, 0.5))
    ds = dicom_dataset(sl)
    for key in ("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing", "SliceThickness",
                "RescaleSlope", "RescaleIntercept"):
        delattr(ds, key)
    ds.NumberOfFrames = len(positions)
    ds.Rows, ds.Columns = 4, 8
    frames = np.stack([np.full((4, 8), 10 * (k + 1), np.uint16) for k in range(len(positions))])
    ds.PixelData = frames.tobytes()

    def item(**seqs):
        it = Dataset()
        for name, attrs in seqs.items():
            inner = Dataset()
            for k, v in attrs.items():
                setattr(inner, k, v)
            setattr(it, name, Sequence([inner]))
        return it

    ds.SharedFunctionalGroupsSequence = Sequence([item(
        PlaneOrientationSequence={"ImageOrientationPatient": [0, 1, 0, 0, 0, -1]},
        PixelMeasuresSequence={"PixelSpacing": [0.7, 0.9], "SliceThickness": 3},
        PixelValueTransformationSequence={"RescaleSlope": 2, "RescaleIntercept": -5},
    )])
    ds.PerFrameFunctionalGroupsSequence = Sequence(
        [item(PlanePositionSequence={"ImagePositionPatient": list(p)}) for p in positions]
    )
    path = tmp_path / "enhanced.dcm"
    ds.save_as(path, enforce_file_format=True)
    return path


def test_multiframe_dicom_gives_one_slice_per_frame(tmp_path):
    path = _enhanced_mr(tmp_path, [(1, 2, 3), (4, 2, 3), (7, 2, 3)])
    slices = read_slices(path)
    assert [s.source for s in slices] == [f"{path}#{k}" for k in (1, 2, 3)]
    for k, s in enumerate(slices):
        assert s.shape == (4, 8)
        assert np.allclose(s.origin_mm, (1 + 3 * k, 2, 3))
        assert np.allclose(s.col_dir, (0, 1, 0)) and np.allclose(s.row_dir, (0, 0, -1))
        assert s.pixel_spacing_mm == (0.7, 0.9) and s.slice_thickness_mm == 3.0
        assert np.all(s.pixels == 2 * 10 * (k + 1) - 5)


# --------------------------------------------------------------------------- plain images


@pytest.mark.parametrize("suffix", [".npy", ".tif", ".png"])
def test_plain_image_round_trip(tmp_path, oblique_sim, suffix):
    path = tmp_path / f"img{suffix}"
    info = write_plain_image(oblique_sim.slice.pixels, path)
    (sl,) = read_slices([path], pixel_spacing=(0.4, 0.6))
    assert sl.pixel_spacing_mm == (0.4, 0.6)
    assert np.allclose(sl.T_scanner_from_image(), np.eye(4))
    assert np.allclose(sl.pixel_to_scanner(3, 5), [[5 * 0.6, 3 * 0.4, 0.0]])
    ref = oblique_sim.slice.pixels * info["scale"]
    tol = {".npy": 0.0, ".tif": 1e-6 * ref.max(), ".png": 0.5}[suffix]
    assert np.abs(sl.pixels - ref).max() <= tol


def test_rgb_png_becomes_luminance(tmp_path):
    rgb = np.zeros((5, 6, 3), np.uint8)
    rgb[..., 0], rgb[..., 1], rgb[..., 2] = 100, 50, 200
    path = tmp_path / "rgb.png"
    Image.fromarray(rgb).save(path)
    (sl,) = read_slices(path, pixel_spacing=(1, 1))
    assert np.allclose(sl.pixels, 0.299 * 100 + 0.587 * 50 + 0.114 * 200)


# --------------------------------------------------------------------------- bad inputs


def _write(path, data: bytes):
    path.write_bytes(data)
    return path


def _bad_cases(tmp_path, dicom_bytes):
    """(path, pixel_spacing, expected message fragment) for every way reading must fail."""
    cases = []
    cases.append((tmp_path / "missing.dcm", None, "no such file"))
    (tmp_path / "folder").mkdir()
    cases.append((tmp_path / "folder", None, "directory"))
    cases.append((_write(tmp_path / "notes.txt", b"a text file\n" * 30), (0.5, 0.5), "not an image"))
    cases.append((_write(tmp_path / "notes.dcm", b"a text file\n" * 30), None, "not an image"))
    cases.append((_write(tmp_path / "notes.png", b"a text file\n" * 30), (0.5, 0.5), "not an image"))
    cases.append((_write(tmp_path / "empty.dcm", b""), None, "empty"))
    for n in (200, 1500, len(dicom_bytes) // 2, len(dicom_bytes) - 1):
        cases.append((_write(tmp_path / f"cut{n}.dcm", dicom_bytes[:n]), None, "truncated"))
    # DICOM without pixel data, without geometry, with a broken orientation
    ds = pydicom.dcmread(tmp_path / "slice.dcm")
    del ds.PixelData
    ds.save_as(tmp_path / "nopixels.dcm")
    cases.append((tmp_path / "nopixels.dcm", None, "truncated"))
    ds = pydicom.dcmread(tmp_path / "slice.dcm")
    ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID = pydicom.uid.BasicTextSRStorage
    for key in ("PixelData", "Rows", "Columns"):
        delattr(ds, key)
    ds.save_as(tmp_path / "report.dcm")
    cases.append((tmp_path / "report.dcm", None, "no pixel data"))
    for key in ("ImagePositionPatient", "ImageOrientationPatient", "PixelSpacing"):
        ds = pydicom.dcmread(tmp_path / "slice.dcm")
        delattr(ds, key)
        ds.save_as(tmp_path / f"no-{key}.dcm")
        cases.append((tmp_path / f"no-{key}.dcm", None, key))
    ds = pydicom.dcmread(tmp_path / "slice.dcm")
    ds.ImageOrientationPatient = [1, 0, 0, 1, 0, 0]
    ds.save_as(tmp_path / "parallel.dcm")
    cases.append((tmp_path / "parallel.dcm", None, "orthonormal"))
    # plain arrays
    np.save(tmp_path / "vol.npy", np.zeros((3, 8, 8)))
    cases.append((tmp_path / "vol.npy", (0.5, 0.5), "2-D"))
    np.save(tmp_path / "ok.npy", np.zeros((8, 8)))
    cases.append((tmp_path / "ok.npy", None, "pixel-spacing"))
    cases.append((tmp_path / "ok.npy", (0.0, 0.5), "positive"))
    cases.append((tmp_path / "ok.npy", (0.5, -1.0), "positive"))
    nan = np.zeros((8, 8))
    nan[2, 2] = np.nan
    np.save(tmp_path / "nan.npy", nan)
    cases.append((tmp_path / "nan.npy", (0.5, 0.5), "NaN"))
    np.save(tmp_path / "objects.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    cases.append((tmp_path / "objects.npy", (0.5, 0.5), "objects"))
    cases.append((_write(tmp_path / "cut.npy", (tmp_path / "ok.npy").read_bytes()[:150]), (0.5, 0.5), "truncated"))
    tifffile.imwrite(tmp_path / "stack.tif", np.zeros((4, 8, 8), np.uint16), photometric="minisblack")
    cases.append((tmp_path / "stack.tif", (0.5, 0.5), "2-D"))
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(tmp_path / "ok.png")
    cases.append((tmp_path / "ok.png", None, "pixel-spacing"))
    png = (tmp_path / "ok.png").read_bytes()
    cases.append((_write(tmp_path / "cut.png", png[: len(png) // 2]), (0.5, 0.5), "cannot be decoded"))
    return cases


def test_every_bad_input_is_one_line_image_read_error(tmp_path, dicom_file):
    cases = _bad_cases(tmp_path, dicom_file.read_bytes())
    for path, spacing, fragment in cases:
        with pytest.raises(ImageReadError) as info:
            read_slices([path], pixel_spacing=spacing)
        message = str(info.value)
        assert message.startswith(str(path)), message
        assert fragment in message, (path, message)
        assert "\n" not in message and len(message) < 300
        assert info.value.exit_code == 2


def test_read_slices_stops_at_the_first_bad_file(tmp_path, dicom_file):
    with pytest.raises(ImageReadError, match="missing.dcm"):
        read_slices([dicom_file, tmp_path / "missing.dcm"])
    assert len(read_slices([dicom_file, dicom_file])) == 2


@pytest.mark.parametrize("syntax", ["RLELossless", "JPEG2000Lossless", "JPEGLSLossless"])
def test_compressed_dicom_reads_as_the_uncompressed_file(dicom_file, tmp_path, syntax):
    """Scanners and PACS export compressed DICOM: it reads pixel for pixel as the uncompressed file."""
    ds = pydicom.dcmread(dicom_file)
    ds.compress(getattr(pydicom.uid, syntax))
    ds.save_as(tmp_path / "c.dcm")
    assert pydicom.dcmread(tmp_path / "c.dcm").file_meta.TransferSyntaxUID.is_compressed
    (plain,), (packed,) = read_slices([dicom_file]), read_slices([tmp_path / "c.dcm"])
    np.testing.assert_array_equal(packed.pixels, plain.pixels)
    assert packed.pixel_spacing_mm == plain.pixel_spacing_mm


def test_compressed_dicom_without_a_pydicom_decoder_is_decoded_by_gdcm(dicom_file, tmp_path, monkeypatch):
    """JPEG lossless and the other syntaxes pydicom has no decoder for without GPL plugins: SimpleITK's GDCM decodes
    them (it rescales; the reader undoes that and applies the file's rescale as for every DICOM)."""
    ds = pydicom.dcmread(dicom_file)
    ds.compress(pydicom.uid.JPEG2000Lossless)
    ds.save_as(tmp_path / "c.dcm")
    plain = read_slices([dicom_file])[0].pixels

    def no_decoder(self):
        raise RuntimeError("no decoder plugin")

    monkeypatch.setattr(pydicom.dataset.Dataset, "pixel_array", property(no_decoder))
    np.testing.assert_allclose(read_slices([tmp_path / "c.dcm"])[0].pixels, plain, rtol=1e-12, atol=1e-9)


def test_a_private_transfer_syntax_is_a_one_line_error(dicom_file, tmp_path):
    ds = pydicom.dcmread(dicom_file)
    ds.file_meta.TransferSyntaxUID = "1.2.3.4.5"
    ds.save_as(tmp_path / "p.dcm")
    with pytest.raises(ImageReadError, match="cannot be decoded"):
        read_slices([tmp_path / "p.dcm"])


def test_damaged_compressed_dicom_names_its_compression(dicom_file, tmp_path):
    ds = pydicom.dcmread(dicom_file)
    ds.compress(pydicom.uid.JPEG2000Lossless)
    ds.PixelData = ds.PixelData[:40] + b"\x00" * 64  # the codestream cut short
    ds.save_as(tmp_path / "bad.dcm")
    with pytest.raises(ImageReadError, match="compressed as JPEG 2000 .* cannot be decoded"):
        read_slices([tmp_path / "bad.dcm"])


@pytest.mark.skipif(shutil.which("dcmcjpeg") is None, reason="dcmcjpeg (dcmtk) is not installed")
def test_jpeg_lossless_dicom_from_dcmtk_reads_as_the_uncompressed_file(dicom_file, tmp_path):
    """JPEG Lossless, first-order prediction (the syntax most PACS exports use), written by dcmtk's encoder (pydicom
    has no decoder for it without a GPL plugin: GDCM reads it)."""
    out = tmp_path / "jpeg.dcm"
    subprocess.run(["dcmcjpeg", "+e1", str(dicom_file), str(out)], check=True, capture_output=True, timeout=60)
    assert pydicom.dcmread(out).file_meta.TransferSyntaxUID == pydicom.uid.JPEGLosslessSV1
    np.testing.assert_array_equal(read_slices([out])[0].pixels, read_slices([dicom_file])[0].pixels)
