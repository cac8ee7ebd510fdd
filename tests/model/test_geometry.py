"""The geometry objects (lines, helices) and the geometry file's round trip and hash check."""

import math

import numpy as np
import pytest
import yaml

from chic_register.errors import GeometryFileError
from chic_register.model.geometry import content_sha256, geometry_to_yaml, load_geometry, write_geometry
from chic_register.model.tubes import HelixTube, LineTube
from tests.helpers import modules_after


def test_helix_angle_and_points_at_z():
    h = HelixTube("H0", "helix", radius=12.5, theta0_deg=10, pitch_deg_per_mm=1.4, z0=0, z1=50, diameter=3)
    assert h.angle_deg_at(0) == pytest.approx(10)
    assert h.angle_deg_at(25) == pytest.approx(45)
    assert h.angle_deg_at(50) == pytest.approx(80)
    assert h.z_at_angle(45) == pytest.approx(25)
    p = h.point_at_z(25)[0]
    assert p == pytest.approx([12.5 * math.cos(math.radians(45)), 12.5 * math.sin(math.radians(45)), 25])
    # every point lies on the cylinder of the helix radius
    pts = h.points(np.linspace(0, 1, 11))
    assert np.hypot(pts[:, 0], pts[:, 1]) == pytest.approx(np.full(11, 12.5))
    # arc length: unrolled helix is a straight line of slope r*omega
    assert h.length_mm == pytest.approx(50 * math.hypot(1, 12.5 * math.radians(1.4)))
    # tangent is the normalised derivative (finite differences)
    eps = 1e-6
    fd = (h.points(0.5 + eps) - h.points(0.5 - eps))[0]
    assert h.tangents(0.5)[0] == pytest.approx(fd / np.linalg.norm(fd), abs=1e-6)


def test_left_handed_helix_turns_clockwise():
    h = HelixTube("H", "helix", radius=5, theta0_deg=80, pitch_deg_per_mm=-2, z0=10, z1=30, diameter=1)
    assert h.angle_deg_at(30) == pytest.approx(40)
    assert h.z_at_angle(60) == pytest.approx(20)


def test_line_points_and_plane_crossing():
    d0 = LineTube("D0", "diametric", (12.5, 0, 0), (12.5, 0, 50), 3.0)
    assert d0.point_at_z(20)[0] == pytest.approx([12.5, 0, 20])
    # a plane through (0,0,25) tilted 45 deg toward +x meets x = 12.5 at z = 25 - 12.5
    n = np.array([math.sin(math.radians(45)), 0, math.cos(math.radians(45))])
    assert d0.intersect_plane([0, 0, 25], n)[0] == pytest.approx([12.5, 0, 12.5])
    # beyond the tube's extent: no crossing
    n60 = np.array([math.sin(math.radians(70)), 0, math.cos(math.radians(70))])
    assert d0.intersect_plane([0, 0, 25], n60).shape == (0, 3)
    # parallel plane: none
    assert d0.intersect_plane([0, 0, 0], [1, 0, 0]).shape == (0, 3)


def test_helix_plane_crossings_match_the_plane_equation():
    h = HelixTube("H0", "helix", radius=12.5, theta0_deg=10, pitch_deg_per_mm=1.4, z0=0, z1=50, diameter=3)
    assert h.intersect_plane([0, 0, 30], [0, 0, 1])[0] == pytest.approx(h.point_at_z(30)[0])
    rng = np.random.default_rng(1)
    for _ in range(50):
        tilt, az = np.radians(rng.uniform(0, 60)), rng.uniform(0, 2 * np.pi)
        n = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
        o = np.array([0, 0, rng.uniform(15, 35)])
        pts = h.intersect_plane(o, n)
        assert len(pts) == 1
        assert float((pts[0] - o) @ n) == pytest.approx(0, abs=1e-9)
        assert np.hypot(*pts[0, :2]) == pytest.approx(12.5)
    # a plane containing the axis crosses a multi-turn helix several times
    coil = HelixTube("C", "other", radius=5, theta0_deg=0, pitch_deg_per_mm=36, z0=0, z1=20, diameter=1)
    assert len(coil.intersect_plane([0, 0, 0], [0, 1, 0])) == 4  # 2 turns: angles 180, 360, 540, 720


