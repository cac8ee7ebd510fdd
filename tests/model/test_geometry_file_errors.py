"""Implausible or hostile geometry files (and FIFOs) are one-line GeometryFileErrors, never a traceback or a hang."""

from __future__ import annotations

import copy
import json
import os
import time

import pytest
import yaml

from chic_register.cli.main import main as register_main
from chic_register.errors import GeometryFileError
from chic_register.model.geometry import content_sha256, load_geometry
from tests.helpers import one_line_error


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
    err = one_line_error(capsys, "chic-register: error: --reference ")
    assert "is a FIFO (named pipe), not a reference file" in err
