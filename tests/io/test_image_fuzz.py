"""Property-based: mutated DICOM files, any pixel spacing and arbitrary arrays give a pose, a no lock or a one-line
ImageReadError.

Seeded (``derandomize``), modest example counts and a per-example deadline that catches a hang.
"""

from __future__ import annotations

import warnings

import numpy as np
import pydicom
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from chic_register.errors import ImageReadError, NoLock
from chic_register.imaging.simulate import simulate_slice, write_simulated
from chic_register.io.images import read_slices
from chic_register.pipeline.register import register
from tests.helpers import FUZZ, assert_one_line


@pytest.fixture(scope="module")
def base_dicom(tmp_path_factory, neuro_geometry):
    sim = simulate_slice(neuro_geometry, 25.0, 10.0, 30.0, 20.0, noise="rician", snr=25.0, rng=2,
                         shape=(128, 128))
    path, _ = write_simulated(sim, tmp_path_factory.mktemp("fuzz") / "base.dcm")
    return path


DICOM_ATTRS = st.sampled_from(["PixelSpacing", "RescaleSlope", "RescaleIntercept", "SliceThickness",
                               "ImagePositionPatient", "ImageOrientationPatient", "Rows", "Columns",
                               "BitsAllocated", "PhotometricInterpretation", "NumberOfFrames", "SamplesPerPixel",
                               "PixelRepresentation"])


DICOM_VALUES = st.one_of(
    st.sampled_from(["1e-300", "1e300", "nan", "inf", "-inf", "0", "-1", "", "abc", "0.5", "1:10"]),
    st.lists(st.sampled_from(["1e-300", "0.5", "nan", "inf", "0", "-1", "1", "1e300"]), min_size=1, max_size=7)
    .map(lambda v: "\\".join(v)),
    st.integers(0, 70000).map(str),
)


def _is_result_or_domain_error(slices, geom) -> None:
    try:
        reg = register(slices, geom)
    except NoLock as exc:
        assert exc.reason and "\n" not in exc.reason
        return
    assert np.all(np.isfinite(reg.T_scanner_from_fiducial))


@settings(max_examples=30, deadline=20_000, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(edits=st.lists(st.tuples(DICOM_ATTRS, DICOM_VALUES), min_size=1, max_size=3))
def test_mutated_dicom_gives_a_result_or_a_one_line_error(tmp_path, base_dicom, neuro_geometry, edits):
    ds = pydicom.dcmread(base_dicom)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            for attr, value in edits:
                ds.data_element(attr).value = value if attr != "PixelSpacing" else value.split("\\")[:2]
            path = tmp_path / "mutated.dcm"
            ds.save_as(path)
        except Exception:  # pydicom cannot even write this value: not an input we can be given
            return
    try:
        slices = read_slices([path])
    except ImageReadError as exc:
        assert_one_line(exc, str(path))
        return
    _is_result_or_domain_error(slices, neuro_geometry)


SPACING = st.one_of(st.sampled_from([1e-300, 5e-324, 0.0, -0.5, 0.009, 0.01, 50.0, 50.1, 1e300]),
                    st.floats(allow_nan=True, allow_infinity=True))


@FUZZ
@given(spacing=st.tuples(SPACING, SPACING))
def test_any_pixel_spacing_gives_a_result_or_a_one_line_error(tmp_path, base_dicom, neuro_geometry, spacing):
    """A real fiducial image (the fuzz DICOM's pixels) as NPY, at any --pixel-spacing."""
    path = tmp_path / "slice.npy"
    np.save(path, read_slices([base_dicom])[0].pixels)
    try:
        slices = read_slices([path], spacing)
    except ImageReadError as exc:
        assert_one_line(exc, str(path))
        return
    _is_result_or_domain_error(slices, neuro_geometry)


@settings(max_examples=30, deadline=20_000, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(shape=st.tuples(st.integers(0, 80), st.integers(0, 80)),
       fill=st.sampled_from([0.0, 1.0, np.nan, np.inf, -1e308, 1e308]),
       dtype=st.sampled_from(["f8", "f4", "u1", "i2", "c8", "?"]),
       seed=st.integers(0, 2**16))
def test_arbitrary_arrays_give_a_result_or_a_one_line_error(tmp_path, neuro_geometry, shape, fill, dtype, seed):
    rng = np.random.default_rng(seed)
    with np.errstate(all="ignore"):
        arr = rng.random(shape) * 1000
        mask = rng.random(shape) < 0.05
        arr[mask] = fill
        arr = arr.astype(dtype)
    path = tmp_path / "a.npy"
    np.save(path, arr)
    try:
        slices = read_slices([path], (0.5, 0.5))
    except ImageReadError as exc:
        assert_one_line(exc, str(path))
        return
    _is_result_or_domain_error(slices, neuro_geometry)
