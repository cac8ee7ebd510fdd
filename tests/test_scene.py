"""The tool frame, and the Slicer scene of a registration, loaded back with Slicer's MRML libraries."""

from __future__ import annotations

import json
import stat

import numpy as np
import pytest
import yaml

from chic_design.errors import SpecError
from chic_design.families import family_of
from chic_design.families.sections import ToolSpec
from chic_design.spec import parse_spec
from chic_register.cli.main import main
from chic_register.model.geometry import content_sha256, geometry_from_dict, load_geometry, write_geometry
from chic_register.model.pose import rigid, rot_y
from chic_register.imaging.simulate import simulate_slice, write_simulated
from chic_register.io.stl import stl_bytes, stl_header
from chic_register.io.transforms import LPS_TO_RAS, slicer_matrix

from .conftest import NEURO
from .test_slicer import needs_slicer, run_probe

TIP_MM = -60.0


@pytest.fixture(scope="module")
def tool_geometry(neuro_spec):
    spec = neuro_spec.model_copy(update={"tool": ToolSpec(tip_offset_mm=TIP_MM)})
    return family_of(spec).geometry(spec, source={"spec": "designs/neuro.yaml"})


def test_geometry_without_tool_keeps_its_hash_and_with_tool_covers_it(neuro_geometry, tool_geometry, tmp_path):
    plain = neuro_geometry.to_dict()
    assert "tool" not in plain  # files without the key: same content, same hash as before the tool existed
    with_tool = tool_geometry.to_dict()
    assert {k: v for k, v in with_tool.items() if k not in ("tool", "sha256")} == \
        {k: v for k, v in plain.items() if k != "sha256"}
    assert with_tool["tool"]["T_fiducial_from_tool"][2][3] == TIP_MM
    path = write_geometry(tool_geometry, tmp_path / "geometry.yaml")
    back = load_geometry(path)
    np.testing.assert_allclose(back.tool.tip_mm, [0.0, 0.0, TIP_MM])
    data = yaml.safe_load(path.read_text())
    data["tool"]["T_fiducial_from_tool"][2][3] = -50.0  # an edited tool is caught by the hash
    with pytest.raises(Exception, match="sha256 does not match"):
        geometry_from_dict(data, path)
    data["tool"]["T_fiducial_from_tool"][0][0] = 2.0
    data["sha256"] = content_sha256(data)
    with pytest.raises(Exception, match="rigid 4x4"):
        geometry_from_dict(data, path)


@pytest.mark.parametrize("tool, message", [
    ({}, "exactly one"),
    ({"tip_offset_mm": -60, "T_fiducial_from_tool": np.eye(4).tolist()}, "exactly one"),
    ({"T_fiducial_from_tool": (2 * np.eye(4)).tolist()}, "rigid 4x4"),
    ({"tip_offset_mm": -60, "colour": "red"}, "colour"),
])
def test_spec_tool_section_is_validated(tool, message):
    data = yaml.safe_load(NEURO.read_text())
    data["tool"] = tool
    with pytest.raises(SpecError, match=message):
        parse_spec(data, "neuro.yaml")


def test_full_tool_transform_from_the_spec(neuro_spec):
    T = rigid(rot_y(90.0), (1.0, 2.0, -40.0))
    data = yaml.safe_load(NEURO.read_text())
    data["tool"] = {"T_fiducial_from_tool": T.tolist()}
    spec = parse_spec(data, "neuro.yaml")
    geom = family_of(spec).geometry(spec)
    np.testing.assert_allclose(geom.tool.T_fiducial_from_tool, T)


@pytest.fixture(scope="module")
def solved_scene(tmp_path_factory, tool_geometry):
    """solve --scene on a noisy tilted slice with a tool, the JSON it printed and the truth."""
    import contextlib
    import io

    tmp = tmp_path_factory.mktemp("scene")
    gfile = write_geometry(tool_geometry, tmp / "geometry.yaml")
    # a body.stl beside the geometry file (as in an export folder), with a header that says nothing
    (tmp / "body.stl").write_bytes(stl_bytes([[15, 0, 0], [0, 15, 0], [0, 0, 50]], [[0, 1, 2]])
                                   .replace(stl_header(), b"STL Export by Lib3MF".ljust(80, b"\0"), 1))
    sim = simulate_slice(tool_geometry, 24.0, 12.0, 40.0, 25.0, noise="rician", snr=30.0, distractors=2, rng=7,
                         slice_thickness_mm=2.0, image_position=(-60.0, -75.0, 30.0))
    img, _ = write_simulated(sim, tmp / "slice.dcm")
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = main(["solve", str(img), "--geometry", str(gfile), "--json", "--scene", str(tmp / "scene")])
    assert rc == 0
    return tmp / "scene", json.loads(out.getvalue()), sim


