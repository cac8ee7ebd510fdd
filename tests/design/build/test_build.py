"""Full build of designs/neuro.yaml: every output file, the output checks, and atomic writing."""

import hashlib
import json
import math
import shutil
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import trimesh
from build123d import Mesher
from PIL import Image

import chic_design.build.folders as folders_mod
import chic_design.build.pipeline as pipeline_mod
import chic_design.cad.export as export_mod
from chic_design.build.folders import replace_folder
from chic_design.build.pipeline import build_design
from chic_design.cad.export import STL_ANGULAR_TOLERANCE_RAD, STL_TOLERANCE_MM
from chic_design.cli.main import main
from chic_design.errors import BuildCheckError, InfeasibleDesign, SpecError
from chic_design.families import FAMILIES
from chic_design.families.chic import ChicFamily
from chic_design.feasibility.records import Finding
from chic_design.feasibility.sections import section_clearance_mm, section_heights
from chic_design.printing.plate import read_plate
from chic_design.printing.slicer import find_slicer
from chic_design.spec import load_spec, spec_sha256
from chic_design.verify import verify_export
from chic_register.model.geometry import load_geometry
from chic_register.model.tubes import LineTube
from tests.conftest import NEURO

CHIC = FAMILIES["chic"]

pytestmark = pytest.mark.slow

PART_FILES = [f"{p}.{e}" for p in ("body", "cap_top", "cap_bottom") for e in ("stl", "step", "3mf")]
ALL_FILES = PART_FILES + ["assembly.step", "geometry.yaml", "preview.png", "report.md",
                          "tilt_limits.png", "feasibility.json", "plate.3mf",
                          "fill_guide.png", "fill_guide.html", "fill_guide.pdf"]


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """One full build of neuro.yaml for this module's tests (the slow part)."""
    out = tmp_path_factory.mktemp("exports")
    result = build_design(NEURO, out_root=out, progress=False)
    spec = load_spec(NEURO)
    parts = CHIC.parts(spec, CHIC.geometry(spec))
    volumes = {name: float(p.volume) for name, p in parts.items()}
    return out, result, volumes


def _tree_digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_every_output_file_exists(built):
    out, result, _ = built
    assert result.folder == (out / "neuro").resolve()
    for name in ALL_FILES:
        path = result.folder / name
        assert path.is_file() and path.stat().st_size > 0, name
    assert not list(out.glob(".neuro.*")), "temporary folder left behind"
    assert "output checks passed" in result.summary_text()


def test_output_checks_pass_and_cover_every_tube(built):
    _, result, _ = built
    assert result.checks.ok
    names = [c.name for c in result.checks.checks]
    for part in ("body", "cap_top", "cap_bottom"):
        for suffix in ("watertight", "winding consistent", "is a volume", "volume matches CAD"):
            assert f"{part}.stl {suffix}" in names
            assert f"{part}.3mf {suffix}" in names
    assert len(result.checks.section_heights_mm) == 5
    for z in result.checks.section_heights_mm:
        for tid in ("D0", "D1", "D2", "D3", "H0", "H1", "H2", "O0", "O1"):
            assert f"body.stl section z={z:.2f} {tid}" in names
    assert "cap_top does not overlap body (mesh)" in names
    assert "cap_bottom does not overlap body (CAD)" in names


def test_geometry_file_is_the_spec_geometry(built):
    _, result, _ = built
    geom = load_geometry(result.folder / "geometry.yaml")
    want = CHIC.geometry(load_spec(NEURO))
    assert geom.tubes == want.tubes
    assert geom.source["spec"] == str(NEURO)
    assert geom.source["spec_sha256"] == spec_sha256(NEURO)


def test_meshes_are_printable_and_in_frame_F(built):
    _, result, volumes = built
    body = trimesh.load_mesh(result.folder / "body.stl")
    assert body.is_watertight and body.is_volume
    assert np.allclose(body.bounds, [[-15, -15, 0], [15, 15, 50]], atol=1e-3)
    assert body.volume == pytest.approx(volumes["body"], rel=5e-3)
    top = trimesh.load_mesh(result.folder / "cap_top.stl")
    assert top.bounds[0, 2] == pytest.approx(46.0) and top.bounds[1, 2] == pytest.approx(52.0)
    scene = trimesh.load(result.folder / "cap_bottom.3mf")
    assert list(scene.geometry) == ["cap_bottom"]


