"""The print check with the real PrusaSlicer: shipped designs slice with the plate's own settings and keep every
channel open; a channel too small for the nozzle and a helix too steep for the layer height are failed, named
with their layer; a resin plate slices as SLA layer images, checked the same way. (`.ci/run` installs prusa-slicer.)"""

from __future__ import annotations

import dataclasses
import json
import zipfile

import numpy as np
import pytest
import shapely
import trimesh

from chic_design.build.pipeline import build_design
from chic_design.cad.parts import VENT_DEPTH_MM
from chic_design.cli.main import main
from chic_design.errors import ChannelsNotPrintable, InfeasibleDesign
from chic_design.families import FAMILIES
from chic_design.families.chic import ChicFamily
from chic_design.printing.plate import read_plate
from chic_design.printing.slicer import find_slicer, slice_plate
from chic_register.model.geometry import load_geometry
from tests.conftest import ROOT

pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(find_slicer() is None, reason="prusa-slicer is not installed (.ci/run installs it)")]

DATA = ROOT / "tests" / "data"
ORIGINAL_CHECK = ChicFamily.check


def _footer(gcode_path) -> dict[str, str]:
    out = {}
    for line in gcode_path.read_text().splitlines()[-600:]:
        if line.startswith("; ") and " = " in line:
            k, v = line[2:].split(" = ", 1)
            out[k] = v
    return out


def test_needle_guide_plate_slices_with_its_own_settings_and_keeps_every_channel_open(tmp_path):
    result = build_design(ROOT / "designs" / "needle-guide.yaml", out_root=tmp_path, progress=False)
    folder = result.folder
    plate = read_plate(folder / "plate.3mf")
    gcode = slice_plate(folder / "plate.3mf", tmp_path / "plate.gcode")
    used = _footer(gcode)
    for key in ("layer_height", "perimeters", "fill_density", "support_material", "seam_position", "nozzle_diameter"):
        assert used[key] == plate.config[key], key
    assert used["layer_height"] == "0.16"  # a tenth of the 1.6 mm channels
    check = json.loads((folder / "printcheck.json").read_text())
    assert check["ok"] and check["layers"] == round(40 / 0.16)
    ids = {c["id"] for c in check["channels"]}
    assert ids == {"D0", "D1", "D2", "D3", "H0", "H1", "H2", "O0", "O1"} | {f"port{k}" for k in range(1, 10)}
    for c in check["channels"]:
        assert c["min_clear_mm"] > 0.9 * c["diameter_mm"] and c["max_offset_mm"] < 0.05
    report = (folder / "report.md").read_text()
    assert "## Print check (toolpaths)" in report and "**every channel is open.**" in report
    assert (folder / "printcheck.png").stat().st_size > 10_000


def test_a_channel_too_small_for_the_nozzle_fails_the_print_check_with_channel_and_layer(tmp_path, capsys):
    """`check` foresees it (narrower_than_nozzle); built anyway, the toolpaths' check fails it too."""
    result = build_design(DATA / "narrow-channels.yaml", out_root=tmp_path, progress=False, printcheck=False,
                          pictures_in_worker=False, force=True)
    assert not (result.folder / "printcheck.json").exists()
    assert main(["printcheck", str(result.folder), "--quiet"]) == 6
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "D0 (body): narrower than the 0.8 mm nozzle" in err[0] and "at layer z = " in err[0]
    check = json.loads((result.folder / "printcheck.json").read_text())
    assert not check["ok"] and all(not c["ok"] for c in check["channels"] if c["part"] == "body")


