"""chic-register map: scanner <-> stereotactic frame coordinates, hand-worked poses, round trips, uncertainty, errors;
and solve's frame_coordinates."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from chic_register.cli.main import main
from chic_register.io.markups import MarkupPoint, PointList, as_system, read_points, write_points
from chic_register.model.body import FrameCoordinates
from chic_register.model.geometry import content_sha256, write_geometry
from chic_register.model.pose import apply, rigid, rot_y, rot_z
from chic_register.model.pose_params import PARAMETER_ORDER, tre_rms_mm
from chic_register.outputs.frame import map_points
from chic_register.precision.points import PointUncertainty, point_covariance_F

#: Leksell coordinates of a fiducial whose F has x to the patient's left, y posterior and z superior, its origin
#: 60 mm below the frame centre: X = x + 100, Y = 100 - y, Z = 160 - z; F's (0, 0, 60) is (100, 100, 100).
LEKSELL = np.array([[1.0, 0, 0, 100], [0, -1.0, 0, 100], [0, 0, -1.0, 160], [0, 0, 0, 1]])
AXES = "X patient right to left, Y posterior to anterior, Z superior to inferior; centre (100, 100, 100)"


@pytest.fixture(scope="module")
def leksell_geometry(zframe_geometry):
    return dataclasses.replace(zframe_geometry, frame_coordinates=FrameCoordinates("leksell", LEKSELL, AXES,
                                                                                   "Elekta Leksell IFU"))


@pytest.fixture()
def geom_file(tmp_path, leksell_geometry):
    return write_geometry(leksell_geometry, tmp_path / "leksell.yaml")


def pose_file(tmp_path, T, cov=None, name="pose.json", **extra):
    doc = {"status": "ok", "T_scanner_from_fiducial": np.asarray(T).tolist(), **extra}
    if cov is not None:
        doc["covariance"] = {"parameters": list(PARAMETER_ORDER), "matrix": np.asarray(cov).tolist()}
    p = tmp_path / name
    p.write_text(json.dumps(doc))
    return p


def run_json(capsys, argv) -> dict:
    assert main([*argv, "--json"]) == 0, capsys.readouterr().err
    return json.loads(capsys.readouterr().out)


def test_leksell_matrix_puts_the_frame_centre_at_100(leksell_geometry):
    assert np.allclose(leksell_geometry.frame_coordinates.to_frame_mm([0.0, 0.0, 60.0]), [[100, 100, 100]])


def test_pure_translation_pose(tmp_path, geom_file, capsys):
    pose = pose_file(tmp_path, rigid(np.eye(3), (10.0, -20.0, 30.0)))
    doc = run_json(capsys, ["map", "--geometry", str(geom_file), "--pose", str(pose), "--to", "frame",
                            "--point", "10", "-20", "90", "--point", "11", "-20", "30"])
    assert doc["output_coordinates"] == "leksell" and doc["input_coordinates"] == "LPS"
    assert np.allclose(doc["points"][0]["output_mm"], [100, 100, 100], atol=1e-12)
    assert np.allclose(doc["points"][1]["output_mm"], [101, 100, 160], atol=1e-12)  # F's origin + 1 mm along x
    assert doc["points"][0]["uncertainty"] is None  # the pose file holds no covariance
    assert np.allclose(np.array(doc["T_frame_from_scanner"]) @ np.array(doc["T_scanner_from_frame"]), np.eye(4))


def test_ninety_degree_rotation_pose_both_ways(tmp_path, geom_file, capsys):
    T = rigid(rot_z(90.0), (5.0, 0.0, 0.0))  # F's x along the scanner's y
    pose = pose_file(tmp_path, T)
    g = ["--geometry", str(geom_file), "--pose", str(pose)]
    doc = run_json(capsys, ["map", *g, "--to", "frame", "--point", "5", "0", "60", "--point", "5", "10", "0"])
    assert np.allclose(doc["points"][0]["output_mm"], [100, 100, 100], atol=1e-12)
    assert np.allclose(doc["points"][1]["output_mm"], [110, 100, 160], atol=1e-12)
    back = run_json(capsys, ["map", *g, "--to", "scanner", "--point", "110", "100", "160"])
    assert np.allclose(back["points"][0]["output_mm"], [5, 10, 0], atol=1e-12)
    ras = run_json(capsys, ["map", *g, "--to", "scanner", "--ras", "--point", "110", "100", "160"])
    assert ras["output_coordinates"] == "RAS" and np.allclose(ras["points"][0]["output_mm"], [-5, -10, 0], atol=1e-12)


def _oblique_pose():
    return rigid(rot_z(35.0) @ rot_y(25.0) @ rot_z(-70.0), (31.5, -52.25, 18.75))


@pytest.mark.parametrize("suffix", [".csv", ".mrk.json", ".fcsv"])
def test_round_trip_through_files_to_1e_9_mm(tmp_path, geom_file, suffix, capsys):
    rng = np.random.default_rng(7)
    scanner = rng.uniform(-150, 150, (12, 3))
    src = write_points(PointList(tuple(MarkupPoint(f"p{i}", tuple(p)) for i, p in enumerate(scanner)), "LPS"),
                       tmp_path / f"in{suffix}")
    pose = pose_file(tmp_path, _oblique_pose(), np.diag([1e-3, 2e-3, 1e-3, 1e-2, 1e-2, 4e-2]))
    g = ["--geometry", str(geom_file), "--pose", str(pose)]
    fwd = tmp_path / f"frame{suffix}"
    assert main(["map", *g, "--to", "frame", "--points", str(src), "--out", str(fwd)]) == 0
    back = tmp_path / f"back{suffix}"
    assert main(["map", *g, "--to", "scanner", "--points", str(fwd), "--out", str(back)]) == 0
    capsys.readouterr()
    out = read_points(back)
    assert out.labels == [f"p{i}" for i in range(12)]
    assert np.abs(out.positions_lps_mm() - scanner).max() < 1e-9
    frame = read_points(fwd)
    expect = apply(LEKSELL @ np.linalg.inv(_oblique_pose()), scanner)
    # a Slicer file of frame coordinates declares RAS: Slicer's table shows the frame's X, Y, Z unchanged
    assert frame.coordinate_system == ("leksell" if suffix == ".csv" else "RAS")
    assert np.abs(frame.positions_mm - expect).max() < 1e-9
    if suffix == ".csv":
        text = fwd.read_text().splitlines()
        assert text[0].split(",")[:10] == ["label", "x", "y", "z", "coordinates", "sigma_x_mm", "sigma_y_mm",
                                           "sigma_z_mm", "rms_mm", "radius95_mm"]


def test_library_round_trip_to_1e_9_mm(leksell_geometry):
    rng = np.random.default_rng(3)
    scanner = rng.uniform(-300, 300, (200, 3))
    T = _oblique_pose()
    frame = leksell_geometry.frame_coordinates
    fwd = map_points(scanner, "frame", T, frame)
    back = map_points(np.array([m.frame_mm for m in fwd]), "scanner", T, frame)
    assert np.abs(np.array([m.scanner_lps_mm for m in back]) - scanner).max() < 1e-9


def test_ras_and_lps_inputs_give_the_same_frame_point(tmp_path, geom_file, capsys):
    pose = pose_file(tmp_path, _oblique_pose())
    g = ["--geometry", str(geom_file), "--pose", str(pose), "--to", "frame"]
    q = np.array([12.5, -40.0, 77.0])
    lps = run_json(capsys, ["map", *g, "--point", *map(str, q)])["points"][0]["output_mm"]
    ras = run_json(capsys, ["map", *g, "--ras", "--point", str(-q[0]), str(-q[1]), str(q[2])])["points"][0]
    pts = PointList((MarkupPoint("q", tuple(q)),), "LPS")
    for name in ("r.mrk.json", "r.fcsv"):
        f = write_points(as_system(pts, "RAS"), tmp_path / name)
        assert read_points(f).coordinate_system == "RAS"
        from_file = run_json(capsys, ["map", *g, "--points", str(f)])
        assert from_file["input_coordinates"] == "RAS"
        assert np.allclose(from_file["points"][0]["output_mm"], lps, atol=1e-12)
    assert np.allclose(ras["output_mm"], lps, atol=1e-12)
    assert np.allclose(ras["scanner_mm"], [-q[0], -q[1], q[2]]) and ras["frame_mm"] == ras["output_mm"]


def test_frame_coordinates_slicer_saved_in_lps_are_its_ras_numbers(tmp_path, geom_file, capsys):
    """A frame-coordinate list typed into Slicer's table (which shows RAS) and saved by Slicer in LPS."""
    typed = tmp_path / "typed.mrk.json"
    typed.write_text(json.dumps({"markups": [{"coordinateSystem": "LPS", "controlPoints": [
        {"label": "centre", "position": [-100.0, -100.0, 100.0]}]}]}))
    pose = pose_file(tmp_path, rigid(np.eye(3), (10.0, -20.0, 30.0)))
    doc = run_json(capsys, ["map", "--geometry", str(geom_file), "--pose", str(pose), "--to", "scanner",
                            "--points", str(typed)])
    assert doc["input_coordinates"] == "leksell" and doc["points"][0]["label"] == "centre"
    assert np.allclose(doc["points"][0]["frame_mm"], [100, 100, 100])
    assert np.allclose(doc["points"][0]["output_mm"], [10, -20, 90], atol=1e-12)