def test_stl_parts_declare_lps_for_slicer(built):
    """Slicer reads SPACE= from the STL header: F is declared LPS, the convention of the .tfm."""
    _, result, _ = built
    for part in ("body", "cap_top", "cap_bottom"):
        assert (result.folder / f"{part}.stl").read_bytes()[:9] == b"SPACE=LPS"


def test_assembly_step_has_labelled_parts(built):
    _, result, _ = built
    text = (result.folder / "assembly.step").read_text(errors="replace")
    for name in ("neuro", "body", "cap_top", "cap_bottom"):
        assert f"PRODUCT('{name}'" in text


def test_preview_shows_the_coloured_channels(built):
    _, result, _ = built
    img = np.asarray(Image.open(result.folder / "preview.png").convert("RGB")).astype(int)
    assert img.shape == (800, 1000, 3)
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    assert ((r > 150) & (g < 80) & (b < 80)).sum() > 500  # red diametric tubes
    assert ((b > 100) & (r < 60) & (g < 60)).sum() > 500  # blue helices
    assert ((g > 90) & (r < 60) & (b < 60)).sum() > 200  # green orientation tubes


def test_feasibility_is_in_the_export(built):
    _, result, _ = built
    data = json.loads((result.folder / "feasibility.json").read_text())
    assert data["feasible"] is True and data["tilt_limits"]
    assert result.feasible is True
    text = (result.folder / "report.md").read_text()
    assert "## Feasibility" in text and "tilt_limits.png" in text
    assert Image.open(result.folder / "tilt_limits.png").size[0] > 200


def test_infeasible_design_is_refused_before_cad_unless_forced(tmp_path, monkeypatch):
    real = ChicFamily.check

    def with_violation(self, spec, **kwargs):
        report = real(self, spec, **kwargs)
        return replace(report, violations=(Finding("wall_too_thin", "0.5 mm wall", "D0"),))

    def no_cad(*args, **kwargs):
        raise AssertionError("CAD work started for an infeasible design")

    monkeypatch.setattr(ChicFamily, "check", with_violation)
    monkeypatch.setattr(ChicFamily, "parts", no_cad)
    out = tmp_path / "exports"
    with pytest.raises(InfeasibleDesign, match="wall_too_thin") as err:
        build_design(NEURO, out_root=out, progress=False)
    assert err.value.exit_code == 4
    assert not out.exists() or not any(out.iterdir())
    assert main(["build", str(NEURO), "--out", str(out), "--quiet"]) == 4
    with pytest.raises(AssertionError, match="CAD work started"):  # --force goes on to the CAD
        build_design(NEURO, out_root=out, force=True, progress=False, pictures_in_worker=False, printcheck=False)
    assert not any(out.iterdir())


def test_report_has_volumes_and_filling(built):
    _, result, volumes = built
    text = (result.folder / "report.md").read_text()
    for needle in ("## Channels", "## Filling and closing", "## Output checks", "fill port", "H2", "mL"):
        assert needle.lower() in text.lower(), needle
    assert f"{volumes['body']:.1f}" in text
    total_ml = (math.pi / 4 * 500 * 50 - volumes["body"]) / 1000
    assert f"{total_ml:.3f} mL" in text
    assert "FAIL" not in text
    # the fill guide's section, and its files listed with the build's
    for needle in ("[fill_guide.pdf](fill_guide.pdf)", "| 9 | 10.83 | -6.25 | O1 | 3 | fill |",
                   "Seal the ports in this order", "D0 and H0: touch in the wall"):
        assert needle in text, needle
    assert {"fill_guide.png", "fill_guide.html", "fill_guide.pdf"} <= set(result.files)


def test_section_heights_avoid_touching_channels(neuro_geometry):
    z = section_heights(neuro_geometry)
    assert len(z) == 5 and np.all(np.diff(z) > 0)
    assert np.all(section_clearance_mm(neuro_geometry, z) >= 0.3)
    # near the ends the helices meet the diametric tubes: those heights are not used
    assert section_clearance_mm(neuro_geometry, [1.0])[0] < 0
    assert z.min() > 1.0 and z.max() < 49.0


