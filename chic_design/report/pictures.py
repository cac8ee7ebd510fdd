"""The build's pictures: an off-screen 3-D preview after the paper's Fig. 1, the tilt plot and the precision map.

The preview shows the body's envelope (the annulus ``inner..outer diameter``,
``z = 0..length``) semi-transparent, and each channel as a coloured tube of
its diameter along its centreline (red: diametric, blue: helices, green:
orientation), labelled with its id (straight tubes at the top, helices at the bottom). It is drawn from the
geometry objects alone, so it can be rendered in a separate process while the
CAD model is built (:func:`preview_job`); this module does not import the
CAD kernel.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from chic_design.feasibility.tilt_plot import save_tilt_plot
from chic_register.model.geometry import FiducialGeometry
from chic_register.util.atomic import write_text

ROLE_COLOURS = {"diametric": "red", "helix": "blue", "orientation": "green", "other": "orange",
                "axial": "red", "diagonal": "blue"}


def render_preview(geometry: FiducialGeometry, png_path, window_size: tuple[int, int] = (1000, 800)) -> Path:
    """Render the fiducial to ``png_path`` off-screen (temporary file, then rename)."""
    import pyvista as pv  # VTK: loaded only by the process that draws (the build's worker)
    import vtk

    vtk.vtkObject.GlobalWarningDisplayOff()  # no "bad X server connection" noise off-screen
    png_path = Path(png_path)
    b = geometry.body
    h = b.outer_half_mm
    if h is not None:  # a square (Z-frame) or rectangular (N-localizer) frame: its outside box
        body = pv.Box((-h[0], h[0], -h[1], h[1], 0.0, b.length))
        (ox, oy), (ix, iy) = 2 * h, 2 * b.inner_half_mm
        size = (f"L {b.length:g}, outside {ox:g}, bore {ix:g} mm" if b.shape == "square" else
                f"L {b.length:g}, outside {ox:g} x {oy:g}, bore {ix:g} x {iy:g} mm")
        legend = "red: axial rods  blue: diagonal rods" + ("  orange: edge rods" if geometry.by_role("other") else "")
    else:
        body = pv.Disc(inner=b.inner_diameter / 2, outer=b.outer_diameter / 2, r_res=1, c_res=120)
        body = body.extrude((0.0, 0.0, b.length), capping=True)
        size = f"L {b.length:g}, OD {b.outer_diameter:g}, ID {b.inner_diameter:g} mm"
        legend = "red: diametric  blue: helix  green: orientation"

    plotter = pv.Plotter(off_screen=True, window_size=list(window_size))
    plotter.set_background("white")
    plotter.add_mesh(body, color="lightgrey", opacity=0.25)
    labels, label_pts = [], []
    for tube in geometry.tubes:
        pts = tube.points(np.linspace(0.0, 1.0, 120))
        plotter.add_mesh(pv.lines_from_points(pts).tube(radius=tube.diameter / 2, n_sides=16, capping=True),
                         color=ROLE_COLOURS.get(tube.role, "orange"))
        labels.append(tube.id)
        # straight tubes labelled above their top end, helices below their bottom end:
        # a helix ends next to a diametric tube, and the two labels would overlap
        if tube.curved:
            label_pts.append(pts[np.argmin(pts[:, 2])] - np.array([0.0, 0.0, 3.0]))
        elif tube.role == "diagonal" or np.ptp(pts[:, 2]) < 1e-9:  # ends on other rods: label the middle
            label_pts.append(pts[len(pts) // 2])
        else:
            label_pts.append(pts[np.argmax(pts[:, 2])] + np.array([0.0, 0.0, 2.0]))
    plotter.add_point_labels(np.array(label_pts), labels, font_size=18, point_size=1,
                             shape_opacity=0.6, always_visible=True)
    plotter.add_text(
        f"{geometry.name}: {size}\n{legend}",
        font_size=12, color="black",
    )
    plotter.add_axes()
    plotter.camera_position = "iso"
    plotter.camera.elevation = 10
    tmp = png_path.with_name(f".{png_path.stem}.tmp{os.getpid()}.png")
    try:
        plotter.screenshot(str(tmp))
        os.replace(tmp, png_path)
    finally:
        plotter.close()
        tmp.unlink(missing_ok=True)
    return png_path


def preview_job(geometry: FiducialGeometry, folder) -> float:
    """Write ``folder/preview.png``; returns the wall time (s). Runs in the build's worker process."""
    t0 = time.perf_counter()
    render_preview(geometry, Path(folder) / "preview.png")
    return time.perf_counter() - t0


def tilt_plot_job(feasibility_report, folder) -> float:
    """Write ``folder/tilt_limits.png`` (the feasibility plot); returns the wall time (s)."""
    t0 = time.perf_counter()
    save_tilt_plot(feasibility_report, Path(folder) / "tilt_limits.png")
    return time.perf_counter() - t0


def precision_job(geometry: FiducialGeometry, pixel_size_mm: float, slice_thickness_mm: float, folder) -> float:
    """Write ``folder/precision.png`` and ``folder/precision.md`` (the report's precision section); returns the wall time (s)."""
    from chic_register.precision.report import design_precision, plot_map, report_section  # by the drawing worker

    t0 = time.perf_counter()
    pm = design_precision(geometry, pixel_size_mm, slice_thickness_mm)
    if pm is not None:
        plot_map(pm, Path(folder) / "precision.png", title=geometry.name)
    write_text(Path(folder) / "precision.md", report_section(pm, "precision.png" if pm is not None else None))
    return time.perf_counter() - t0