def test_uncertainty_grows_with_distance_from_the_fiducial_under_a_rotation_only_covariance(tmp_path, geom_file,
                                                                                             capsys):
    sd_deg = 0.1
    cov = np.diag([sd_deg ** 2] * 3 + [0.0] * 3)
    T = rigid(np.eye(3), (0.0, 0.0, 0.0))
    pose = pose_file(tmp_path, T, cov)
    out = tmp_path / "frame.csv"
    doc = run_json(capsys, ["map", "--geometry", str(geom_file), "--pose", str(pose), "--to", "frame", "--out",
                            str(out), *[a for z in (0, 30, 60, 120) for a in ("--point", "0", "0", str(z))]])
    rms = [p["uncertainty"]["rms_mm"] for p in doc["points"]]
    assert rms[0] == pytest.approx(0.0, abs=1e-12) and rms[1] < rms[2] < rms[3]
    # a point at distance d from F's origin moves r x p: sigma d (rad) across each of the two perpendicular axes
    for z, p in zip((0, 30, 60, 120), doc["points"]):
        s = math.radians(sd_deg) * z
        assert p["uncertainty"]["sigma_mm"] == pytest.approx([s, s, 0.0], abs=1e-9)
        assert p["uncertainty"]["rms_mm"] == pytest.approx(math.sqrt(2) * s, abs=1e-9)
        assert p["uncertainty"]["rms_mm"] == pytest.approx(tre_rms_mm(cov, (0, 0, z)), abs=1e-9)  # the TRE's
        assert p["uncertainty"]["radius95_mm"] == pytest.approx(2.4477 * s, rel=1e-3)  # chi-square(2) 95 %
    rows = out.read_text().splitlines()[1:]
    assert [float(r.split(",")[8]) for r in rows] == pytest.approx(rms, abs=1e-9)


