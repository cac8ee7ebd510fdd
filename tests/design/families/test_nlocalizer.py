"""The N-localizer family: spec, rod layout (Leksell G box), Leksell coordinates, geometry file, check and build."""

import numpy as np
import pytest
import yaml

from chic_design.errors import SpecError
from chic_design.families import FAMILIES
from chic_design.spec import load_spec, parse_spec
from chic_register.model.geometry import load_geometry, write_geometry
from chic_register.model.symmetry import frame_symmetries
from tests.conftest import ROOT

LEKSELL_CT = ROOT / "designs" / "leksell-g-ct.yaml"
LEKSELL_MR = ROOT / "designs" / "leksell-g-mr.yaml"
BRW = ROOT / "designs" / "brw-nlocalizer.yaml"
NLOC = FAMILIES["nlocalizer"]


def _data(path=LEKSELL_CT, **changes):
    data = yaml.safe_load(path.read_text())
    for key, value in changes.items():
        if "__" in key:
            section, name = key.split("__")
            data[section][name] = value
        else:
            data[key] = value
    return data


@pytest.fixture(scope="module")
def ct():
    spec = load_spec(LEKSELL_CT)
    return spec, NLOC.geometry(spec, source={"spec": "designs/leksell-g-ct.yaml"})


def test_the_preset_is_the_leksell_ct_box():
    assert NLOC.preset["name"] == "leksell-g-ct"
    preset = parse_spec(NLOC.preset)
    from_file = load_spec(LEKSELL_CT)
    assert preset.plates == from_file.plates and preset.frame == from_file.frame
    assert preset.hardware == from_file.hardware == "commercial"


def test_leksell_ct_rods_are_at_the_hand_worked_points(ct):
    """Right plate at x = -95 (normal -x), left at x = +95; rods at y = +-60; diagonals (y -60, z 0) to (y 60, z 120)."""
    _, geom = ct
    want = {
        "right_a": ((-95, 60, 0), (-95, 60, 120)), "right_d": ((-95, -60, 0), (-95, 60, 120)),
        "right_b": ((-95, -60, 0), (-95, -60, 120)),
        "left_a": ((95, -60, 0), (95, -60, 120)), "left_d": ((95, -60, 0), (95, 60, 120)),
        "left_b": ((95, 60, 0), (95, 60, 120)),
    }
    assert geom.ids == tuple(want)
    for tid, (p0, p1) in want.items():
        t = geom.tube(tid)
        assert t.p0 == p0 and t.p1 == p1, tid  # exact: no rounding noise in geometry.yaml
        assert t.diameter == 2.0
    assert [t.role for t in geom.tubes] == ["axial", "diagonal", "axial"] * 2
    assert geom.family == "nlocalizer" and geom.body.shape == "box" and geom.body.length == 120.0
    # the body encloses every rod: rod planes at x = +-95 in 8 mm walls
    assert geom.body.outer_size == (198.0, 144.0) and geom.body.inner_size == (182.0, 128.0)


@pytest.mark.parametrize("z", [0.0, 17.5, 60.0, 101.0, 120.0])
def test_the_diagonal_crosses_height_z_at_y_minus_60_plus_z_on_both_plates(ct, z):
    _, geom = ct
    for plate, x in (("right", -95.0), ("left", 95.0)):
        p = geom.tube(f"{plate}_d").point_at_z(z)[0]
        assert p == pytest.approx((x, -60.0 + z, z), abs=1e-9)


