"""An off-screen picture of the fiducial, after the paper's Fig. 1.

Semi-transparent body with each channel drawn as a coloured tube along its
centreline (red: diametric, blue: helices, green: orientation), each labelled
with its id at its top end.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from chic_register.geometry import FiducialGeometry

ROLE_COLOURS = {"diametric": "red", "helix": "blue", "orientation": "green", "other": "orange"}


def _centreline_polydata(tube, n: int = 200):
    import pyvista as pv

    pts = tube.points(np.linspace(0.0, 1.0, n))
    return pv.lines_from_points(pts)


def render_preview(geometry: FiducialGeometry, body_vertices, body_faces, png_path,
                   window_size: tuple[int, int] = (1000, 800)) -> Path:
    """Render the body mesh and the channel centrelines to ``png_path`` (off-screen).

    Args:
        geometry: tube centrelines (frame F).
        body_vertices: body mesh vertices, shape (V, 3), mm.
        body_faces: body mesh triangles, shape (F, 3), vertex indices.
        png_path: output picture; written via a temporary file, then renamed.
    """
    import pyvista as pv
    import vtk

    vtk.vtkObject.GlobalWarningDisplayOff()  # no "bad X server connection" noise off-screen
    png_path = Path(png_path)
    faces = np.asarray(body_faces, dtype=np.int64)
    cells = np.hstack([np.full((len(faces), 1), 3, dtype=np.int64), faces]).ravel()
    body = pv.PolyData(np.asarray(body_vertices, dtype=float), cells)

    plotter = pv.Plotter(off_screen=True, window_size=list(window_size))
    plotter.set_background("white")
    plotter.add_mesh(body, color="lightgrey", opacity=0.25)
    labels, label_pts = [], []
    for tube in geometry.tubes:
        line = _centreline_polydata(tube)
        plotter.add_mesh(line.tube(radius=tube.diameter / 2, n_sides=16, capping=True),
                         color=ROLE_COLOURS.get(tube.role, "orange"), smooth_shading=True)
        top = tube.points([1.0])[0] if tube.points([1.0])[0, 2] >= tube.points([0.0])[0, 2] else tube.points([0.0])[0]
        labels.append(tube.id)
        label_pts.append(top + np.array([0.0, 0.0, 2.0]))
    plotter.add_point_labels(np.array(label_pts), labels, font_size=18, point_size=1,
                             shape_opacity=0.6, always_visible=True)
    b = geometry.body
    plotter.add_text(
        f"{geometry.name}: L {b.length:g}, OD {b.outer_diameter:g}, ID {b.inner_diameter:g} mm\n"
        "red: diametric  blue: helix  green: orientation",
        font_size=12, color="black",
    )
    plotter.add_axes()
    plotter.camera_position = "iso"
    plotter.camera.elevation = 10
    plotter.camera.zoom(1.3)
    tmp = png_path.with_name(f".{png_path.stem}.tmp{os.getpid()}.png")
    try:
        plotter.screenshot(str(tmp))
        os.replace(tmp, png_path)
    finally:
        plotter.close()
        tmp.unlink(missing_ok=True)
    return png_path