def test_point_uncertainty_is_the_same_in_every_frame_up_to_rotation():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(6, 6))
    cov = A @ A.T * 1e-3
    C = point_covariance_F(cov, (10.0, -5.0, 40.0))
    R = _oblique_pose()[:3, :3]
    u, v = PointUncertainty(C), PointUncertainty(R @ C @ R.T)
    assert u.rms_mm == pytest.approx(v.rms_mm) and u.radius95_mm == pytest.approx(v.radius95_mm, rel=1e-9)
    assert u.rms_mm == pytest.approx(tre_rms_mm(cov, (10.0, -5.0, 40.0)))
    assert PointUncertainty(np.eye(3)).radius95_mm == pytest.approx(2.795483, abs=1e-5)


def test_tfm_pose_maps_without_uncertainty(tmp_path, geom_file, capsys):
    from chic_register.io.transforms import write_tfm

    tfm = write_tfm(rigid(rot_z(90.0), (5.0, 0.0, 0.0)), tmp_path / "pose.tfm")
    assert main(["map", "--geometry", str(geom_file), "--pose", str(tfm), "--to", "frame", "--point", "5", "0",
                 "60"]) == 0
    out = capsys.readouterr().out
    assert "no covariance" in out and "100.0000" in out


def _one_line_error(capsys, argv, *words):
    rc = main(argv)
    err = capsys.readouterr()
    assert rc == 2, err
    assert err.err.count("\n") == 1 and err.out == "", err
    for w in words:
        assert w in err.err, (w, err.err)


