"""Point files: Slicer's markups JSON and fiducial CSV and plain CSV, read and written, LPS and RAS."""

from __future__ import annotations

import json

import numpy as np
import pytest

from chic_register.errors import ChicRegisterError, InputFileError
from chic_register.io.markups import (
    MarkupPoint,
    PointList,
    as_system,
    point_format,
    read_points,
    write_points,
)

POINTS = PointList((MarkupPoint("a", (1.5, -2.25, 3.0), "first"), MarkupPoint("b, with comma", (-10.0, 20.0, 0.125))),
                   "LPS")


@pytest.mark.parametrize("name", ["p.mrk.json", "p.fcsv", "p.csv"])
@pytest.mark.parametrize("system", ["LPS", "RAS"])
def test_written_points_read_back_exactly(tmp_path, name, system):
    pts = as_system(POINTS, system)
    path = write_points(pts, tmp_path / name)
    back = read_points(path)
    assert back.coordinate_system == system
    assert back.labels == ["a", "b, with comma"]
    assert np.array_equal(back.positions_mm, pts.positions_mm)  # repr of floats: exact
    assert np.array_equal(back.positions_lps_mm(), POINTS.positions_mm)


def test_ras_and_lps_files_of_one_point_agree(tmp_path):
    ras = tmp_path / "r.mrk.json"
    ras.write_text(json.dumps({"markups": [{"coordinateSystem": "RAS", "controlPoints": [
        {"label": "t", "position": [10.0, 20.0, 30.0]}]}]}))
    lps = tmp_path / "l.fcsv"
    lps.write_text("# Markups fiducial file version = 4.11\n# CoordinateSystem = LPS\n"
                   "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
                   "vtkMRMLMarkupsFiducialNode_0,-10,-20,30,0,0,0,1,1,1,0,t,,\n")
    assert np.array_equal(read_points(ras).positions_lps_mm(), [[-10.0, -20.0, 30.0]])
    assert np.array_equal(read_points(lps).positions_lps_mm(), [[-10.0, -20.0, 30.0]])


def test_old_fcsv_numeric_system_and_no_system_line_is_ras(tmp_path):
    old = tmp_path / "old.fcsv"
    old.write_text("# Markups fiducial file version = 4.6\n# CoordinateSystem = 0\n"
                   "# columns = id,x,y,z,ow,ox,oy,oz,vis,sel,lock,label,desc,associatedNodeID\n"
                   "1,1,2,3,0,0,0,1,1,1,0,F-1,,\n")
    assert read_points(old).coordinate_system == "RAS"
    old.write_text("# Markups fiducial file version = 4.4\n1,1,2,3,0,0,0,1,1,1,0,F-1,,\n")
    pts = read_points(old)
    assert pts.coordinate_system == "RAS" and pts.labels == ["F-1"]
    assert np.array_equal(pts.positions_lps_mm(), [[-1.0, -2.0, 3.0]])


def test_csv_without_a_system_takes_the_callers_default(tmp_path):
    p = tmp_path / "p.csv"
    p.write_text("label,x,y,z,note\nentry,1,2,3,skin\n")
    pts = read_points(p)
    assert pts.coordinate_system is None and pts.points[0].columns == {"note": "skin"}
    assert np.array_equal(pts.positions_lps_mm("RAS"), [[-1.0, -2.0, 3.0]])
    frame = PointList(pts.points, "leksell")
    with pytest.raises(ChicRegisterError, match="leksell"):
        frame.positions_lps_mm()


def test_unplaced_slicer_points_are_skipped(tmp_path):
    p = tmp_path / "p.mrk.json"
    p.write_text(json.dumps({"markups": [{"coordinateSystem": "LPS", "controlPoints": [
        {"label": "set", "position": [1, 2, 3]}, {"label": "unset", "position": [0, 0, 0], "positionStatus": "undefined"}]}]}))
    assert read_points(p).labels == ["set"]


@pytest.mark.parametrize("name, text, key", [
    ("bad.mrk.json", "{not json", "not a JSON file"),
    ("bad.mrk.json", '{"points": []}', "'markups'"),
    ("bad.mrk.json", '{"markups": [{"coordinateSystem": "IJK", "controlPoints": []}]}', "coordinateSystem"),
    ("bad.mrk.json", '{"markups": [{"controlPoints": [{"label": "x"}]}]}', "controlPoints[0]"),
    ("bad.mrk.json", '{"markups": [{"controlPoints": [{"position": [1, "a", 3]}]}]}', "controlPoints[0].position"),
    ("bad.fcsv", "# CoordinateSystem = XYZ\n", "CoordinateSystem"),
    ("bad.fcsv", "# columns = id,x,y\n1,2,3\n", "columns"),
    ("bad.fcsv", "1,2,nan,4,0,0,0,1,1,1,0,a,,\n", "line 1"),
    ("bad.csv", "name,x,y,z\na,1,2,3\n", "label"),
    ("bad.csv", "label,x,y,z\na,1,2\n", "line 2"),
    ("bad.csv", "label,x,y,z,coordinates\na,1,2,3,LPS\nb,1,2,3,RAS\n", "several systems"),
])
def test_malformed_files_name_the_file_and_the_key(tmp_path, name, text, key):
    p = tmp_path / name
    p.write_text(text)
    with pytest.raises(InputFileError) as err:
        read_points(p)
    msg = str(err.value)
    assert msg.startswith(str(p)) and key in msg and "\n" not in msg


def test_missing_file_and_unknown_suffix(tmp_path):
    with pytest.raises(InputFileError, match="no such"):
        read_points(tmp_path / "none.fcsv")
    with pytest.raises(ChicRegisterError, match=r"\.mrk\.json, \.fcsv or \.csv"):
        point_format(tmp_path / "p.txt")
    assert point_format("P.MRK.JSON") == "mrk.json"


def test_a_failed_write_leaves_the_earlier_file(tmp_path):
    path = write_points(POINTS, tmp_path / "p.fcsv")
    before = path.read_bytes()
    with pytest.raises(ChicRegisterError, match="LPS or RAS"):
        write_points(PointList(POINTS.points, "leksell"), path)  # a Slicer file needs LPS or RAS
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.fcsv"]
