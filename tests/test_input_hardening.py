"""Inputs that could crash or hang the programs: each gives a one-line error and a non-zero exit (or a correct
result), never a traceback or a hang."""

from __future__ import annotations

import copy
import json
import os
import time
from pathlib import Path

import numpy as np
import pydicom
import pytest
import yaml

from chic_register.cli.main import main as register_main
from chic_register.errors import GeometryFileError, NoLock
from chic_register.imaging.simulate import simulate_slice, write_simulated
from chic_register.live.folder import track
from chic_register.model.geometry import content_sha256, load_geometry

ROOT = Path(__file__).resolve().parents[1]


def _one_line_error(capsys, prefix: str) -> str:
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and "\n" not in err, err
    assert err.startswith(prefix), err
    return err


# ----------------------------------------------------------------------------- geometry files

def _geometry_text(neuro_geometry, edit, rehash=True) -> str:
    data = copy.deepcopy(neuro_geometry.to_dict())
    edit(data)
    if rehash:
        data["sha256"] = content_sha256(data)
    return yaml.safe_dump(data, sort_keys=False)


@pytest.mark.parametrize("edit, fragment", [
    (lambda d: d.update(version=1.0), "version is 1.0; this solver reads version 1 (an integer)"),
    (lambda d: d.update(version=True), "version is True"),
    (lambda d: d["body"].update(inner_diameter=40.0), "body.inner_diameter (40) must be smaller than"),
    (lambda d: d["body"].update(length=float("inf")), "body.length must be a finite number"),
    (lambda d: d["tubes"][0].update(diameter=-3.0), "tubes[0].diameter must be > 0"),
    (lambda d: d["tubes"][0].update(p1=[12.5, 0.0, 5000.0]), "tubes[0].p1[2] must lie within +-1000 mm"),
    (lambda d: d["tubes"][0].update(p1=[400.0, 0.0, 50.0]), "tube D0 reaches 400 mm from the axis"),
    (lambda d: d["tubes"][4].update(pitch_deg_per_mm=900.0), "tubes[4] turns 125 times"),
    (lambda d: d.update(source=["x"]), "source must be a mapping"),
])
def test_implausible_geometry_files_are_one_line_errors(tmp_path, neuro_geometry, edit, fragment):
    path = tmp_path / "geometry.yaml"
    path.write_text(_geometry_text(neuro_geometry, edit))
    with pytest.raises(GeometryFileError) as err:
        load_geometry(path)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(str(path)) and fragment in msg, msg


@pytest.mark.parametrize("source_yaml, fragment", [
    ("source: {built: !!binary aGVsbG8=}", "!!binary"),
    ("source: {built: !!set {a, b}}", "!!set"),
    ("source: {x: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\n  , y: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
     "  , z: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b, *b]\n  , w: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c, *c]\n"
     "  , v: &e [*d, *d, *d, *d, *d, *d, *d, *d, *d, *d]\n  , u: [*e, *e, *e, *e, *e, *e, *e, *e, *e, *e]}",
     "expands to more than"),
    ("source: " + "{a: " * 3000 + "1" + "}" * 3000, "nested deeper than 32 levels"),
])
def test_hostile_source_values_are_refused(tmp_path, neuro_geometry, source_yaml, fragment):
    text = yaml.safe_dump({k: v for k, v in neuro_geometry.to_dict().items() if k != "source"}, sort_keys=False)
    path = tmp_path / "geometry.yaml"
    path.write_text(text + source_yaml + "\n")
    t0 = time.process_time()
    with pytest.raises(GeometryFileError, match=fragment.replace("(", r"\(")):
        load_geometry(path)
    assert time.process_time() - t0 < 5.0


def test_non_json_source_values_from_python_callers_are_refused(neuro_geometry):
    import datetime

    from chic_register.model.geometry import geometry_from_dict

    for value, kind in (({1, 2}, "set"), (b"x", "bytes"), (datetime.date(2024, 1, 2), "date")):
        data = copy.deepcopy(neuro_geometry.to_dict())
        data["source"]["when"] = value
        with pytest.raises(GeometryFileError, match=f"source.when holds a {kind}"):
            geometry_from_dict(data, "g.yaml")


def test_a_date_in_source_is_read_as_text(tmp_path, neuro_geometry):
    def edit(d):
        d["source"]["built"] = "2024-01-02"

    path = tmp_path / "geometry.yaml"
    path.write_text(_geometry_text(neuro_geometry, edit).replace("'2024-01-02'", "2024-01-02"))
    geom = load_geometry(path)
    assert geom.source["built"] == "2024-01-02"
    json.dumps(geom.to_dict())  # the JSON output of solve/simulate can hold it


# ----------------------------------------------------------------------------- images

@pytest.fixture(scope="module")
def dicom_slice(tmp_path_factory, neuro_geometry):
    sim = simulate_slice(neuro_geometry, 25.0, 10.0, 30.0, 20.0, noise="rician", snr=25.0, rng=1)
    path, _ = write_simulated(sim, tmp_path_factory.mktemp("dcm") / "ok.dcm")
    return path, sim.truth.T_scanner_from_fiducial