def test_leksell_coordinates_by_hand(ct):
    """X = 100 + x, Y = 100 - y, Z = 160 - z: the box centre is (100, 100, 100); the bottom (inferior) right
    anterior corner (x -95, y -60, z 0) is X 5 (the patient's right), Y 160 (anterior), Z 160 (inferior)."""
    _, geom = ct
    fc = geom.frame_coordinates
    assert fc.system == "leksell" and "Cureus" in fc.reference
    assert np.array_equal(fc.T_frame_from_fiducial, [[1, 0, 0, 100], [0, -1, 0, 100], [0, 0, -1, 160], [0, 0, 0, 1]])
    assert fc.to_frame_mm([0, 0, 60])[0] == pytest.approx((100, 100, 100))
    assert fc.to_frame_mm([-95, -60, 0])[0] == pytest.approx((5, 160, 160))
    # Z grows toward the feet: the top (superior) face z = 120 is Leksell Z 40
    assert fc.to_frame_mm([0, 0, 120])[0, 2] == pytest.approx(40)
    # another height: Z = 100 + height / 2 - z
    tall = NLOC.geometry(parse_spec(_data(frame__height=160)))
    assert tall.frame_coordinates.T_frame_from_fiducial[2, 3] == 180


def test_geometry_round_trips_through_the_file_with_frame_coordinates(ct, tmp_path):
    _, geom = ct
    path = write_geometry(geom, tmp_path / "geometry.yaml")
    text = path.read_text()
    assert "family: nlocalizer" in text and "shape: box" in text and "frame_coordinates:" in text
    back = load_geometry(path)  # checks the hash
    assert back.content() == geom.content()
    assert back.frame_coordinates.system == "leksell"
    assert np.array_equal(back.frame_coordinates.T_frame_from_fiducial, geom.frame_coordinates.T_frame_from_fiducial)
    assert back.body.outer_size == (198.0, 144.0)
    # no coordinates section: no key in the file
    plain = NLOC.geometry(parse_spec({k: v for k, v in _data().items() if k != "coordinates"}))
    assert plain.frame_coordinates is None and "frame_coordinates" not in plain.content()


def test_custom_coordinates_are_written_as_given():
    T = [[0, 1, 0, 5], [-1, 0, 0, 0], [0, 0, 1, -3], [0, 0, 0, 1]]
    geom = NLOC.geometry(parse_spec(_data(coordinates={"system": "custom", "T_frame_from_fiducial": T,
                                                       "reference": "lab convention"})))
    assert geom.frame_coordinates.system == "custom" and geom.frame_coordinates.reference == "lab convention"
    assert np.array_equal(geom.frame_coordinates.T_frame_from_fiducial, T)


def test_mr_box_has_edge_rods_along_y_at_both_faces():
    geom = NLOC.geometry(load_spec(LEKSELL_MR))
    edges = geom.by_role("other")
    assert [t.id for t in edges] == ["right_bottom", "right_top", "left_bottom", "left_top"]
    for t in edges:
        x = -95.0 if t.id.startswith("right") else 95.0
        z = 0.0 if t.id.endswith("bottom") else 120.0
        assert sorted((t.p0, t.p1)) == [(x, -60.0, z), (x, 60.0, z)], t.id
    assert NLOC.required_tubes(geom) == tuple(t for t in geom.tubes if t.role != "other")


@pytest.mark.parametrize("path", [LEKSELL_CT, LEKSELL_MR])
def test_check_reports_usable_slices_tilt_limit_and_the_half_turn_symmetry(path):
    report = NLOC.check(load_spec(path))
    assert report.feasible, report.violations
    (sym,) = [w for w in report.warnings if w.code == "symmetric_frame"]
    assert "half turn about the x axis" in sym.message and "--prior LPS" in sym.message
    assert report.unambiguity.unambiguous is False
    (lo, hi), = report.usable_depth[0].ranges_mm  # each diagonal leaves its rods a few mm from the faces
    assert 3 <= lo <= 8 and 112 <= hi <= 117
    # rods about 112 mm from the axis: visibility alone allows atan(60 / 112.4) = 28.1 deg at mid-depth
    mid = report.mid_depth_limit
    assert mid.visibility_tilt_deg == pytest.approx(np.degrees(np.arctan2(60, np.hypot(95, 60))), abs=0.1)
    assert 20 < mid.max_tilt_deg <= mid.visibility_tilt_deg
    # commercial hardware: no printability findings
    assert report.clearances == () and report.overhangs == ()
    text = report.summary_text()
    assert "all 6 vertical and diagonal rods visible" in text
    assert ("4 edge rods" in text) == (path == LEKSELL_MR)


