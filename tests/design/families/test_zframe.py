"""The Z-frame family: spec, rod layout (z001), geometry file, symmetry, feasibility check, and check vs solver."""

import json

import numpy as np
import pytest
import yaml
from scipy import ndimage
from scipy.spatial.transform import Rotation

from chic_design.cli.main import main as design_main
from chic_design.errors import SpecError
from chic_design.families import FAMILIES, family_of
from chic_design.feasibility.contacts import channel_contacts
from chic_design.spec import load_spec, parse_spec
from chic_register.imaging.blob_width import render_tubes_widened
from chic_register.imaging.simulate import simulate_slice
from chic_register.model.geometry import content_sha256, geometry_from_dict, load_geometry, write_geometry
from chic_register.model.pose import slice_frame
from chic_register.model.symmetry import frame_symmetries
from tests.conftest import NEEDLE, NEURO, ROOT, ZFRAME

ZNEEDLE = ROOT / "designs" / "zframe-needle.yaml"
ZFRAME_FAMILY = FAMILIES["zframe"]


def _geometry(spec, source=None):
    return family_of(spec).geometry(spec, source)


#: z001's seven fiducials (start, end) in its own frame (origin at the cube centre), as the
#: ZFrameRegistration configuration lists them; F is that frame shifted by +30 mm along z.
Z001 = [
    ((30, -30, -30), (30, -30, 30)),
    ((30, -30, 30), (30, 30, -30)),
    ((30, 30, -30), (30, 30, 30)),
    ((30, 30, 30), (-30, 30, -30)),
    ((-30, 30, -30), (-30, 30, 30)),
    ((-30, 30, 30), (-30, -30, -30)),
    ((-30, -30, -30), (-30, -30, 30)),
]

#: content hashes (no ``source``) of the CHIC designs' geometry, pinned: adding a family must not change
#: a CHIC geometry file.
CHIC_CONTENT_SHA256 = {
    NEURO: "5dee8c386e436721f0521ea6c24ce7af3f332f9c13373b251c6fbfebc4c37ec1",
    NEEDLE: "e8318411cb6a012aefc1b7b06368c08e7a7deb3edf263b24759c4b15962e3f1a",
}


@pytest.fixture(scope="module")
def zgeom():
    return _geometry(load_spec(ZFRAME), source={"spec": "designs/zframe.yaml"})


def _segments(tubes):
    return sorted(tuple(sorted((tuple(np.round(t.p0, 9)), tuple(np.round(t.p1, 9))))) for t in tubes)


def _zframe_data(**changes):
    data = yaml.safe_load(ZFRAME.read_text())
    for key, value in changes.items():
        section, name = key.split("__")
        data[section][name] = value
    return data


def test_default_layout_is_z001_shifted_by_half_the_height(zgeom):
    shifted = [(np.add(a, (0, 0, 30)), np.add(b, (0, 0, 30))) for a, b in Z001]
    want = sorted(tuple(sorted((tuple(map(float, a)), tuple(map(float, b))))) for a, b in shifted)
    assert _segments(zgeom.tubes) == want
    # the same order as z001's fiducials 1..7, the direction of each rod included (z up)
    for tube, (a, b) in zip(zgeom.tubes, shifted):
        lo, hi = (a, b) if a[2] < b[2] else (b, a)
        assert np.allclose(tube.p0, lo) and np.allclose(tube.p1, hi), tube.id
    assert [t.role for t in zgeom.tubes] == ["axial", "diagonal"] * 3 + ["axial"]
    assert zgeom.family == "zframe" and zgeom.body.shape == "square"
    assert (zgeom.body.outer_side, zgeom.body.inner_side, zgeom.body.length) == (67.0, 53.0, 60.0)


def test_faces_and_reversal_pick_the_diagonals():
    g = _geometry(parse_spec(_zframe_data(diagonals__faces=["+x", "-y"], diagonals__reversed_faces=["-y"])))
    assert [t.id for t in g.tubes] == ["A0", "Z+x", "A1", "A2", "A3", "Z-y"]
    zmy = g.tube("Z-y")
    # z001's rule would run -y from (30, -30) at the bottom; reversed it starts at (-30, -30)
    assert np.allclose(zmy.p0, (-30, -30, 0)) and np.allclose(zmy.p1, (30, -30, 60))


def test_geometry_file_round_trip_keeps_family_and_square_body(zgeom, tmp_path):
    path = write_geometry(zgeom, tmp_path / "geometry.yaml")
    text = path.read_text()
    assert "family: zframe" in text and "shape: square" in text
    back = load_geometry(path)
    assert back == zgeom
    data = _zframe_data()
    data["tool"] = {"tip_offset_mm": -40}  # a needle tip 40 mm below the frame: written like a CHIC tool
    with_tool = load_geometry(write_geometry(_geometry(parse_spec(data)), tmp_path / "tool.yaml"))
    assert np.allclose(with_tool.tool.T_fiducial_from_tool[:3, 3], (0, 0, -40)) and with_tool.family == "zframe"
    data = yaml.safe_load(text)
    data["family"] = "tripod"
    data["sha256"] = content_sha256(data)
    with pytest.raises(Exception, match="family is 'tripod'; allowed: chic, zframe"):
        geometry_from_dict(data, "g.yaml")


