"""The print stage of an export folder: write ``plate.3mf`` for a build, and check it with the slicer.

:func:`write_print_plate` lays the folder's STL parts on the bed with the
settings of :mod:`.settings`. :func:`run_printcheck` slices that plate with
PrusaSlicer, reads the toolpaths back and checks every channel
(:mod:`.check`), then writes ``printcheck.json``, ``printcheck.png`` (the
worst layer, channels drawn over the toolpaths) and ``printcheck.md``.
Everything it needs is in the export folder: ``geometry.yaml`` and ``plate.3mf``.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from chic_design.cad.channels import fill_ports_xy
from chic_design.errors import PrintFileError
from chic_design.printing.check import (
    CheckedChannel,
    PrintCheck,
    check_channels,
    check_channels_raster,
    nominal_section,
    paths_near,
    port_channels,
)
from chic_design.printing.plate import Plate, make_plate, read_plate, write_plate
from chic_design.printing.settings import print_settings
from chic_design.printing.sla_layers import SlaStack, read_sla_layers
from chic_design.printing.slicer import find_slicer, slice_plate, slicer_version
from chic_design.printing.toolpaths import read_toolpaths
from chic_register.errors import InputFileError
from chic_register.model.geometry import FiducialGeometry, content_sha256, load_geometry
from chic_register.util.atomic import save_figure, write_json, write_text

PLATE_NAME = "plate.3mf"
#: The files :func:`run_printcheck` writes into the export folder.
PRINTCHECK_FILES = ("printcheck.json", "printcheck.png", "printcheck.md")
PARTS = ("body", "cap_top", "cap_bottom")


def _load_meshes(folder: Path) -> tuple[dict, dict]:
    import trimesh  # the mesh reader: loaded only when a plate is written

    meshes, faces = {}, {}
    for name in PARTS:
        mesh = trimesh.load(folder / f"{name}.stl", force="mesh")
        meshes[name], faces[name] = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    return meshes, faces


def write_print_plate(folder, spec, geometry: FiducialGeometry, cap_dims) -> Plate:
    """Write ``folder/plate.3mf`` from the folder's STL parts, for ``spec``'s printer; returns the plate."""
    folder = Path(folder)
    meshes, faces = _load_meshes(folder)
    length = geometry.body.length
    info = {
        "design": geometry.name, "geometry_sha256": content_sha256(geometry.content()),
        "ports": {"diameter_mm": cap_dims.port_diameter if cap_dims.port_diameter > 0 else 0.0,
                  "z_mm": [length, length + cap_dims.thickness],
                  "xy_mm": [[float(x), float(y)] for x, y in fill_ports_xy(geometry)]
                  if cap_dims.port_diameter > 0 else []},
    }
    plate = make_plate(meshes, geometry, print_settings(spec, geometry), info)
    write_plate(folder / PLATE_NAME, plate, meshes, faces, geometry.name)
    return plate


def checked_channels(geometry: FiducialGeometry, plate: Plate) -> tuple[CheckedChannel, ...]:
    """The body's channels and the top cap's fill ports, as the plate's information lists them."""
    body = tuple(CheckedChannel(t.id, "body", t) for t in geometry.tubes)
    ports = plate.info.get("ports", {})
    if not ports.get("xy_mm") or not ports.get("diameter_mm"):
        return body
    z0, z1 = ports["z_mm"]
    return body + port_channels(ports["xy_mm"], float(ports["diameter_mm"]), float(z0), float(z1 - z0))


def load_export(folder) -> tuple[FiducialGeometry, Plate]:
    """The geometry and plate of an export folder; refuses a plate laid out for another geometry."""
    folder = Path(folder)
    if not folder.is_dir():
        raise PrintFileError(f"{folder}: no such export folder; give the folder chic-design build wrote "
                             "(e.g. exports/neuro)")
    try:
        geometry = load_geometry(folder / "geometry.yaml")
    except InputFileError as exc:
        raise PrintFileError(str(exc)) from None
    plate = read_plate(folder / PLATE_NAME)
    if plate.info.get("geometry_sha256") != content_sha256(geometry.content()):
        raise PrintFileError(f"{folder / PLATE_NAME}: laid out for another geometry.yaml than the one beside it; "
                             "rebuild the design")
    return geometry, plate


def scan_calibration(path) -> dict:
    """The calibration record of a geometry file written by ``chic-register calibrate`` (its ``source.calibration``)."""
    try:
        geometry = load_geometry(path)
    except InputFileError as exc:
        raise PrintFileError(str(exc)) from None
    record = (geometry.source or {}).get("calibration")
    if not isinstance(record, dict) or "factor" not in record:
        raise PrintFileError(f"{path}: no calibration in its source; give the geometry file chic-register "
                             "calibrate wrote")
    return {**record, "file": str(path)}