def test_solve_reports_the_tool_pose_and_tip(solved_scene):
    _, doc, sim = solved_scene
    T = np.array(doc["T_scanner_from_fiducial"])
    T_tool = np.array(doc["T_scanner_from_tool"])
    np.testing.assert_allclose(T_tool, T @ rigid(np.eye(3), (0, 0, TIP_MM)), atol=1e-9)
    np.testing.assert_allclose(doc["tool_tip_mm"], (T @ [0, 0, TIP_MM, 1])[:3], atol=1e-9)
    true_tip = (sim.truth.T_scanner_from_fiducial @ [0, 0, TIP_MM, 1])[:3]
    assert np.linalg.norm(np.array(doc["tool_tip_mm"]) - true_tip) < 1.0  # 85 mm lever from the slice
    s = doc["slices"][0]
    assert len(s["candidates_rc"]) >= len(s["assignment"])  # what `assignment` indexes is printed
    assert all(0 <= i < len(s["candidates_rc"]) for i in s["assignment"].values())


def test_scene_files_and_permissions(solved_scene):
    folder, _, _ = solved_scene
    names = sorted(p.name for p in folder.iterdir())
    assert names == ["CHIC.tfm", "CHICTool.tfm", "body.stl", "detected.mrk.json", "predicted.mrk.json", "registration.json",
                     "scene.mrml", "slice_1.nrrd", "tool.stl", "tool_tip.mrk.json", "tubes.stl"]
    assert (folder / "tubes.stl").read_bytes().startswith(b"SPACE=LPS")
    assert (folder / "body.stl").read_bytes().startswith(b"SPACE=LPS")  # the copy says what Slicer assumes
    assert all(stat.S_IMODE(p.stat().st_mode) & 0o044 == 0o044 for p in folder.iterdir())  # not mkstemp's 0600


@needs_slicer
def test_scene_loads_in_slicer_with_the_right_nodes_hierarchy_and_positions(solved_scene, tool_geometry, tmp_path):
    folder, doc, sim = solved_scene
    got = run_probe(tmp_path, {"mode": "scene", "mrml": str(folder / "scene.mrml")})
    assert got["imported"]
    nodes = {n["name"]: n for n in got["nodes"]}
    assert {(n["name"], n["class"], n["parent"]) for n in got["nodes"]} == {
        ("CHIC", "vtkMRMLLinearTransformNode", None),
        ("CHICTool", "vtkMRMLLinearTransformNode", None),
        ("fiducial tubes", "vtkMRMLModelNode", "CHIC"),
        ("body", "vtkMRMLModelNode", "CHIC"),
        ("tool", "vtkMRMLModelNode", "CHICTool"),
        ("slice 1", "vtkMRMLScalarVolumeNode", None),
        ("detected", "vtkMRMLMarkupsFiducialNode", None),
        ("predicted", "vtkMRMLMarkupsFiducialNode", None),
        ("tool tip", "vtkMRMLMarkupsFiducialNode", None),
    }
    T = np.array(doc["T_scanner_from_fiducial"])
    np.testing.assert_allclose(nodes["CHIC"]["to_world"], slicer_matrix(T), atol=1e-9)
    assert nodes["fiducial tubes"]["n_points"] > 1000 and nodes["tool"]["n_points"] > 50
    # each predicted crossing, taken back through Slicer's own transform, lies on its tube's centreline
    M = np.array(nodes["CHIC"]["to_world"])
    residuals = doc["slices"][0]["residuals_mm"]
    pred = {p["label"]: np.array(p["ras"]) for p in nodes["predicted"]["points"]}
    det = {p["label"]: (np.array(p["ras"]), p["description"]) for p in nodes["detected"]["points"]}
    assert sorted(pred) == sorted(residuals)
    for tid, ras in pred.items():
        p_F = (LPS_TO_RAS @ np.linalg.inv(M) @ np.r_[ras, 1.0])[:3]
        tube = tool_geometry.tube(tid)
        on_tube = tube.point_at_z(p_F[2]).reshape(3)
        assert np.linalg.norm(p_F - on_tube) < 0.01, tid
        ras_det, text = det[tid]
        # the blob centre and the model's crossing agree to a fraction of a pixel (the solver's own residual,
        # in the description, may be measured from refined positions rather than the blob centre)
        assert np.linalg.norm(ras_det - ras) < 0.05
        assert f"residual {residuals[tid]:.4f} mm" in text
    assert any(label.startswith("extra") for label in det)  # the rejected distractor blobs are shown too
    tip = nodes["tool tip"]["points"][0]["ras"]
    np.testing.assert_allclose(tip, LPS_TO_RAS[:3, :3] @ doc["tool_tip_mm"], atol=1e-6)
    # the slice volume sits where the image is: pixel (0, 0) at the image origin
    vol = nodes["slice 1"]
    assert vol["dimensions"] == [256, 256, 1]
    np.testing.assert_allclose(np.array(vol["ijk_to_ras"])[:3, 3], [60.0, 75.0, 30.0], atol=1e-4)
    assert vol["sum"] == pytest.approx(float(np.sum(sim.slice.pixels.astype(np.float32), dtype=float)), rel=1e-5)


def test_scene_refuses_to_replace_a_foreign_folder(solved_scene, tool_geometry, tmp_path):
    from chic_register.errors import OutputError
    from chic_register.outputs.scene import write_scene

    folder, _, _ = solved_scene
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("x")
    with pytest.raises(OutputError, match="not an earlier scene"):
        write_scene(tmp_path / "mine", None, tool_geometry, [])
    assert (tmp_path / "mine" / "thesis.tex").read_text() == "x"