@pytest.mark.parametrize("spec_path", [NEURO, NEEDLE])
def test_chic_geometry_content_is_unchanged(spec_path):
    geom = _geometry(load_spec(spec_path))
    content = geom.content()
    assert content == FAMILIES["chic"].geometry(load_spec(spec_path)).content()
    assert "family" not in content and set(content["body"]) == {"length", "outer_diameter", "inner_diameter"}
    content.pop("tool", None)  # the optional tool frame is not part of the tubes
    assert content_sha256(content) == CHIC_CONTENT_SHA256[spec_path]


def test_diagonals_touch_their_corner_rods_near_the_faces_by_hand(zgeom, zcheck):
    """Z+x's section at height z: ellipse at (30, 30 - z), semi-axes 1.5 sqrt(2) along y and 1.5;
    A1's a 1.5 mm circle at (30, 30): they overlap while z < 1.5 (1 + sqrt(2)) = 3.62 mm."""
    got = {(c.a, c.b): c.z_ranges_mm for c in channel_contacts(zgeom)}
    top = 1.5 * (1 + 2**0.5)
    assert len(got) == 6
    for (a, b), ranges in got.items():
        (lo, hi), = ranges
        assert {a[0], b[0]} == {"A", "Z"}
        assert (lo, hi) == pytest.approx((0.0, top), abs=0.05) or (lo, hi) == pytest.approx((60 - top, 60), abs=0.05)
    # the feasibility report gives the same ranges (one answer)
    clear = {(c.a, c.b): c for c in zcheck.clearances if c.status == "intersect"}
    assert {frozenset(k): v.intersect_z_mm for k, v in clear.items()} == {frozenset(k): v for k, v in got.items()}


@pytest.mark.parametrize("changes, expected", [
    ({"rods__diameter": 7}, "rods.diameter (7) must be smaller than frame.wall (7)"),
    ({"diagonals__reversed_faces": ["-y"]}, "reversed_faces ['-y'] carry no diagonal"),
    ({"diagonals__faces": ["+x", "+x"]}, "faces must be different"),
    ({"diagonals__faces": ["+z"]}, "diagonals.faces.0"),
    ({"frame__colour": "red"}, "unknown key 'frame.colour'; allowed keys here: side, height, wall"),
])
def test_bad_zframe_specs_are_one_line_errors(changes, expected):
    with pytest.raises(SpecError) as exc:
        parse_spec(_zframe_data(**changes), "z.yaml")
    assert expected in str(exc.value) and "\n" not in str(exc.value)


def test_unknown_family_and_chic_keys_in_a_zframe_spec():
    with pytest.raises(SpecError, match="family: unknown family 'tripod'; allowed: chic, zframe"):
        parse_spec({"family": "tripod", "name": "x"}, "t.yaml")
    with pytest.raises(SpecError, match="unknown key 'body'; allowed keys here: family, name"):
        parse_spec({"family": "zframe", "name": "x", "body": {}}, "t.yaml")


def test_z001_is_symmetric_under_a_half_turn_about_y(zgeom):
    syms, _ = frame_symmetries(zgeom, 0.5)
    assert [s.what.split(" through")[0] for s in syms] == ["half turn about the y axis"]
    assert dict(syms[0].mapping) == {"A0": "A3", "Z+x": "Z-x", "A1": "A2", "Z+y": "Z+y",
                                     "A2": "A1", "Z-x": "Z+x", "A3": "A0"}
    # reversing the -x diagonal breaks it: nothing maps the rods within 50 mm
    asym = _geometry(parse_spec(_zframe_data(diagonals__reversed_faces=["-x"])))
    syms, best = frame_symmetries(asym, 0.5)
    assert syms == () and best > 50
    # diagonals on all four faces: the four-fold frame (z quarter turns among its symmetries)
    four = _geometry(parse_spec(_zframe_data(diagonals__faces=["+x", "+y", "-x", "-y"])))
    whats = [s.what for s in frame_symmetries(four, 0.5)[0]]
    assert "rotation by 90 deg about the z axis" in whats and len(whats) == 7


@pytest.fixture(scope="module")
def zcheck():
    return ZFRAME_FAMILY.check(load_spec(ZFRAME))