def run_printcheck(folder, exe: str | None = None, progress=None, calibration=None, out=None) -> PrintCheck:
    """Slice ``folder/plate.3mf``, check every channel in the toolpaths and write the check's files
    (into ``out``, default ``folder``).

    ``progress`` (optional) is called with a short text at each step; ``calibration``
    (a geometry file from ``chic-register calibrate`` of a scan of this print) is
    compared with the toolpaths' scale in the report. Raises
    :class:`~chic_design.errors.SlicerError` when PrusaSlicer is missing or fails.
    """
    folder = Path(folder)
    geometry, plate = load_export(folder)
    scan = scan_calibration(calibration) if calibration is not None else None
    resin = plate.info.get("printer") == "resin"
    exe = exe or find_slicer()
    say = progress or (lambda _text: None)
    placements = {p.name: p for p in plate.placements}
    channels = checked_channels(geometry, plate)
    with tempfile.TemporaryDirectory(prefix="chic-printcheck-") as tmp:
        say("slicing plate.3mf with prusa-slicer")
        sliced = slice_plate(folder / PLATE_NAME, Path(tmp) / ("plate.sl1" if resin else "plate.gcode"), exe=exe,
                             sla=resin)
        say("reading the layer images" if resin else "reading the toolpaths")
        layers = read_sla_layers(sliced) if resin else read_toolpaths(sliced)
    version = slicer_version(exe) if exe else ""
    if resin:
        say(f"checking {len(channels)} channels in {len(layers.z_top_mm)} layers")
        result = check_channels_raster(channels, placements, layers, float(plate.info["layer_mm"]), slicer=version)
    else:
        say(f"checking {len(channels)} channels in {len(layers)} layers")
        result = check_channels(channels, placements, layers, float(plate.info["extrusion_width_mm"]),
                                float(plate.info["layer_mm"]), nozzle_mm=float(plate.info.get("nozzle_mm", 0.0)),
                                slicer=version)
    out = folder if out is None else Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "printcheck.json", {**result.to_dict(), **({"scan_calibration": scan} if scan else {})})
    draw_worst_layer(result, channels, placements, layers, out / "printcheck.png")
    write_text(out / "printcheck.md", printcheck_markdown(result, plate, scan))
    return result


