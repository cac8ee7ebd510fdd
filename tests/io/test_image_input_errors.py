"""Hostile image inputs (DICOM values out of range, tiny spacings, FIFOs, a huge array header) are a one-line error
and exit 2, never a traceback or a hang; a blank valid image is still a no lock.
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from chic_register.cli.main import main as register_main
from chic_register.errors import NoLock
from tests.helpers import edited_dicom, one_line_error


@pytest.mark.parametrize("attrs, fragment", [
    ({"PixelSpacing": ["1e-300", "1e-300"]}, "PixelSpacing: pixel spacing must be two positive numbers in 0.01..50 mm"),
    ({"PixelSpacing": ["0.5", "1e300"]}, "PixelSpacing: pixel spacing must be two positive numbers"),
    ({"RescaleSlope": "nan"}, "RescaleSlope/RescaleIntercept must be finite"),
    ({"RescaleSlope": "inf"}, "RescaleSlope/RescaleIntercept must be finite"),
    ({"RescaleIntercept": "-inf"}, "RescaleSlope/RescaleIntercept must be finite"),
    ({"RescaleSlope": "1e308"}, "not finite after RescaleSlope"),
    ({"SliceThickness": "inf"}, "SliceThickness must be in 0..100 mm"),
])
def test_bad_dicom_values_exit_2_with_one_line(tmp_path, capsys, dicom_slice, neuro_geometry_file, attrs, fragment):
    path = edited_dicom(dicom_slice[0], tmp_path / "bad.dcm", **attrs)
    assert register_main(["solve", str(path), "--geometry", str(neuro_geometry_file), "--json"]) == 2
    assert fragment in one_line_error(capsys, f"chic-register: error: {path}: ")


def test_tiny_pixel_spacing_flag_and_fifo_image_exit_2(tmp_path, capsys, neuro_geometry_file):
    npy = tmp_path / "s.npy"
    np.save(npy, np.zeros((64, 64)))
    assert register_main(["solve", str(npy), "--geometry", str(neuro_geometry_file),
                          "--pixel-spacing", "1e-300", "1e-300"]) == 2
    assert "--pixel-spacing: pixel spacing must be two positive numbers in 0.01..50 mm" in one_line_error(
        capsys, "chic-register: error: ")
    fifo = tmp_path / "slice.dcm"
    os.mkfifo(fifo)
    t0 = time.monotonic()
    assert register_main(["solve", str(fifo), "--geometry", str(neuro_geometry_file)]) == 2
    assert "is a FIFO (named pipe), not an image file" in one_line_error(capsys, "chic-register: error: ")
    assert time.monotonic() - t0 < 10
    os.mkfifo(tmp_path / "v.nii")
    assert register_main(["solve", str(tmp_path / "v.nii"), "--geometry", str(neuro_geometry_file),
                          "--slices", "0"]) == 2
    assert "is a FIFO" in one_line_error(capsys, "chic-register: error: ")


def test_an_image_too_large_for_a_slice_is_refused_before_decoding(tmp_path, capsys, neuro_geometry_file):
    path = tmp_path / "huge.npy"
    with open(path, "wb") as fh:  # header of a 100000 x 100000 float64 array (80 GB), no data
        np.lib.format.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False, "shape": (100000, 100000)})
    assert register_main(["solve", str(path), "--geometry", str(neuro_geometry_file),
                          "--pixel-spacing", "0.5", "0.5"]) == 2
    assert "too large for a slice" in one_line_error(capsys, f"chic-register: error: {path}: ")


def test_no_lock_is_still_a_no_lock(tmp_path, capsys, neuro_geometry_file):
    """The hardening does not turn a blank (valid) image into an error."""
    npy = tmp_path / "blank.npy"
    np.save(npy, np.zeros((64, 64)))
    rc = register_main(["solve", str(npy), "--geometry", str(neuro_geometry_file), "--pixel-spacing", "0.5", "0.5"])
    assert rc == NoLock.exit_code