def test_the_half_turn_maps_each_diagonal_onto_itself_and_only_a_third_plate_breaks_it(ct):
    _, geom = ct
    (fs,), _ = frame_symmetries(geom, 0.5)
    assert dict(fs.mapping) == {"right_a": "right_b", "right_d": "right_d", "right_b": "right_a",
                                "left_a": "left_b", "left_d": "left_d", "left_b": "left_a"}
    # two equal plates are always symmetric: with one diagonal reversed a half turn about z swaps them
    plates = _data()["plates"]
    plates[1]["diagonal_from"] = "right"
    syms, _ = frame_symmetries(NLOC.geometry(parse_spec(_data(plates=plates))), 0.5)
    assert "rotation by 180 deg about the z axis" in [s.what for s in syms]
    # a third (anterior) plate breaks it
    plates = _data()["plates"] + [{"name": "ant", "azimuth_deg": 270, "distance": 80, "width": 120,
                                   "diagonal_from": "left"}]
    assert frame_symmetries(NLOC.geometry(parse_spec(_data(plates=plates))), 0.5)[0] == ()


def test_brw_frame_has_no_whole_frame_symmetry_and_is_feasible():
    spec = load_spec(BRW)
    geom = NLOC.geometry(spec)
    assert len(geom.tubes) == 9 and geom.body.outer_size == (118.0, 118.0) and geom.body.inner_size == (102.0, 102.0)
    report = NLOC.check(spec)
    assert report.feasible, report.violations
    assert report.unambiguity.frame_symmetries == ()
    assert {w.code for w in report.warnings} <= {"channels_intersect", "ambiguous_slices"}
    assert min(c.gap_mm for c in report.clearances if c.b in ("bore", "outside")) == pytest.approx(2.5)


@pytest.mark.parametrize("changes, expected", [
    ({"plates": [{"name": "right", "azimuth_deg": 180, "distance": 95, "width": 120, "diagonal_from": "right"}]},
     "plates: Tuple should have at least 2 items"),
    ({"rods__diameter": 8}, "rods.diameter (8) must be smaller than frame.wall (8)"),
    ({"plates": [{"name": "a", "azimuth_deg": 0, "distance": 95, "width": 120, "diagonal_from": "left"}] * 2},
     "plates must have different names"),
    ({"plates": [{"name": "a", "azimuth_deg": 0, "distance": 95, "width": 120, "diagonal_from": "up"},
                 {"name": "b", "azimuth_deg": 180, "distance": 95, "width": 120, "diagonal_from": "left"}]},
     "plates.0.diagonal_from"),
    ({"plates": [{"name": "a", "azimuth_deg": 0, "distance": 95, "width": 120, "diagonal_from": "left"},
                 {"name": "b", "azimuth_deg": 90, "distance": 60, "width": 190, "diagonal_from": "left"}]},
     "plates a and b have rods 0.0 mm apart"),
    ({"coordinates": {"system": "brw"}}, "system brw needs T_frame_from_fiducial"),
    ({"coordinates": {"system": "leksell", "T_frame_from_fiducial": np.eye(4).tolist()}},
     "T_frame_from_fiducial is computed for system leksell"),
    ({"hardware": "printed", "edge_rods": True}, "edge_rods need hardware: commercial"),
    ({"hardware": "bought"}, "hardware"),
    ({"frame__colour": "red"}, "unknown key 'frame.colour'; allowed keys here: height, wall"),
])
def test_bad_nlocalizer_specs_are_one_line_errors(changes, expected):
    with pytest.raises(SpecError) as exc:
        parse_spec(_data(**changes), "n.yaml")
    assert expected in str(exc.value) and "\n" not in str(exc.value)


