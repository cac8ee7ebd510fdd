"""Full build of designs/zframe.yaml: printable parts, geometry.yaml and the output checks."""

import json

import numpy as np
import pytest
import trimesh

from chic_design.build.pipeline import build_design
from chic_design.families import FAMILIES
from chic_design.spec import load_spec
from chic_design.verify import section_loops, verify_export
from chic_register.model.geometry import load_geometry
from tests.conftest import ZFRAME

pytestmark = pytest.mark.slow

ZF = FAMILIES["zframe"]


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    out = tmp_path_factory.mktemp("exports")
    return out, build_design(ZFRAME, out_root=out, progress=False)


def test_zframe_builds_with_every_output_check_passing(built):
    _, result = built
    assert result.checks.ok
    names = [c.name for c in result.checks.checks]
    for part in ("body", "cap_top", "cap_bottom"):
        assert f"{part}.stl watertight" in names and f"{part}.3mf volume matches CAD" in names
    assert "cap_top does not overlap body (mesh)" in names
    # five sections, each: outer wall and bore + one hole per rod
    assert len(result.checks.section_heights_mm) == 5
    rods = [n for n in names if n.startswith("body.stl section") and not n.endswith("bore")]
    assert len(rods) == 5 * 7
    assert {p.name for p in result.folder.iterdir()} >= {"geometry.yaml", "report.md", "feasibility.json",
                                                         "assembly.step", "preview.png", "tilt_limits.png"}


def test_geometry_file_is_the_spec_layout(built):
    _, result = built
    geom = load_geometry(result.folder / "geometry.yaml")
    assert geom.family == "zframe"
    assert geom.tubes == ZF.geometry(load_spec(ZFRAME)).tubes
    feas = json.loads((result.folder / "feasibility.json").read_text())
    assert feas["feasible"] and feas["unambiguity"]["unambiguous"] is False
    report = (result.folder / "report.md").read_text()
    assert report.startswith("# Z-frame fiducial `zframe`") and "| rod diameter | 3 mm |" in report


def test_body_section_holes_sit_on_the_rods(built):
    """Independent of verify: a section at z = 20 mm has the frame, the bore and seven holes on the rods."""
    _, result = built
    mesh = trimesh.load_mesh(result.folder / "body.stl")
    geom = load_geometry(result.folder / "geometry.yaml")
    loops = sorted(section_loops(mesh, 20.0), key=lambda l: -l[0])
    assert len(loops) == 2 + 7
    assert loops[0][0] == pytest.approx(67.0**2, rel=1e-3) and loops[1][0] == pytest.approx(53.0**2, rel=1e-3)
    holes = np.array([c for _, c in loops[2:]])
    for tube in geom.tubes:
        want = tube.point_at_z(20.0)[0, :2]
        assert np.min(np.linalg.norm(holes - want, axis=1)) < 0.02, tube.id
    # the top cap has one fill port per distinct opening: 4 corners (each diagonal ends at one)
    cap = trimesh.load_mesh(result.folder / "cap_top.stl")
    plate = section_loops(cap, 61.0)
    assert len(plate) == 2 + 4


def test_verify_catches_a_rod_moved_in_geometry_yaml(built, tmp_path):
    """The output checks compare the meshes with geometry.yaml: a rod moved by 0.2 mm fails them."""
    import shutil

    import yaml

    from chic_register.model.geometry import content_sha256

    _, result = built
    folder = tmp_path / "copy"
    shutil.copytree(result.folder, folder)
    data = yaml.safe_load((folder / "geometry.yaml").read_text())
    data["tubes"][0]["p0"][0] += 0.2
    data["tubes"][0]["p1"][0] += 0.2
    data["sha256"] = content_sha256(data)
    (folder / "geometry.yaml").write_text(yaml.safe_dump(data))
    spec = load_spec(ZFRAME)
    parts = ZF.parts(spec, ZF.geometry(spec))
    volumes = {name: float(p.volume) for name, p in parts.items()}
    res = verify_export(folder, volumes, raise_on_failure=False)
    failed = {c.name for c in res.failed}
    assert failed and all("A0" in n for n in failed), failed