def test_a_helix_the_layer_height_cannot_overhang_fails_the_print_check(tmp_path, monkeypatch):
    """`check` foresees it (overhang_for_layer, from h tan(beta)); the toolpaths' check measures it. A build
    that only the toolpaths fail is refused and writes nothing; with --force it is written with a warning."""
    with pytest.raises(InfeasibleDesign, match="overhang_for_layer"):
        build_design(DATA / "steep-helix.yaml", out_root=tmp_path, progress=False, pictures_in_worker=False)
    monkeypatch.setattr(ChicFamily, "check", lambda self, spec, **kw: _without_print_violations(spec))
    with pytest.raises(ChannelsNotPrintable) as err:
        build_design(DATA / "steep-helix.yaml", out_root=tmp_path, progress=False, pictures_in_worker=False)
    text = str(err.value)
    for helix in ("H0", "H1", "H2"):
        assert f"{helix} (body): overhang of" in text
    assert "at layer z = " in text and "D0" not in text
    assert not (tmp_path / "steep-helix").exists()
    forced = build_design(DATA / "steep-helix.yaml", out_root=tmp_path, progress=False, pictures_in_worker=False,
                          force=True)
    assert "WARNING: the print check failed" in forced.summary_text() and "H0 (body)" in forced.print_failures
    assert not json.loads((forced.folder / "printcheck.json").read_text())["ok"]


def _without_print_violations(spec):
    report = ORIGINAL_CHECK(FAMILIES["chic"], spec)
    kept = tuple(v for v in report.violations if v.code != "overhang_for_layer")
    return dataclasses.replace(report, violations=kept)


def test_a_resin_plate_carries_an_sla_profile_that_prusaslicer_slices_and_keeps_every_channel_open(tmp_path):
    spec = (DATA / "steep-helix.yaml").read_text().replace("  layer_height: 0.3", "  printer: resin")
    path = tmp_path / "resin.yaml"
    path.write_text(spec.replace("name: steep-helix", "name: resin-helix"))
    result = build_design(path, out_root=tmp_path / "out", progress=False, pictures_in_worker=False)
    check = json.loads((result.folder / "printcheck.json").read_text())  # checked in the layer images
    assert check["ok"] and check["layers"] == pytest.approx(15 / 0.05, abs=2)
    for c in check["channels"]:  # 0.05 mm pixels: every channel and port open to within about two pixels
        assert c["min_clear_mm"] > c["diameter_mm"] - 0.15 and c["max_offset_mm"] < 0.05, c["id"]
    plate = read_plate(result.folder / "plate.3mf")
    assert plate.config["printer_technology"] == "SLA" and plate.info["printer"] == "resin"
    sl1 = slice_plate(result.folder / "plate.3mf", tmp_path / "plate.sl1", sla=True)
    with zipfile.ZipFile(sl1) as z:
        names = z.namelist()
        config = z.read("config.ini").decode()
    assert "layerHeight = 0.05" in config
    assert sum(n.endswith(".png") and not n.startswith("thumbnail") for n in names) == pytest.approx(15 / 0.05, abs=2)
    # the vents: beside each channel's lower opening a groove runs out through the side wall, 0.6 mm deep
    body = trimesh.load(result.folder / "body.stl")
    geom = load_geometry(result.folder / "geometry.yaml")
    for t in geom.tubes:
        x, y = t.point_at_z(0.0)[0, :2]
        u = np.array([x, y]) / np.hypot(x, y)
        edge = np.hypot(x, y) + t.diameter / 2
        mid = u * (edge + geom.body.outer_diameter / 2) / 2  # between the channel's wall and the outside
        inside = [_in_section(body, z, mid) for z in (VENT_DEPTH_MM / 2, VENT_DEPTH_MM + 0.5)]
        assert inside == [False, True], t.id


def _in_section(mesh, z_mm, xy) -> bool:
    """Whether the point (x, y) lies in the mesh's section by the plane at ``z_mm``."""
    lines = trimesh.intersections.mesh_plane(mesh, [0, 0, 1], [0, 0, z_mm])[:, :, :2]
    noded = shapely.union_all(shapely.linestrings(np.round(lines, 5)))  # shared end points, exactly
    faces = shapely.get_parts(shapely.polygonize(shapely.get_parts(noded)))
    return sum(face.contains(shapely.Point(*xy)) for face in faces) % 2 == 1  # even-odd: holes cancel