def test_a_printed_frame_must_be_a_rectangular_ring():
    plates = _data(BRW)["plates"]
    plates[1]["azimuth_deg"] = 100
    with pytest.raises(SpecError, match="azimuth_deg \\(100\\) must be 0, 90, 180 or 270 for printed hardware"):
        parse_spec(_data(BRW, plates=plates), "n.yaml")
    plates = _data(BRW)["plates"]
    plates[2]["distance"] = 60
    with pytest.raises(SpecError, match="must equal the opposite plate's \\(55\\)"):
        parse_spec(_data(BRW, plates=plates), "n.yaml")
    # a commercial frame may stand its plates anywhere: its body is a box around them all
    geom = NLOC.geometry(parse_spec({**_data(BRW, plates=plates), "hardware": "commercial",
                                     "plates": [{**p, "azimuth_deg": a} for p, a in zip(plates, (0, 120, 240))]}))
    xy = np.array([t.p0[:2] for t in geom.tubes])
    assert np.all(np.abs(xy) < np.array(geom.body.outer_size) / 2)


@pytest.mark.slow
def test_a_commercial_build_writes_geometry_and_no_part_files(tmp_path):
    from chic_design.build.pipeline import build_design

    result = build_design(LEKSELL_MR, out_root=tmp_path, progress=False, pictures_in_worker=False)
    names = sorted(p.name for p in result.folder.iterdir())
    assert "geometry.yaml" in names and "report.md" in names and "preview.png" in names
    assert "feasibility.json" in names and "tilt_limits.png" in names
    assert not [n for n in names if n.endswith((".stl", ".step", ".3mf")) or n.startswith("fill_guide")]
    assert result.checks.ok and [c.name for c in result.checks.checks] == ["geometry.yaml loads and its hash checks"]
    geom = load_geometry(result.folder / "geometry.yaml")
    assert geom.frame_coordinates.system == "leksell" and len(geom.tubes) == 10
    report = (result.folder / "report.md").read_text()
    assert report.startswith("# N-localizer `leksell-g-mr`") and "nothing is printed" in report
    assert "[0, 0, -1, 160]" in report


@pytest.mark.slow
def test_the_brw_frame_builds_its_parts(tmp_path):
    from chic_design.build.pipeline import build_design

    result = build_design(BRW, out_root=tmp_path, progress=False, pictures_in_worker=False, printcheck=False)
    assert result.checks.ok
    names = {p.name for p in result.folder.iterdir()}
    assert {"body.stl", "cap_top.stl", "cap_bottom.stl", "assembly.step", "plate.3mf", "geometry.yaml"} <= names
    # the body's sections show the bore and all nine channels where geometry.yaml puts them
    assert any("section" in c.name and "post_d" in c.name for c in result.checks.checks)
    report = (result.folder / "report.md").read_text()
    assert report.startswith("# N-localizer `brw-nlocalizer`") and "fill ports (top cap) | 6 x 1.2 mm" in report


def test_check_and_solver_agree_the_leksell_box_needs_a_prior_and_the_brw_frame_does_not(ct):
    """design -> geometry.yaml -> simulated slice (SNR 20, tilted) -> solve: the Leksell box, which check calls
    symmetric, is refused without a prior and registers with one; the BRW frame registers alone."""
    from chic_register.errors import NoLock
    from chic_register.imaging.simulate import simulate_slice
    from chic_register.pipeline.register import register

    def tre(reg, sim, centre):
        c = np.array([*centre, 1.0])
        return np.linalg.norm((reg.T_scanner_from_fiducial @ c)[:3] - (sim.truth.T_scanner_from_fiducial @ c)[:3])

    _, geom = ct
    sim = simulate_slice(geom, 72.0, 8.0, 30.0, 10.0, shape=(320, 320), pixel_spacing_mm=(0.8, 0.8),
                         noise="rician", snr=20, rng=3)
    with pytest.raises(NoLock, match="half turn about the x axis"):
        register([sim.slice], geom)
    assert tre(register([sim.slice], geom, prior=sim.truth.T_scanner_from_fiducial), sim, (0, 0, 60)) < 0.3
    brw = NLOC.geometry(load_spec(BRW))
    sim = simulate_slice(brw, 52.0, 8.0, 30.0, 10.0, noise="rician", snr=20, rng=3)
    assert tre(register([sim.slice], brw), sim, (0, 0, 40)) < 0.3