def test_bad_input_exits_2_naming_the_file_and_key_and_writes_nothing(tmp_path, geom_file, zframe_geometry, capsys):
    pose = pose_file(tmp_path, np.eye(4))
    out = tmp_path / "out.fcsv"
    base = ["map", "--pose", str(pose), "--to", "frame", "--out", str(out)]
    plain = write_geometry(zframe_geometry, tmp_path / "plain.yaml")
    _one_line_error(capsys, [*base, "--geometry", str(plain), "--point", "0", "0", "0"], str(plain),
                    "frame_coordinates")
    g = ["--geometry", str(geom_file)]
    _one_line_error(capsys, [*base, *g, "--points", str(tmp_path / "none.mrk.json")], "none.mrk.json", "no such")
    bad = tmp_path / "bad.mrk.json"
    bad.write_text('{"markups": [{"controlPoints": [{"label": "a"}]}]}')
    _one_line_error(capsys, [*base, *g, "--points", str(bad)], str(bad), "position")
    _one_line_error(capsys, [*base, *g, "--points", str(tmp_path / "p.txt")], "p.txt", ".mrk.json")
    nopose = tmp_path / "nolock.json"
    nopose.write_text(json.dumps({"status": "no_lock", "reason": "x"}))
    _one_line_error(capsys, ["map", "--pose", str(nopose), "--to", "frame", *g, "--point", "0", "0", "0"],
                    str(nopose), "T_scanner_from_fiducial")
    _one_line_error(capsys, [*base, *g], "--point")  # no points at all
    _one_line_error(capsys, ["map", "--pose", str(pose), "--to", "frame", *g, "--point", "0", "0", "0", "--out",
                             str(tmp_path / "o.xyz")], "o.xyz", ".fcsv")
    _one_line_error(capsys, ["map", "--pose", str(pose), "--to", "frame", *g, "--point", "0", "0", "0", "--out",
                             str(tmp_path / "nofolder" / "o.csv")], "nofolder")
    other = pose_file(tmp_path, np.eye(4), name="other.json", geometry={"name": "x", "sha256": "0" * 64})
    _one_line_error(capsys, ["map", "--pose", str(other), "--to", "frame", *g, "--point", "0", "0", "0"],
                    str(other), "another geometry")
    frame_csv = tmp_path / "frame.csv"
    frame_csv.write_text("label,x,y,z,coordinates\na,100,100,100,leksell\n")
    _one_line_error(capsys, [*base, *g, "--points", str(frame_csv)], str(frame_csv), "coordinates")
    assert not out.exists()
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []  # no temporary left


def test_a_pose_solved_before_the_geometry_named_its_frame_is_accepted(tmp_path, geom_file, leksell_geometry,
                                                                        capsys):
    content = leksell_geometry.content()
    content.pop("frame_coordinates")
    pose = pose_file(tmp_path, np.eye(4), geometry={"name": "z", "sha256": content_sha256(content)})
    assert main(["map", "--geometry", str(geom_file), "--pose", str(pose), "--to", "frame", "--point", "0", "0",
                 "60"]) == 0
    assert "100.0000" in capsys.readouterr().out


def test_solve_reports_the_pose_and_target_in_frame_coordinates_and_map_reads_its_json(tmp_path, neuro_geometry,
                                                                                        capsys):
    geom = dataclasses.replace(neuro_geometry, frame_coordinates=FrameCoordinates("leksell", LEKSELL, AXES))
    g = write_geometry(geom, tmp_path / "g.yaml")
    img = tmp_path / "s.dcm"
    assert main(["simulate", "--geometry", str(g), "--out", str(img), "--depth", "22", "--tilt", "20",
                 "--noise", "uniform", "--seed", "4"]) == 0
    capsys.readouterr()
    doc = run_json(capsys, ["solve", str(img), "--geometry", str(g), "--target", "0", "0", "60"])
    fc = doc["frame_coordinates"]
    assert fc["system"] == "leksell" and fc["axes"] == AXES
    T = np.array(doc["T_scanner_from_fiducial"])
    assert np.allclose(np.array(fc["T_frame_from_scanner"]), LEKSELL @ np.linalg.inv(T), atol=1e-9)
    assert np.allclose(np.array(fc["T_scanner_from_frame"]) @ np.array(fc["T_frame_from_scanner"]), np.eye(4))
    assert np.allclose(fc["target_frame_mm"], [100, 100, 100])
    pose = tmp_path / "pose.json"
    pose.write_text(json.dumps(doc))
    centre = apply(T, [0.0, 0.0, 60.0])
    mapped = run_json(capsys, ["map", "--geometry", str(g), "--pose", str(pose), "--to", "frame", "--point",
                               *map(str, centre)])
    p = mapped["points"][0]
    assert np.allclose(p["output_mm"], [100, 100, 100], atol=1e-9)
    assert p["uncertainty"]["rms_mm"] == pytest.approx(doc["predicted_tre_mm"], rel=1e-4)  # the TRE at the target
    assert main(["solve", str(img), "--geometry", str(g)]) == 0
    assert "leksell frame coordinates: scanner origin at" in capsys.readouterr().out
