"""A 3D Slicer scene of one registration: ``solve --scene DIR`` writes ``DIR/scene.mrml`` and its files.

What the scene holds (node names as Slicer shows them):

- ``CHIC``: linear transform, ``CHIC.tfm`` (the registration, as ``--tfm``);
- ``fiducial tubes``: the tube channels of ``geometry.yaml`` drawn in F
  (``tubes.stl``, ``SPACE=LPS``), under ``CHIC``; ``body``: the printed body
  (``body.stl`` from beside the geometry file, when it is there), under ``CHIC``;
- ``slice 1`` ...: each registered slice as a one-plane volume (``slice_1.nrrd``,
  LPS geometry of the image);
- ``detected``: every candidate blob centre (``detected.mrk.json``), labelled
  with its tube id and residual, or ``extra`` when the solver rejected it;
  ``predicted``: the model's crossing of every matched tube with its slice
  (the residual is the solver's: when it refines on fitted section positions
  it can differ a little from the distance between the two markups);
- with a tool frame: ``CHICTool`` (``CHICTool.tfm``), the ``tool`` model
  (``tool.stl``, a 1 mm shaft from the tip) under it, and ``tool tip``.

The frames follow docs/interfaces.md section 5, so the models land on the
fiducial in the image. Written into a temporary folder beside ``DIR`` and
renamed: a failure leaves an earlier scene untouched.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from chic_register.errors import OutputError
from chic_register.io.stl import declare_space, write_stl
from chic_register.io.transforms import write_tfm
from chic_register.model.tubes import sample_centreline
from chic_register.util.atomic import atomic_path, check_parent, write_json

SCENE_FILE = "scene.mrml"
MARKUPS_SCHEMA = ("https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/Markups/"
                  "Resources/Schema/markups-schema-v1.0.3.json#")
TOOL_SHAFT_DIAMETER_MM = 1.0


def _tube_mesh(geom, sides: int = 12):
    """Vertices and triangles of every tube channel (diameter as in the geometry), frame F."""
    import pyvista as pv  # deferred: loads pyvista only when used (one-shot start-up)

    meshes = []
    for tube in geom.tubes:
        line = pv.lines_from_points(sample_centreline(tube, 1.0))
        meshes.append(line.tube(radius=tube.diameter / 2, n_sides=sides, capping=True).triangulate())
    return _merge(meshes)


def _tool_mesh(geom):
    """A shaft along the tool's z axis from the tip to past the far end of the body, and a tip sphere (tool frame)."""
    import pyvista as pv  # deferred: loads pyvista only when used (one-shot start-up)

    T_tool_from_F = np.linalg.inv(geom.tool.T_fiducial_from_tool)
    ends_z = [(T_tool_from_F @ [0.0, 0.0, z, 1.0])[2] for z in (0.0, geom.body.length)]
    far = max(ends_z, key=abs)
    far = far if abs(far) >= 10.0 else (10.0 if far >= 0 else -10.0)
    shaft = pv.Cylinder(center=(0, 0, far / 2), direction=(0, 0, 1), radius=TOOL_SHAFT_DIAMETER_MM / 2,
                        height=abs(far), resolution=16).triangulate()
    tip = pv.Sphere(radius=TOOL_SHAFT_DIAMETER_MM, center=(0, 0, 0)).triangulate()
    return _merge([shaft, tip])


def _merge(meshes):
    verts, tris, base = [], [], 0
    for m in meshes:
        verts.append(np.asarray(m.points, dtype=float))
        tris.append(m.faces.reshape(-1, 4)[:, 1:] + base)
        base += m.n_points
    return np.vstack(verts), np.vstack(tris)


def _write_slice_volume(sl, path: Path) -> None:
    """One slice as a one-plane NRRD volume with its LPS geometry (SimpleITK writes ``space: LPS``)."""
    img = sitk.GetImageFromArray(np.asarray(sl.pixels, dtype=np.float32)[None])
    thickness = sl.slice_thickness_mm if sl.slice_thickness_mm > 0 else 1.0
    img.SetSpacing((float(sl.pixel_spacing_mm[1]), float(sl.pixel_spacing_mm[0]), float(thickness)))
    img.SetOrigin(tuple(float(v) for v in sl.origin_mm))
    img.SetDirection(tuple(np.column_stack([sl.col_dir, sl.row_dir, sl.normal]).ravel().tolist()))
    with atomic_path(path) as tmp:
        sitk.WriteImage(img, str(tmp), True)


