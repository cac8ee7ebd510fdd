"""Property-based tests: mutated specs, geometry files and images give a result or a one-line domain error.

Never another exception, never a message over several lines. Seeded
(``derandomize``), modest example counts and a per-example deadline that
catches a hang.
"""

from __future__ import annotations

import copy
import math
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pydicom
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from chic_design.errors import SpecError
from chic_design.families import family_of
from chic_design.feasibility.printability import build_violations
from chic_design.spec import load_spec, parse_spec
from chic_register.errors import GeometryFileError, ImageReadError, NoLock
from chic_register.imaging.simulate import simulate_slice, write_simulated
from chic_register.io.images import read_slices
from chic_register.model.geometry import (
    content_sha256,
    geometry_from_dict,
    load_geometry,
)
from chic_register.pipeline.register import register

from .conftest import NEURO

FUZZ = settings(max_examples=40, deadline=20_000, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

NEURO_DATA = yaml.safe_load(NEURO.read_text())

#: Values a hostile or careless user might put anywhere.
ANY_VALUE = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, -1, 1e-300, 1e300, 1e9, 44.99, 0.01, 1e6, 2**63, -(2**63)]),
    st.integers(min_value=-(10**30), max_value=10**30),
    st.booleans(),
    st.none(),
    st.text(max_size=300),
    st.sampled_from(["1:10", "010", ".inf", "yes", "2024-01-02", "a" * 255, "../x", "x/y", "\x00"]),
    st.lists(st.floats(allow_nan=True), max_size=5),
    st.dictionaries(st.text(max_size=5), st.integers(), max_size=3),
)


def _paths(data, prefix=()):
    """Every key path of a nested dict (parents and leaves)."""
    for k, v in data.items():
        yield prefix + (k,)
        if isinstance(v, dict):
            yield from _paths(v, prefix + (k,))


def _set(data, path, value):
    node = data
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value


def _one_line(exc, prefix: str) -> None:
    msg = str(exc)
    assert "\n" not in msg and msg.startswith(prefix), msg


SPEC_PATHS = list(_paths(NEURO_DATA)) + [("extra",), ("body", "extra"), ("helix", "pitch_deg_per_mm"),
                                         ("channels", "circle_diameter"), ("helix", "offset_top_deg")]


def _finite_numbers(obj) -> bool:
    if isinstance(obj, dict):
        return all(_finite_numbers(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return all(_finite_numbers(v) for v in obj)
    return not isinstance(obj, float) or math.isfinite(obj)


@FUZZ
@given(edits=st.lists(st.tuples(st.sampled_from(SPEC_PATHS), ANY_VALUE), min_size=1, max_size=3))
def test_mutated_specs_give_a_spec_or_a_one_line_error(edits):
    data = copy.deepcopy(NEURO_DATA)
    for path, value in edits:
        try:
            _set(data, path, value)
        except (TypeError, KeyError):
            pass  # a parent was replaced by a non-mapping earlier
    try:
        spec = parse_spec(data, "fuzz.yaml")
    except SpecError as exc:
        _one_line(exc, "fuzz.yaml: ")
        return
    assert _finite_numbers(spec.model_dump())
    assert 1 <= len(spec.name) <= 64
    family = family_of(spec)
    geom = family.geometry(spec)
    build_violations(spec, geom, spec.imaging.pixel_size, family.length_key)  # the printability rules run on any valid spec


@FUZZ
@given(cuts=st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 40),
                               st.text(alphabet=":-[]{}&*!|>'\"#%@`,?\n .0123456789eEinfa", max_size=12)),
                     min_size=1, max_size=4))
def test_mutated_spec_text_gives_a_spec_or_a_one_line_error(cuts):
    text = NEURO.read_text()
    for pos, length, insert in cuts:
        pos %= len(text) + 1
        text = text[:pos] + insert + text[pos + length:]
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "spec.yaml"
        path.write_text(text)
        try:
            spec = load_spec(path)
        except SpecError as exc:
            _one_line(exc, str(path))
            return
    assert _finite_numbers(spec.model_dump())


# ----------------------------------------------------------------------------- geometry files

@pytest.fixture(scope="module")
def geometry_data(neuro_geometry):
    return neuro_geometry.to_dict()


GEOMETRY_KEYS = st.sampled_from(["version", "name", "units", "source", "body", "tubes", "format",
                                 "body.length", "body.outer_diameter", "body.inner_diameter",
                                 "tube.diameter", "tube.p0", "tube.p1", "tube.radius", "tube.pitch_deg_per_mm",
                                 "tube.z0", "tube.z1", "tube.kind", "tube.role", "tube.id", "tube.theta0_deg"])


@FUZZ
@given(edits=st.lists(st.tuples(GEOMETRY_KEYS, st.integers(0, 9), ANY_VALUE), min_size=1, max_size=3),
       rehash=st.booleans())
def test_mutated_geometry_gives_a_geometry_or_a_one_line_error(geometry_data, edits, rehash):
    data = copy.deepcopy(geometry_data)
    for key, tube_index, value in edits:
        if key.startswith("tube."):
            tubes = [t for t in data.get("tubes", []) if isinstance(t, dict)] if isinstance(data.get("tubes"), list) else []
            if tubes:
                tubes[tube_index % len(tubes)][key[5:]] = value
        elif key.startswith("body.") and isinstance(data.get("body"), dict):
            data["body"][key[5:]] = value
        else:
            data[key] = value
    if rehash:
        try:
            data["sha256"] = content_sha256(data)
        except (TypeError, ValueError):
            pass
    try:
        geom = geometry_from_dict(data, "g.yaml")
    except GeometryFileError as exc:
        _one_line(exc, "g.yaml: ")
        return
    # a geometry that loads is usable: finite, inside its plausible space, JSON-ready
    assert geom.body.inner_diameter < geom.body.outer_diameter
    content = geom.to_dict()
    assert _finite_numbers(content)
    geom.intersect_plane((0.0, 0.0, geom.body.length / 2), (0.0, 0.0, 1.0))


@FUZZ
@given(cuts=st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 20),
                               st.text(alphabet=":-[]{}&*!|>'\"#\n .0123456789eEinf", max_size=10)),
                     min_size=1, max_size=3))
def test_mutated_geometry_text_gives_a_geometry_or_a_one_line_error(tmp_path, neuro_geometry_file, cuts):
    text = neuro_geometry_file.read_text()
    for pos, length, insert in cuts:
        pos %= len(text) + 1
        text = text[:pos] + insert + text[pos + length:]
    path = tmp_path / "mutated.yaml"
    path.write_text(text)
    for check_hash in (True, False):
        try:
            load_geometry(path, check_hash=check_hash)
        except GeometryFileError as exc:
            _one_line(exc, str(path))


# ----------------------------------------------------------------------------- images

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
        _one_line(exc, str(path))
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
        _one_line(exc, str(path))
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
        _one_line(exc, str(path))
        return
    _is_result_or_domain_error(slices, neuro_geometry)
