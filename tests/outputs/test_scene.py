"""The Slicer scene of a registration (solve --scene), loaded back with Slicer's MRML libraries, and its picture."""

from __future__ import annotations

import importlib.util
import json
import stat
from pathlib import Path

import numpy as np
import pytest

from chic_register.cli.main import main
from chic_register.imaging.simulate import simulate_slice, write_simulated
from chic_register.io.stl import stl_bytes, stl_header
from chic_register.io.transforms import LPS_TO_RAS, slicer_matrix
from chic_register.model.geometry import write_geometry
from chic_register.model.pose import rigid
from tests.conftest import TOOL_TIP_MM as TIP_MM
from tests.test_slicer import needs_slicer, run_probe


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


def _render_scene_module():
    """docs/render_scene.py, the script that draws the README's picture of the scene."""
    path = Path(__file__).resolve().parents[2] / "docs" / "render_scene.py"
    spec = importlib.util.spec_from_file_location("render_scene", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_scene_picture_grid_puts_every_detected_centre_on_its_blob(solved_scene):
    """The slice as the picture draws it: each detected point (matched tubes and rejected blobs) lies on the grid
    at a bright pixel, the very pixel of its blob centre (a transposed grid puts them on background)."""
    import SimpleITK as sitk

    folder, doc, sim = solved_scene
    rs = _render_scene_module()
    grid = rs.slice_grid(folder / "slice_1.nrrd")
    img = sitk.ReadImage(str(folder / "slice_1.nrrd"))
    pixels = sitk.GetArrayFromImage(img)[0]  # the slice as the scene holds it (as read from the DICOM file)
    assert grid.dimensions == (pixels.shape[1], pixels.shape[0], 1)
    for i, j in ((0, 0), (17, 201), (255, 3)):  # the grid's geometry is the volume's (LPS -> RAS)
        k = grid.find_closest_point(np.array(img.TransformIndexToPhysicalPoint((i, j, 0))) * [-1, -1, 1])
        np.testing.assert_allclose(grid.points[k], np.array(img.TransformIndexToPhysicalPoint((i, j, 0))) * [-1, -1, 1],
                                   atol=1e-4)
        assert grid["signal"][k] == pixels[j, i]
    xyz, labels, _ = rs.markup_points(folder / "detected.mrk.json")
    s = doc["slices"][0]
    candidates = np.array(s["candidates_rc"])
    index = {**{tid: b for tid, b in s["assignment"].items()}, **{f"extra{b}": b for b in range(len(candidates))}}
    bright = np.percentile(pixels, 99.0)
    assert len(labels) == len(candidates) and any(t.startswith("extra") for t in labels)
    for p, label in zip(xyz, labels):
        k = grid.find_closest_point(p)
        assert np.linalg.norm(grid.points[k] - p) < 0.5 * np.hypot(*sim.slice.pixel_spacing_mm), label
        r, c = np.rint(candidates[index[label]]).astype(int)
        assert grid["signal"][k] == pytest.approx(pixels[r, c]), label  # the pixel of that blob's centre ...
        assert grid["signal"][k] > 0.4 * bright, label  # ... a bright one


def test_scene_picture_renders_off_screen(solved_scene, tmp_path):
    rs = _render_scene_module()
    png = tmp_path / "scene.png"
    rs.render(solved_scene[0] / "scene.mrml", png)
    from PIL import Image

    with Image.open(png) as im:
        assert im.size == (1000, 800)
        rgb = np.asarray(im.convert("RGB")).reshape(-1, 3).astype(int)
    yellow = (rgb[:, 0] > 150) & (rgb[:, 1] > 150) & (rgb[:, 2] < 100)  # the detected centres
    red = (rgb[:, 0] > 150) & (rgb[:, 1] < 100) & (rgb[:, 2] < 100)  # the tube channels
    assert yellow.sum() > 50 and red.sum() > 1000