def _point(label: str, position, description: str = "") -> dict:
    return {"id": label, "label": label, "description": description, "position": [float(v) for v in position],
            "positionStatus": "defined", "locked": True, "visibility": True}


def _markups(points: list[dict], color) -> dict:
    return {"@schema": MARKUPS_SCHEMA,
            "markups": [{"type": "Fiducial", "coordinateSystem": "LPS", "coordinateUnits": "mm", "locked": True,
                         "labelFormat": "%N-%d", "controlPoints": points,
                         "display": {"color": list(color), "selectedColor": list(color), "glyphScale": 2.0,
                                     "textScale": 2.0, "pointLabelsVisibility": True}}]}


def scene_points(reg, slices) -> tuple[list[dict], list[dict]]:
    """Markup points (scanner LPS, mm) of the detected candidates and of the model's predicted crossings."""
    detected, predicted = [], []
    many = len(slices) > 1
    for j, (sl, res) in enumerate(zip(slices, reg.slices)):
        pre = f"s{j + 1}:" if many else ""
        rc = np.asarray(res.blobs_rc if res.blobs_rc is not None else np.zeros((0, 2)), dtype=float).reshape(-1, 2)
        tube_of = {int(b): t for t, b in res.assignment.items()}
        for b in range(rc.shape[0]):
            p = sl.pixel_to_scanner(rc[b, 0], rc[b, 1])[0]
            tid = tube_of.get(b)
            if tid is None:
                detected.append(_point(f"{pre}extra{b}", p, "candidate blob not matched to a tube"))
            else:
                r = res.residuals_mm.get(tid, float("nan"))
                detected.append(_point(f"{pre}{tid}", p, f"detected centre of {tid}; residual {r:.4f} mm"))
        for tid, (r_px, c_px) in (res.predicted_rc or {}).items():
            if tid not in res.assignment:
                continue
            p = sl.pixel_to_scanner(r_px, c_px)[0]
            r = res.residuals_mm.get(tid, float("nan"))
            predicted.append(_point(f"{pre}{tid}", p, f"model crossing of {tid}; residual {r:.4f} mm"))
    return detected, predicted


class _Mrml:
    """Builds the scene XML (node tags and references as Slicer 5 writes them)."""

    def __init__(self):
        self.root = ET.Element("MRML", version="Slicer4.4.0", userTags="")
        self.counts: dict[str, int] = {}

    def node(self, tag: str, cls: str, **attrs) -> str:
        self.counts[cls] = self.counts.get(cls, 0) + 1
        nid = f"vtkMRML{cls}{self.counts[cls]}"
        refs = attrs.pop("references", None)
        el = ET.SubElement(self.root, tag, id=nid, **{k: str(v) for k, v in attrs.items()})
        if refs:
            el.set("references", "".join(f"{role}:{ref};" for role, ref in refs.items() if ref))
        return nid

    def storage(self, tag: str, cls: str, file_name: str, **attrs) -> str:
        return self.node(tag, cls, name=f"{tag}", fileName=file_name, **attrs)

    def transform(self, name: str, file_name: str) -> str:
        st = self.storage("TransformStorage", "TransformStorageNode", file_name)
        return self.node("LinearTransform", "LinearTransformNode", name=name, references={"storage": st})

    def model(self, name: str, file_name: str, transform: str | None, color, opacity: float = 1.0) -> str:
        disp = self.node("ModelDisplay", "ModelDisplayNode", name="ModelDisplay", color=" ".join(map(str, color)),
                         opacity=opacity, visibility="true", visibility2D="true", sliceIntersectionVisibility="true")
        st = self.storage("ModelStorage", "ModelStorageNode", file_name, coordinateSystem="LPS")
        return self.node("Model", "ModelNode", name=name,
                         references={"display": disp, "storage": st, "transform": transform})

    def volume(self, name: str, file_name: str) -> str:
        disp = self.node("VolumeDisplay", "ScalarVolumeDisplayNode", name="VolumeDisplay", autoWindowLevel="1",
                         references={"colorNodeID": "vtkMRMLColorTableNodeGrey"})
        st = self.storage("VolumeArchetypeStorage", "VolumeArchetypeStorageNode", file_name)
        return self.node("Volume", "ScalarVolumeNode", name=name, references={"display": disp, "storage": st})

    def markups(self, name: str, file_name: str, color) -> str:
        disp = self.node("MarkupsFiducialDisplay", "MarkupsFiducialDisplayNode", name="MarkupsFiducialDisplay",
                         color=" ".join(map(str, color)), selectedColor=" ".join(map(str, color)))
        st = self.storage("MarkupsJsonStorage", "MarkupsJsonStorageNode", file_name, coordinateSystem="LPS")
        return self.node("MarkupsFiducial", "MarkupsFiducialNode", name=name,
                         references={"display": disp, "storage": st})

    def text(self) -> str:
        ET.indent(self.root)
        return ET.tostring(self.root, encoding="unicode", xml_declaration=True) + "\n"