def _copy_export(built, tmp_path) -> Path:
    _, result, _ = built
    dst = tmp_path / "copy"
    shutil.copytree(result.folder, dst)
    return dst


def test_verify_catches_a_deleted_face(built, tmp_path):
    _, _, volumes = built
    folder = _copy_export(built, tmp_path)
    mesh = trimesh.load_mesh(folder / "cap_bottom.stl")
    mesh.update_faces(np.arange(1, len(mesh.faces)))
    mesh.export(folder / "cap_bottom.stl")
    with pytest.raises(BuildCheckError, match="cap_bottom.stl watertight") as err:
        verify_export(folder, volumes)
    assert "cap_bottom.stl is a volume" in str(err.value)
    assert "body.stl" not in str(err.value)


def test_verify_catches_a_shifted_channel(built, tmp_path):
    """A body whose D0 channel is 0.2 mm off the geometry file's D0 fails the section check for D0."""
    _, _, volumes = built
    folder = _copy_export(built, tmp_path)
    spec = load_spec(NEURO)
    geom = CHIC.geometry(spec)
    d0 = geom.tube("D0")
    shift = (0.0, 0.2, 0.0)
    moved = LineTube("D0", "diametric", np.add(d0.p0, shift), np.add(d0.p1, shift), d0.diameter)
    bad = replace(geom, tubes=(moved,) + geom.tubes[1:])
    mesher = Mesher()
    mesher.add_shape(CHIC.parts(spec, bad).body, linear_deflection=STL_TOLERANCE_MM,
                     angular_deflection=STL_ANGULAR_TOLERANCE_RAD)
    mesher.write(str(folder / "body.stl"))
    result = verify_export(folder, volumes, raise_on_failure=False)
    failed = [c.name for c in result.failed]
    assert failed and all(n.startswith("body.stl section") and n.endswith(" D0") for n in failed)
    assert len(failed) == len(result.section_heights_mm)
    with pytest.raises(BuildCheckError, match=r"body.stl section z=\S+ D0: hole centroid 0.2"):
        result.raise_if_failed()


def test_verify_catches_a_missing_channel_in_the_mesh(built, tmp_path):
    _, _, volumes = built
    folder = _copy_export(built, tmp_path)
    spec = load_spec(NEURO)
    geom = CHIC.geometry(spec)
    fewer = replace(geom, tubes=tuple(t for t in geom.tubes if t.id != "O1"))
    mesher = Mesher()
    mesher.add_shape(CHIC.parts(spec, fewer).body, linear_deflection=STL_TOLERANCE_MM,
                     angular_deflection=STL_ANGULAR_TOLERANCE_RAD)
    mesher.write(str(folder / "body.stl"))
    with pytest.raises(BuildCheckError) as err:
        verify_export(folder, volumes)
    assert "body.stl volume matches CAD" in str(err.value)
    assert "hole count" in str(err.value) and "9 holes, expected 10 (9 tubes + bore)" in str(err.value)


def test_failed_build_leaves_earlier_export_untouched(built, tmp_path, monkeypatch):
    out = tmp_path / "exports"
    out.mkdir()
    shutil.copytree(built[1].folder, out / "neuro")  # an earlier good export
    before = _tree_digest(out / "neuro")

    real_export = pipeline_mod.export_parts

    def export_then_crash(parts, folder, name):
        real_export(parts, folder, name)  # the new files are all written in the temporary folder
        raise OSError("disk full")

    monkeypatch.setattr(pipeline_mod, "export_parts", export_then_crash)
    with pytest.raises(OSError, match="disk full"):
        build_design(NEURO, out_root=out, progress=False, pictures_in_worker=False)
    assert _tree_digest(out / "neuro") == before
    assert sorted(p.name for p in out.iterdir()) == ["neuro"], "temporary folder left behind"