def draw_worst_layer(result: PrintCheck, channels, placements, layers, png_path) -> Path:
    """The worst channel's worst layer: the toolpaths of its part (grey; ``layers`` a tuple of
    :class:`~chic_design.printing.toolpaths.Layer`) or the cured resin (``layers`` a
    :class:`~chic_design.printing.sla_layers.SlaStack`), every channel's nominal section
    (green: passes, red: fails) and its opening, labelled with its clear width."""
    import matplotlib  # the plotting library: loaded only by the process that draws

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after choosing the off-screen backend
    import shapely
    from matplotlib.patches import PathPatch
    from matplotlib.path import Path as MplPath

    worst = result.worst()
    resin = isinstance(layers, SlaStack)
    if resin:
        k = int(np.argmin(np.abs(layers.z_top_mm - worst.worst_z_mm)))
        z_top, z_mid = float(layers.z_top_mm[k]), float(layers.z_top_mm[k] - layers.height_mm[k] / 2)
    else:
        layer = min(layers, key=lambda lay: abs(lay.z_mm - worst.worst_z_mm))
        z_top, z_mid = layer.z_mm, layer.mid_z_mm
    place = placements[worst.part]
    ok = {c.id: c.ok for c in result.channels}
    sections = []
    for ch in channels:
        if ch.part != worst.part:
            continue
        z_f = float((z_mid - place.T_bed_from_F[2, 3]) / place.T_bed_from_F[2, 2])
        lo, hi = ch.tube.z_range
        if lo < z_f < hi:
            sec, centre = nominal_section(ch, place, z_f)
            if sec is not None:
                sections.append((ch.id, sec, centre))
    if not sections:
        raise PrintFileError("no channel section at the worst layer to draw")
    x0 = min(s.bounds[0] for _, s, _ in sections)
    y0 = min(s.bounds[1] for _, s, _ in sections)
    x1 = max(s.bounds[2] for _, s, _ in sections)
    y1 = max(s.bounds[3] for _, s, _ in sections)
    pad = 4.0
    paths = None if resin else paths_near(layer, (x0 - pad, y0 - pad, x1 + pad, y1 + pad), 0.0)

    def patch(geom, **kw):
        verts, codes = [], []
        for poly in getattr(geom, "geoms", [geom]):
            if poly.is_empty or poly.geom_type != "Polygon":
                continue
            for ring in (poly.exterior, *poly.interiors):
                xy = np.asarray(ring.coords)
                verts += list(xy)
                codes += [MplPath.MOVETO] + [MplPath.LINETO] * (len(xy) - 2) + [MplPath.CLOSEPOLY]
        return PathPatch(MplPath(verts, codes), **kw) if verts else None

    fig, ax = plt.subplots(figsize=(8, 8))
    if resin:  # the cured pixels of the layer, grey
        img = layers.masks[k]
        ax.imshow(np.where(img, 0.75, 1.0), cmap="gray", vmin=0, vmax=1, origin="upper", interpolation="nearest",
                  extent=(layers.x0_mm - layers.dx_mm / 2, layers.x0_mm + (img.shape[1] - 0.5) * layers.dx_mm,
                          layers.y0_mm + (img.shape[0] - 0.5) * layers.dy_mm, layers.y0_mm - layers.dy_mm / 2))
    else:
        p = patch(shapely.clip_by_rect(paths, x0 - pad, y0 - pad, x1 + pad, y1 + pad), facecolor="0.75",
                  edgecolor="0.45", linewidth=0.3)
        if p is not None:
            ax.add_patch(p)
    measure = {c.id: c for c in result.channels}
    for cid, sec, centre in sections:
        colour = "tab:green" if ok[cid] else "tab:red"
        ax.add_patch(patch(sec, facecolor="none", edgecolor=colour, linewidth=1.5))
        opening = sec.difference(paths) if paths is not None else shapely.Polygon()
        if not opening.is_empty:
            q = patch(opening, facecolor=colour, alpha=0.25, edgecolor="none")
            if q is not None:
                ax.add_patch(q)
        c = measure[cid]
        ax.annotate(f"{cid}\n{c.min_clear_mm:.2f}/{c.diameter_mm:g} mm", centre, fontsize=7, ha="center",
                    va="center", color="black")
    ax.set_xlim(x0 - pad, x1 + pad)
    ax.set_ylim(y0 - pad, y1 + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("bed x (mm)")
    ax.set_ylabel("bed y (mm)")
    verdict = "all channels open" if result.ok else f"{len(result.failures)} channel(s) fail"
    what = ("grey: cured resin; outline: nominal section" if resin else
            "grey: toolpaths at their bead width; outline: nominal section; fill: what stays open")
    ax.set_title(f"{worst.part}, layer z = {z_top:g} mm (worst: {worst.id}); {verdict}\n"
                 f"{what}; labels: least clear width / diameter", fontsize=8)
    return save_figure(fig, png_path)


def scale_text(result: PrintCheck, scan: dict | None) -> str:
    """The toolpaths' scale about the axis, and beside it a scan's calibration factor when one is given."""
    text = (f"Channel centres in the toolpaths sit at {result.toolpath_scale:.5f} (SD {result.toolpath_scale_sd:.5f}) "
            "x their nominal distance from the axis. ")
    if scan is None:
        return text + ("Once the print is scanned, `chic-register calibrate` measures its scale in the scanner; "
                       "`chic-design printcheck EXPORT --calibration G2` puts the two side by side.")
    diff = float(scan["factor"]) / result.toolpath_scale - 1.0
    return text + (f"The scan's calibration (`{scan['file']}`) measured {float(scan['factor']):.5f} "
                   f"(SD {float(scan.get('factor_sd', float('nan'))):.5f}): the print and the scanner together "
                   f"scale it by {diff:+.2%} beyond the toolpaths (the printer's shrink or growth times the "
                   "scanner's gradient calibration).")


def printcheck_markdown(result: PrintCheck, plate: Plate, scan: dict | None = None) -> str:
    """The print check's section of the report: settings, per-channel verdicts and the measured print error."""
    info = plate.info
    lim = result.limits
    lines = [
        "## Print check (toolpaths)",
        "",
        f"`plate.3mf` sliced by {result.slicer or 'PrusaSlicer'} with its own settings ({result.layers} layers of "
        f"{result.layer_mm:g} mm, {result.extrusion_width_mm:g} mm beads); each channel's section was compared with "
        "the toolpaths at every layer it crosses. A channel passes when its clear width stays at least "
        f"{lim['min_clear_share']:g} x its diameter and {lim['min_clear_nozzle_share']:g} x the "
        f"{result.nozzle_mm:g} mm nozzle, its open area at least {lim['min_open_share']:.0%} of nominal, "
        f"and its layers ({lim['overhang_percentile']:g}th percentile) overhang its opening by at most "
        f"{lim['max_overhang_share']:g} x the bead width. "
        "Result: " + ("**every channel is open.**" if result.ok else f"**failed**: {result.failure_text()}."),
        "",
        "| channel | part | diameter (mm) | layers | least clear width (mm) | at z (mm) | least open area "
        "| opening offset, mean x, y (mm) | largest offset (mm) | overhang, 90th pct. of layers (mm) | verdict |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for c in result.channels:
        lines.append(
            f"| {c.id} | {c.part} | {c.diameter_mm:g} | {c.layers} | {c.min_clear_mm:.3f} | {c.worst_z_mm:g} "
            f"| {c.min_open_share:.0%} | {c.mean_offset_mm[0]:+.3f}, {c.mean_offset_mm[1]:+.3f} "
            f"| {c.max_offset_mm:.3f} | {c.overhang_mm:.3f} | {'ok' if c.ok else '; '.join(c.problems)} |")
    lines += [
        "",
        "The offsets are the print's error as the toolpaths make it (frame F): the opening's centre minus the "
        "channel's centreline. " + scale_text(result, scan),
        "",
        "The worst layer, channels over the toolpaths: [printcheck.png](printcheck.png).",
        "",
        "![worst layer](printcheck.png)",
        "",
        "Settings in `plate.3mf`: " + "; ".join(f"{k}: {v}" for k, v in info.get("reasons", {}).items()) + ".",
        "",
    ]
    return "\n".join(lines)
