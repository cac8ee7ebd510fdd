"""Render a scene written by ``chic-register solve --scene DIR`` off-screen, as 3D Slicer would show it.

    .venv/bin/python docs/render_scene.py DIR/scene.mrml docs/img/slicer-scene.png

Reads the scene's own files the way Slicer does (models declared
``SPACE=LPS``, placed by their parent transform's ``.tfm``; volumes and
markups in LPS; everything shown in RAS) and draws them with pyvista: the
slice, the fiducial body (translucent) and tube channels, the tool, the
detected (yellow) and predicted (cyan) tube centres and the tool tip. It is
a picture of the scene's content for the README, not a replacement for
opening ``scene.mrml`` in Slicer.
"""

from __future__ import annotations

import json
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pyvista as pv
import SimpleITK as sitk

from chic_register.io.transforms import LPS_TO_RAS, read_tfm, slicer_matrix


def _refs(el) -> dict:
    return dict(r.split(":", 1) for r in (el.get("references") or "").split(";") if r)


def render(mrml: Path, png: Path) -> None:
    folder = mrml.parent
    nodes = {el.get("id"): el for el in ET.parse(mrml).getroot()}
    file_of = {nid: folder / el.get("fileName") for nid, el in nodes.items() if el.get("fileName")}
    to_parent = {nid: slicer_matrix(read_tfm(file_of[_refs(el)["storage"]]))
                 for nid, el in nodes.items() if el.tag == "LinearTransform"}
    pv.OFF_SCREEN = True
    plotter = pv.Plotter(off_screen=True, window_size=(1000, 800))
    plotter.set_background("#1b1b2f")
    for el in nodes.values():
        refs = _refs(el)
        if el.tag == "Model":
            mesh = pv.read(file_of[refs["storage"]])
            mesh.points = mesh.points * np.array([-1.0, -1.0, 1.0])  # SPACE=LPS -> Slicer's RAS
            if "transform" in refs:
                mesh = mesh.transform(to_parent[refs["transform"]], inplace=False)
            disp = nodes[refs["display"]]
            color = [float(v) for v in disp.get("color", "1 1 1").split()]
            plotter.add_mesh(mesh, color=color, opacity=float(disp.get("opacity", 1.0)), smooth_shading=True)
        elif el.tag == "Volume":
            img = sitk.ReadImage(str(file_of[refs["storage"]]))
            arr = sitk.GetArrayFromImage(img)[0].astype(float)
            rows, cols = np.mgrid[0:arr.shape[0], 0:arr.shape[1]]
            idx = np.stack([cols.ravel(), rows.ravel(), np.zeros(rows.size)], axis=1)
            lps = np.array([img.TransformContinuousIndexToPhysicalPoint(tuple(p)) for p in idx])
            ras = lps * np.array([-1.0, -1.0, 1.0])
            grid = pv.StructuredGrid(*(ras[:, k].reshape(arr.shape) for k in range(3)))
            grid["signal"] = arr.ravel()
            plotter.add_mesh(grid, scalars="signal", cmap="gray", show_scalar_bar=False, opacity=0.9)
        elif el.tag == "MarkupsFiducial":
            doc = json.loads(file_of[refs["storage"]].read_text())
            pts = doc["markups"][0]["controlPoints"]
            color = doc["markups"][0]["display"]["color"]
            xyz = np.array([p["position"] for p in pts]) @ LPS_TO_RAS[:3, :3]
            plotter.add_points(xyz, color=color, point_size=12, render_points_as_spheres=True)
    plotter.add_axes(xlabel="R", ylabel="A", zlabel="S")
    plotter.camera_position = "iso"
    plotter.camera.azimuth = 35
    plotter.camera.elevation = 10
    plotter.reset_camera()
    plotter.camera.zoom(1.5)
    plotter.screenshot(str(png))
    plotter.close()


if __name__ == "__main__":
    render(Path(sys.argv[1]), Path(sys.argv[2]))