def test_failed_output_check_leaves_earlier_export_untouched(built, tmp_path, monkeypatch):
    out = tmp_path / "exports"
    out.mkdir()
    shutil.copytree(built[1].folder, out / "neuro")
    before = _tree_digest(out / "neuro")
    monkeypatch.setattr(export_mod, "STL_TOLERANCE_MM", 0.5)  # far too coarse a tessellation
    monkeypatch.setattr(export_mod, "STL_ANGULAR_TOLERANCE_RAD", 0.8)
    with pytest.raises(BuildCheckError, match="volume matches CAD"):
        build_design(NEURO, out_root=out, progress=False, pictures_in_worker=False)
    assert _tree_digest(out / "neuro") == before
    assert sorted(p.name for p in out.iterdir()) == ["neuro"]


def test_invalid_spec_fails_before_cad_and_writes_nothing(tmp_path, monkeypatch):
    bad = tmp_path / "bad.yaml"
    bad.write_text(NEURO.read_text().replace("length: 50", "length: -5"))
    out = tmp_path / "exports"

    def no_cad(*args, **kwargs):
        raise AssertionError("CAD work started before validation")

    monkeypatch.setattr(ChicFamily, "parts", no_cad)
    with pytest.raises(SpecError, match="body.length"):
        build_design(bad, out_root=out, progress=False)
    assert not out.exists() or not any(out.iterdir())
    assert main(["build", str(bad), "--out", str(out), "--quiet"]) == 2


def test_skirts_that_would_meet_are_refused_even_with_force(tmp_path):
    bad = tmp_path / "long-skirt.yaml"
    bad.write_text(NEURO.read_text().replace("skirt_height: 4.0", "skirt_height: 30.0"))
    with pytest.raises(InfeasibleDesign, match="caps_meet .caps.skirt_height.") as err:
        build_design(bad, out_root=tmp_path / "exports", force=True, progress=False, pictures_in_worker=False)
    assert "--force cannot" in str(err.value)
    assert not (tmp_path / "exports" / "neuro").exists()
    assert not any((tmp_path / "exports").iterdir())


def test_replace_folder_swaps_and_cleans_up(tmp_path):
    final = tmp_path / "neuro"
    final.mkdir()
    (final / "old.txt").write_text("old")
    new = tmp_path / ".neuro.tmp-1"
    new.mkdir()
    (new / "new.txt").write_text("new")
    replace_folder(new, final)
    assert [p.name for p in final.iterdir()] == ["new.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["neuro"]


def test_replace_folder_restores_the_old_export_if_the_rename_fails(tmp_path, monkeypatch):
    final = tmp_path / "neuro"
    final.mkdir()
    (final / "old.txt").write_text("old")
    new = tmp_path / ".neuro.tmp-1"
    new.mkdir()
    real_rename = folders_mod.os.rename
    calls = []

    def flaky_rename(src, dst):
        calls.append((src, dst))
        if len(calls) == 2:
            raise OSError("disk full")
        return real_rename(src, dst)

    monkeypatch.setattr(folders_mod.os, "rename", flaky_rename)
    with pytest.raises(OSError, match="disk full"):
        replace_folder(new, final)
    assert (final / "old.txt").read_text() == "old"


def test_the_plate_lays_out_the_parts_and_its_toolpaths_keep_every_channel_open(built):
    """plate.3mf: the three parts, the top cap turned over, the design's settings; with prusa-slicer on the
    PATH the build sliced it and every channel and fill port stayed open at all 250 layers of 0.2 mm."""
    _, result, _ = built
    plate = read_plate(result.folder / "plate.3mf")
    assert [p.name for p in plate.placements] == ["body", "cap_top", "cap_bottom"]
    assert plate.placement("cap_top").T_bed_from_F[2, 2] == pytest.approx(-1.0)
    assert plate.config["layer_height"] == "0.2" and plate.info["ports"]["diameter_mm"] == 1.2
    if find_slicer() is None:
        assert "Not run: skipped: prusa-slicer is not on the PATH" in (result.folder / "report.md").read_text()
        return
    check = json.loads((result.folder / "printcheck.json").read_text())
    assert check["ok"] and check["layers"] == 250
    assert len(check["channels"]) == 9 + 9  # nine channels, nine fill ports