def _fill(folder: Path, reg, geom, slices, name: str, geometry_path) -> None:
    mrml = _Mrml()
    T = np.asarray(reg.T_scanner_from_fiducial, dtype=float)
    write_tfm(T, folder / f"{name}.tfm")
    tf = mrml.transform(name, f"{name}.tfm")
    v, t = _tube_mesh(geom)
    write_stl(folder / "tubes.stl", v, t)
    mrml.model("fiducial tubes", "tubes.stl", tf, (1.0, 0.2, 0.2))
    body = Path(geometry_path).parent / "body.stl" if geometry_path else None
    if body is not None and body.is_file():
        shutil.copyfile(body, folder / "body.stl")
        declare_space(folder / "body.stl")
        mrml.model("body", "body.stl", tf, (0.9, 0.9, 0.8), opacity=0.3)
    for j, sl in enumerate(slices):
        _write_slice_volume(sl, folder / f"slice_{j + 1}.nrrd")
        mrml.volume(f"slice {j + 1}", f"slice_{j + 1}.nrrd")
    detected, predicted = scene_points(reg, slices)
    write_json(folder / "detected.mrk.json", _markups(detected, (1.0, 1.0, 0.0)))
    mrml.markups("detected", "detected.mrk.json", (1.0, 1.0, 0.0))
    write_json(folder / "predicted.mrk.json", _markups(predicted, (0.0, 0.8, 1.0)))
    mrml.markups("predicted", "predicted.mrk.json", (0.0, 0.8, 1.0))
    if geom.tool is not None:
        T_tool = T @ geom.tool.T_fiducial_from_tool
        write_tfm(T_tool, folder / f"{name}Tool.tfm")
        tt = mrml.transform(f"{name}Tool", f"{name}Tool.tfm")
        v, t = _tool_mesh(geom)
        write_stl(folder / "tool.stl", v, t)
        mrml.model("tool", "tool.stl", tt, (0.2, 1.0, 0.2))
        write_json(folder / "tool_tip.mrk.json", _markups([_point("tip", T_tool[:3, 3], "tool tip")], (0.2, 1.0, 0.2)))
        mrml.markups("tool tip", "tool_tip.mrk.json", (0.2, 1.0, 0.2))
    (folder / SCENE_FILE).write_text(mrml.text(), encoding="utf-8")
    (folder / "registration.json").write_text(json.dumps(reg.to_dict(), indent=2) + "\n", encoding="utf-8")


def _new_folder(parent: Path, prefix: str) -> Path:
    """A new, uniquely named folder in ``parent`` with the permissions of the umask (as ``mkdir`` gives)."""
    while True:
        path = parent / f"{prefix}{secrets.token_hex(4)}"
        try:
            path.mkdir()  # mode 0o777 less the umask, unlike mkdtemp's private 0o700
            return path
        except FileExistsError:
            continue


def write_scene(folder, reg, geom, slices, *, name: str = "CHIC", geometry_path=None) -> Path:
    """Write the scene of ``reg`` (a Registration of ``slices`` with ``geom``) into ``folder``; returns the .mrml.

    ``folder``'s parent must exist; ``folder`` itself is created, or replaced
    when it holds an earlier scene (a ``scene.mrml``); any other existing
    non-empty folder is refused (:class:`OutputError`), never overwritten.
    """
    folder = check_parent(Path(folder))
    if folder.exists() and (not folder.is_dir() or (any(folder.iterdir()) and not (folder / SCENE_FILE).is_file())):
        raise OutputError(f"{folder}: exists and is not an earlier scene (no {SCENE_FILE}); "
                          "give a new folder name")
    tmp = _new_folder(folder.parent, f".{folder.name}.tmp-")
    try:
        _fill(tmp, reg, geom, slices, name, geometry_path)
        old = None
        if folder.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{folder.name}.old-", dir=folder.parent))
            os.replace(folder, old / folder.name)
        os.replace(tmp, folder)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return folder / SCENE_FILE
