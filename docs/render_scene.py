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

RAS_FROM_LPS = np.array([-1.0, -1.0, 1.0])


def _refs(el) -> dict:
    return dict(r.split(":", 1) for r in (el.get("references") or "").split(";") if r)


def slice_grid(nrrd_path) -> pv.StructuredGrid:
    """A one-plane volume as a grid in RAS with its pixel values as point scalars ``signal``.

    Points and scalars are both laid out in pyvista's order (the first grid
    axis fastest): the grid's axes are (column i, row j), so point (i, j)
    holds pixel ``[j, i]``, where the volume puts it.
    """
    img = sitk.ReadImage(str(nrrd_path))
    arr = sitk.GetArrayFromImage(img)[0].astype(float)  # (rows j, columns i)
    cols, rows = np.meshgrid(np.arange(arr.shape[1]), np.arange(arr.shape[0]), indexing="ij")  # (i, j) arrays
    origin = np.array(img.GetOrigin())
    D = np.array(img.GetDirection()).reshape(3, 3) * np.array(img.GetSpacing())  # index (i, j, k) -> LPS offset
    lps = origin + cols[..., None] * D[:, 0] + rows[..., None] * D[:, 1]
    ras = lps * RAS_FROM_LPS
    grid = pv.StructuredGrid(ras[..., 0], ras[..., 1], ras[..., 2])
    grid["signal"] = arr.T.ravel(order="F")  # arr.T[i, j] = pixel (row j, column i), first axis fastest
    return grid


def markup_points(path) -> tuple[np.ndarray, list[str], list]:
    """(positions in RAS (n, 3), labels, display colour) of a ``.mrk.json`` point list (LPS)."""
    doc = json.loads(Path(path).read_text())
    markups = doc["markups"][0]
    pts = markups["controlPoints"]
    xyz = np.array([p["position"] for p in pts], dtype=float).reshape(-1, 3) @ LPS_TO_RAS[:3, :3]
    return xyz, [p["label"] for p in pts], markups["display"]["color"]


def render(mrml: Path, png: Path) -> None:
    """Draw every model, volume and point list of ``mrml`` off-screen into ``png``."""
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
            mesh.points = mesh.points * RAS_FROM_LPS  # SPACE=LPS -> Slicer's RAS
            if "transform" in refs:
                mesh = mesh.transform(to_parent[refs["transform"]], inplace=False)
            disp = nodes[refs["display"]]
            color = [float(v) for v in disp.get("color", "1 1 1").split()]
            plotter.add_mesh(mesh, color=color, opacity=float(disp.get("opacity", 1.0)), smooth_shading=True)
        elif el.tag == "Volume":
            grid = slice_grid(file_of[refs["storage"]])
            plotter.add_mesh(grid, scalars="signal", cmap="gray", show_scalar_bar=False, opacity=0.9)
        elif el.tag == "MarkupsFiducial":
            xyz, _, color = markup_points(file_of[refs["storage"]])
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