def test_check_reports_usable_range_and_ambiguity_honestly(zcheck):
    assert zcheck.feasible, zcheck.violations
    codes = {w.code for w in zcheck.warnings}
    assert {"symmetric_frame", "channels_intersect"} <= codes
    assert "ambiguous_slices" not in codes  # every slice is ambiguous already: said once, for the frame
    d = zcheck.to_dict()
    assert d["unambiguity"]["unambiguous"] is False
    assert "half turn about the y axis" in d["unambiguity"]["frame_symmetries"][0]["what"]
    (lo, hi), = zcheck.usable_depth[0].ranges_mm
    # the diagonals leave their corners' axial rods a few mm from the faces: 3.6 mm touch + blob size
    assert 4 <= lo <= 8 and 52 <= hi <= 56
    assert 25 < zcheck.mid_depth_limit.max_tilt_deg < 40
    text = zcheck.summary_text()
    assert "all 7 rods visible and separate" in text and "usable depth at tilt 0 deg: 6-54 mm" in text


def _n_blobs(geom, depth, tilt, azimuth, pixel=0.5, thickness=2.0):
    img = render_tubes_widened(geom.tubes, slice_frame(depth, tilt, azimuth, 0.0), (200, 200), (pixel, pixel),
                               thickness, supersample=2, thickness_samples=5)
    return ndimage.label(img > 0.02, structure=np.ones((3, 3)))[1]


def test_tilt_limit_agrees_with_rendered_slices(zgeom, zcheck):
    """Just inside the computed limit the seven rods are seven separate blobs; past it they merge."""
    mid = zcheck.mid_depth_limit
    assert _n_blobs(zgeom, mid.depth_mm, 0.0, 0.0) == 7
    assert _n_blobs(zgeom, mid.depth_mm, mid.max_tilt_deg - 1.0, mid.azimuth_deg) == 7
    assert _n_blobs(zgeom, mid.depth_mm, mid.max_tilt_deg + 3.0, mid.azimuth_deg) < 7
    # near the bottom face a diagonal's blob merges with its corner rod's
    assert _n_blobs(zgeom, 2.0, 0.0, 0.0) < 7


def test_check_cli_json_for_the_needle_variant(capsys):
    assert design_main(["check", str(ZNEEDLE), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["feasible"] and out["name"] == "zframe-needle"
    assert out["unambiguity"]["unambiguous"] is False
    assert out["tilt_limits"][0]["depth_mm"] == 0 and out["tilt_limits"][-1]["depth_mm"] == 45


def test_check_and_solver_agree_on_ambiguity(zgeom, zcheck, tmp_path):
    """design -> geometry.yaml -> simulated slice (SNR 20, tilted) -> solve.

    z001, which check calls ambiguous, is refused without an orientation prior and registers
    with one; with the -x diagonal reversed, which check calls unambiguous, it registers alone.
    """
    from chic_register.errors import NoLock
    from chic_register.pipeline.register import register

    centre = np.array([0.0, 0.0, 30.0, 1.0])

    def tre(reg, sim):
        return np.linalg.norm((reg.T_scanner_from_fiducial @ centre)[:3] - (sim.truth.T_scanner_from_fiducial @ centre)[:3])

    geom = load_geometry(write_geometry(zgeom, tmp_path / "geometry.yaml"))
    sim = simulate_slice(geom, 22.0, 10.0, 40.0, 15.0, noise="rician", snr=20, rng=7)
    assert zcheck.unambiguity.unambiguous is False
    with pytest.raises(NoLock, match="ambiguous"):
        register([sim.slice], geom)
    T = sim.truth.T_scanner_from_fiducial
    prior = T.copy()
    prior[:3, :3] = Rotation.from_rotvec(np.radians(15.0) * np.array([0.6, 0.8, 0.0])).as_matrix() @ T[:3, :3]
    assert tre(register([sim.slice], geom, prior=prior), sim) < 0.3

    spec = parse_spec(_zframe_data(diagonals__reversed_faces=["-x"]))
    asym = _geometry(spec)
    report = ZFRAME_FAMILY.check(spec)
    assert report.unambiguity.frame_symmetries == ()
    # no whole-frame symmetry, but slices near mid-height have a flipped twin (hand: tilt atan(2s / (30 - s)))
    (band,) = [w for w in report.warnings if w.code == "ambiguous_slices"]
    (sym,) = report.unambiguity.symmetries
    lo, hi = sym.depth_range_mm
    assert 26 <= lo < 30 < hi <= 34 and sym.mismatch_mm < 1e-6 and sym.at_depth_mm == 30.0
    # outside the band a single slice registers without a prior; inside it the solver refuses
    sim = simulate_slice(asym, 38.0, 15.0, 120.0, 15.0, noise="rician", snr=20, rng=8)
    assert tre(register([sim.slice], asym), sim) < 0.3
    sim = simulate_slice(asym, 30.0, 0.0, 0.0, 15.0, noise="rician", snr=20, rng=9)
    with pytest.raises(NoLock, match="ambiguous"):
        register([sim.slice], asym)