def test_geometry_file_round_trip(neuro_geometry, tmp_path):
    (tmp_path / "g").mkdir()
    path = write_geometry(neuro_geometry, tmp_path / "g" / "geometry.yaml")
    loaded = load_geometry(path)
    assert loaded == neuro_geometry
    data = yaml.safe_load(path.read_text())
    assert data["format"] == "chic-geometry" and data["version"] == 1 and data["units"] == "mm"
    assert [t["id"] for t in data["tubes"]] == ["D0", "D1", "D2", "D3", "H0", "H1", "H2", "O0", "O1"]
    assert data["tubes"][0]["p0"] == [12.5, 0.0, 0.0]  # +x toward D0 (docs/interfaces.md s.1)
    assert data["sha256"] == content_sha256(data)
    assert not list(path.parent.glob(".geometry-*"))  # no temporary left behind


def test_hash_ignores_number_spelling_but_catches_edits(neuro_geometry_file):
    text = neuro_geometry_file.read_text()
    neuro_geometry_file.write_text(text.replace("length: 50.0", "length: 50"))
    load_geometry(neuro_geometry_file)  # 50 and 50.0 are the same content
    neuro_geometry_file.write_text(text.replace("theta0_deg: 10.0", "theta0_deg: 11.0"))
    with pytest.raises(GeometryFileError, match="sha256 does not match"):
        load_geometry(neuro_geometry_file)


@pytest.mark.parametrize(
    "edit,message",
    [
        (lambda d: d.update(format="z-frame"), "format is 'z-frame'; expected 'chic-geometry'"),
        (lambda d: d.update(version=2), "version is 2; this solver reads version 1"),
        (lambda d: d.pop("sha256"), "missing key 'sha256'"),
        (lambda d: d["tubes"][4].update(kind="spiral"), "tubes[4].kind is 'spiral'; allowed: line, helix"),
        (lambda d: d["tubes"][0].pop("p1"), "missing key 'tubes[0].p1'"),
        (lambda d: d["tubes"][1].update(id="D0"), "duplicate tube ids: D0"),
        (lambda d: d["body"].update(length="x"), "body.length must be a finite number"),
    ],
)
def test_geometry_loader_rejects_bad_files(neuro_geometry_file, edit, message):
    data = yaml.safe_load(neuro_geometry_file.read_text())
    edit(data)
    if "sha256" in data:
        data["sha256"] = content_sha256(data)  # a well-hashed file that is still wrong
    neuro_geometry_file.write_text(yaml.safe_dump(data))
    with pytest.raises(GeometryFileError) as err:
        load_geometry(neuro_geometry_file)
    assert message in str(err.value) and str(neuro_geometry_file) in str(err.value)


def test_loader_on_missing_and_non_yaml(tmp_path):
    with pytest.raises(GeometryFileError, match="no such geometry file"):
        load_geometry(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("tubes: [\n")
    with pytest.raises(GeometryFileError, match="not valid YAML"):
        load_geometry(bad)


def test_geometry_files_written_by_the_dumper_read_back_identically(tmp_path, neuro_geometry):
    """The writer (PyYAML's dumper) and this loader agree on every scalar, so the hash still checks."""
    path = tmp_path / "geometry.yaml"
    path.write_text(geometry_to_yaml(neuro_geometry))
    again = load_geometry(path)
    assert again.to_dict() == neuro_geometry.to_dict()


def test_geometry_import_does_not_pull_in_scipy_optimize():
    mods = modules_after("import chic_register.model.geometry")
    assert "chic_register.model.geometry" in mods and "scipy.optimize" not in mods