def _edited_dicom(src, dst, **attrs) -> Path:
    import warnings

    ds = pydicom.dcmread(src)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pydicom warns about the invalid DS values we mean to write
        for k, v in attrs.items():
            setattr(ds, k, v)
        ds.save_as(dst)
    return dst


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
    path = _edited_dicom(dicom_slice[0], tmp_path / "bad.dcm", **attrs)
    assert register_main(["solve", str(path), "--geometry", str(neuro_geometry_file), "--json"]) == 2
    assert fragment in _one_line_error(capsys, f"chic-register: error: {path}: ")


def test_tiny_pixel_spacing_flag_and_fifo_image_exit_2(tmp_path, capsys, neuro_geometry_file):
    npy = tmp_path / "s.npy"
    np.save(npy, np.zeros((64, 64)))
    assert register_main(["solve", str(npy), "--geometry", str(neuro_geometry_file),
                          "--pixel-spacing", "1e-300", "1e-300"]) == 2
    assert "--pixel-spacing: pixel spacing must be two positive numbers in 0.01..50 mm" in _one_line_error(
        capsys, "chic-register: error: ")
    fifo = tmp_path / "slice.dcm"
    os.mkfifo(fifo)
    t0 = time.monotonic()
    assert register_main(["solve", str(fifo), "--geometry", str(neuro_geometry_file)]) == 2
    assert "is a FIFO (named pipe), not an image file" in _one_line_error(capsys, "chic-register: error: ")
    assert time.monotonic() - t0 < 10
    os.mkfifo(tmp_path / "v.nii")
    assert register_main(["solve", str(tmp_path / "v.nii"), "--geometry", str(neuro_geometry_file),
                          "--slices", "0"]) == 2
    assert "is a FIFO" in _one_line_error(capsys, "chic-register: error: ")


def test_an_image_too_large_for_a_slice_is_refused_before_decoding(tmp_path, capsys, neuro_geometry_file):
    path = tmp_path / "huge.npy"
    with open(path, "wb") as fh:  # header of a 100000 x 100000 float64 array (80 GB), no data
        np.lib.format.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False, "shape": (100000, 100000)})
    assert register_main(["solve", str(path), "--geometry", str(neuro_geometry_file),
                          "--pixel-spacing", "0.5", "0.5"]) == 2
    assert "too large for a slice" in _one_line_error(capsys, f"chic-register: error: {path}: ")


# ----------------------------------------------------------------------------- track

def test_track_survives_a_bad_file_and_registers_the_next(tmp_path, dicom_slice, neuro_geometry):
    watch = tmp_path / "w"
    watch.mkdir()
    _edited_dicom(dicom_slice[0], watch / "a_bad.dcm", PixelSpacing=["1e-300", "1e-300"])
    (watch / "b_good.dcm").write_bytes(dicom_slice[0].read_bytes())
    events, messages = [], []
    summary = track(watch, neuro_geometry, include_existing=True, max_files=1, timeout_s=60, settle_s=0.0,
                    on_event=events.append, on_message=messages.append)
    assert [Path(e.source).name for e in events] == ["b_good.dcm"] and events[0].status == "ok"
    assert summary.stopped_by == "max_files"
    assert any("a_bad.dcm" in m and "PixelSpacing" in m for m in messages)


def test_track_reports_an_unexpected_failure_and_goes_on(tmp_path, dicom_slice, neuro_geometry):
    from chic_register.pipeline.register import register

    watch = tmp_path / "w"
    watch.mkdir()
    for name in ("a.dcm", "b.dcm"):
        (watch / name).write_bytes(dicom_slice[0].read_bytes())

    def flaky(slices, geom, **kw):
        if slices[0].source.endswith("a.dcm"):
            raise ZeroDivisionError("float division by zero")
        return register(slices, geom, **kw)

    events = []
    summary = track(watch, neuro_geometry, include_existing=True, max_files=2, timeout_s=60, settle_s=0.0,
                    on_event=events.append, on_message=None, register=flaky)
    assert [(Path(e.source).name, e.status) for e in events] == [("a.dcm", "error"), ("b.dcm", "ok")]
    assert "ZeroDivisionError" in events[0].reason and "a.dcm: error: ZeroDivisionError" in events[0].text()
    assert summary.to_dict()["errors"] == 1 and summary.to_dict()["no_lock"] == 0


# ----------------------------------------------------------------------------- outputs and pipes


def test_no_lock_is_still_a_no_lock(tmp_path, capsys, neuro_geometry_file):
    """The hardening does not turn a blank (valid) image into an error."""
    npy = tmp_path / "blank.npy"
    np.save(npy, np.zeros((64, 64)))
    rc = register_main(["solve", str(npy), "--geometry", str(neuro_geometry_file), "--pixel-spacing", "0.5", "0.5"])
    assert rc == NoLock.exit_code




def test_fifo_geometry_and_reference_files_are_refused_not_waited_on(tmp_path, capsys, neuro_geometry_file):
    fifo = tmp_path / "fifo-geometry.yaml"
    os.mkfifo(fifo)
    with pytest.raises(GeometryFileError, match="is a FIFO .named pipe., not a geometry file"):
        load_geometry(fifo)
    ref = tmp_path / "ref.json"
    os.mkfifo(ref)
    vol = tmp_path / "v.nii"
    vol.write_bytes(b"")
    rc = register_main(["reslice", str(vol), "--geometry", str(neuro_geometry_file), "--reference", str(ref)])
    assert rc == 2
    err = _one_line_error(capsys, "chic-register: error: --reference ")
    assert "is a FIFO (named pipe), not a reference file" in err
