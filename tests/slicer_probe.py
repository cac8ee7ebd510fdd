"""Read our outputs with 3D Slicer's own MRML libraries (``slicer-core``) and report what Slicer sees, as JSON.

Runs in the separate environment that has ``slicer-core`` (it pins its own
vtk), started by the tests as ``PYTHON tests/slicer_probe.py REQUEST.json``:

- ``{"mode": "model", "stl": S, "tfm": F, "matrices": {name: 4x4}}``: the
  STL read by vtkMRMLModelStorageNode, placed under the .tfm read by
  vtkMRMLTransformStorageNode and under a transform node of each matrix (as
  an OpenIGTLink TRANSFORM creates); prints the model's vertices in RAS
  (world) for each, after Slicer hardens the transform.
- ``{"mode": "scene", "mrml": M}``: the scene imported into a vtkMRMLScene;
  prints every node with its class, name, parent transform, its world
  matrix, markup points (RAS) and volume geometry.
- ``{"mode": "markups", "files": [F, ...]}``: each point file (``.mrk.json``
  by vtkMRMLMarkupsJsonStorageNode, ``.fcsv`` by
  vtkMRMLMarkupsFiducialStorageNode) read into a fiducial node; prints its
  points (label, description, position in RAS) per file.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import slicer
import vtk


def _new_scene():
    scene = slicer.vtkMRMLScene()
    for cls in ("vtkMRMLMarkupsFiducialNode", "vtkMRMLMarkupsFiducialDisplayNode", "vtkMRMLMarkupsJsonStorageNode"):
        if scene.GetClassNameByTag(getattr(slicer, cls)().GetNodeTagName()) is None:
            scene.RegisterNodeClass(getattr(slicer, cls)())
    return scene


def _matrix(vtk_matrix) -> list:
    return [[vtk_matrix.GetElement(i, j) for j in range(4)] for i in range(4)]


def _world_points(node) -> list:
    """The model's vertices in world RAS, hardening the transform the way Slicer's Transforms module does."""
    logic = slicer.vtkSlicerTransformLogic()
    if node.GetParentTransformNode() is not None:
        assert logic.hardenTransform(node), "hardenTransform failed"
    pts = node.GetPolyData().GetPoints()
    return [list(pts.GetPoint(i)) for i in range(pts.GetNumberOfPoints())]


def _load_model(scene, path):
    model = scene.AddNewNodeByClass("vtkMRMLModelNode")
    storage = scene.AddNewNodeByClass("vtkMRMLModelStorageNode")
    storage.SetFileName(path)
    assert storage.ReadData(model), f"ModelStorageNode cannot read {path}"
    model.SetAndObserveStorageNodeID(storage.GetID())
    return model


def probe_model(req: dict) -> dict:
    out = {}
    scene = _new_scene()
    model = _load_model(scene, req["stl"])
    out["local"] = _world_points(model)
    if req.get("tfm"):
        scene = _new_scene()
        model = _load_model(scene, req["stl"])
        tnode = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode")
        storage = scene.AddNewNodeByClass("vtkMRMLTransformStorageNode")
        storage.SetFileName(req["tfm"])
        assert storage.ReadData(tnode), f"TransformStorageNode cannot read {req['tfm']}"
        m = vtk.vtkMatrix4x4()
        tnode.GetMatrixTransformToParent(m)
        out["tfm_to_parent"] = _matrix(m)
        model.SetAndObserveTransformNodeID(tnode.GetID())
        out["tfm"] = _world_points(model)
    for name, M in (req.get("matrices") or {}).items():
        scene = _new_scene()
        model = _load_model(scene, req["stl"])
        tnode = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", name)
        vm = vtk.vtkMatrix4x4()
        for i in range(4):
            for j in range(4):
                vm.SetElement(i, j, float(M[i][j]))
        tnode.SetMatrixTransformToParent(vm)
        model.SetAndObserveTransformNodeID(tnode.GetID())
        out[name] = _world_points(model)
    return out


def probe_scene(req: dict) -> dict:
    scene = _new_scene()
    scene.SetURL(req["mrml"])
    ok = scene.Import()
    nodes = []
    for i in range(scene.GetNumberOfNodes()):
        n = scene.GetNthNode(i)
        if not isinstance(n, (slicer.vtkMRMLTransformableNode,)):
            continue
        parent = n.GetParentTransformNode() if hasattr(n, "GetParentTransformNode") else None
        d = {"class": n.GetClassName(), "name": n.GetName(), "parent": parent.GetName() if parent else None}
        if isinstance(n, slicer.vtkMRMLTransformNode):
            m = vtk.vtkMatrix4x4()
            n.GetMatrixTransformToWorld(m)
            d["to_world"] = _matrix(m)
        if isinstance(n, slicer.vtkMRMLStorableNode) and n.GetStorageNode() is not None:
            d["file"] = n.GetStorageNode().GetFileName()
        if isinstance(n, slicer.vtkMRMLModelNode):
            pd = n.GetPolyData()
            d["n_points"] = pd.GetNumberOfPoints() if pd is not None else 0
        if isinstance(n, slicer.vtkMRMLMarkupsNode):
            pts = []
            for k in range(n.GetNumberOfControlPoints()):
                p = [0.0, 0.0, 0.0]
                n.GetNthControlPointPositionWorld(k, p)
                pts.append({"label": n.GetNthControlPointLabel(k),
                            "description": n.GetNthControlPointDescription(k), "ras": p})
            d["points"] = pts
        if isinstance(n, slicer.vtkMRMLScalarVolumeNode):
            m = vtk.vtkMatrix4x4()
            n.GetIJKToRASMatrix(m)
            d["ijk_to_ras"] = _matrix(m)
            img = n.GetImageData()
            d["dimensions"] = list(img.GetDimensions()) if img is not None else None
            if img is not None:
                from vtk.util.numpy_support import vtk_to_numpy

                arr = vtk_to_numpy(img.GetPointData().GetScalars())
                d["sum"] = float(np.sum(arr, dtype=float))
        nodes.append(d)
    return {"imported": bool(ok), "nodes": nodes}


def probe_markups(req: dict) -> dict:
    out = {}
    for path in req["files"]:
        scene = _new_scene()
        if path.endswith(".fcsv") and scene.GetClassNameByTag("MarkupsFiducialStorage") is None:
            scene.RegisterNodeClass(slicer.vtkMRMLMarkupsFiducialStorageNode())
        node = scene.AddNewNodeByClass("vtkMRMLMarkupsFiducialNode")
        cls = "vtkMRMLMarkupsFiducialStorageNode" if path.endswith(".fcsv") else "vtkMRMLMarkupsJsonStorageNode"
        storage = scene.AddNewNodeByClass(cls)
        storage.SetFileName(path)
        assert storage.ReadData(node), f"{cls} cannot read {path}"
        pts = []
        for k in range(node.GetNumberOfControlPoints()):
            p = [0.0, 0.0, 0.0]
            node.GetNthControlPointPosition(k, p)
            pts.append({"label": node.GetNthControlPointLabel(k),
                        "description": node.GetNthControlPointDescription(k), "ras": p})
        out[path] = pts
    return out


def main(argv) -> int:
    with open(argv[1], encoding="utf-8") as f:
        req = json.load(f)
    probes = {"model": probe_model, "scene": probe_scene, "markups": probe_markups}
    result = probes[req["mode"]](req)
    print("PROBE-JSON " + json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
