"""The print check: every channel's cross-section, at every layer of the sliced plate, against ``geometry.yaml``.

For each layer the extrusion paths near a channel are drawn at their spacing
(round-capped segments, :mod:`shapely`; :func:`bead_width_mm`), and the channel's nominal section in
that layer's cutting plane (an ellipse for an inclined channel, from its tube
object) is compared with what the paths leave open:

- ``open_share``: open area / nominal area;
- ``clear_mm``: the widest circle that fits in the opening (what a fill needle
  or the fluid passes), compared with the channel's diameter;
- ``offset_mm``: the opening's centroid minus the nominal centre, in frame F
  (the print's error as the solver would see it);
- ``overhang_mm``: how far this layer's paths reach over the opening of the
  layer below (printed over air); a channel is judged on its
  :data:`~chic_design.printing.limits.OVERHANG_PERCENTILE` th percentile over its layers.

A channel fails when it is closed or narrowed beyond the limits of
:mod:`chic_design.printing.limits` (of its diameter, of the nozzle, of its area), or
when its layers overhang it by more than a share of the extrusion width (its roof
then sags into it).
The top cap's fill ports are checked the same way as the body's channels.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field

import numpy as np
import shapely

from chic_design.printing.limits import (
    MAX_OVERHANG_SHARE,
    MIN_CLEAR_NOZZLE_SHARE,
    MIN_CLEAR_SHARE,
    MIN_OPEN_SHARE,
    MIN_WALL_SHARE,
    OVERHANG_PERCENTILE,
    WALL_RING_MM,
)
from chic_design.printing.plate import Placement
from chic_design.printing.toolpaths import KIND_CODE, Layer
from chic_register.model.tubes import LineTube, Tube

#: Vertices of a nominal section's outline.
SECTION_VERTICES = 72
#: Channels closer to horizontal than this (|tangent z|) have no layer section to judge.
MIN_TANGENT_Z = 0.05
#: Extrusion kinds that are not part of the object (drawn on the bed around it).
NOT_OBJECT = (KIND_CODE["Skirt/Brim"], KIND_CODE["Custom"])


@dataclass(frozen=True)
class CheckedChannel:
    """A channel to check: its tube in the frame F of the part it runs through."""

    id: str
    part: str
    tube: Tube

    @property
    def diameter_mm(self) -> float:
        return self.tube.diameter


def port_channels(ports_xy, port_diameter_mm: float, z0_mm: float, thickness_mm: float) -> tuple[CheckedChannel, ...]:
    """The top cap's fill ports as vertical channels through its plate (``z0_mm`` .. ``z0_mm + thickness_mm`` in F)."""
    return tuple(CheckedChannel(f"port{k}", "cap_top",
                                LineTube(f"port{k}", "port", (x, y, z0_mm), (x, y, z0_mm + thickness_mm),
                                         port_diameter_mm))
                 for k, (x, y) in enumerate(ports_xy, start=1))


@dataclass(frozen=True)
class LayerMeasure:
    """One channel in one layer: bed height (mm), open share, clear width (mm), offset (mm, F x, y), overhang (mm),
    and the nominal centre (mm, F x, y) the offset is from."""

    z_mm: float
    open_share: float
    clear_mm: float
    offset_mm: tuple[float, float]
    overhang_mm: float
    centre_mm: tuple[float, float] = (0.0, 0.0)
    wall_share: float = 1.0


@dataclass(frozen=True)
class ChannelResult:
    """A channel's verdict over all its layers: the worst layer and the limits it was held to."""

    id: str
    part: str
    diameter_mm: float
    layers: int
    worst_z_mm: float
    min_clear_mm: float
    min_open_share: float
    max_offset_mm: float
    mean_offset_mm: tuple[float, float]
    overhang_mm: float
    overhang_z_mm: float
    ok: bool
    problems: tuple[str, ...] = ()
    wall_share: float = 1.0

    @property
    def clear_share(self) -> float:
        return self.min_clear_mm / self.diameter_mm


@dataclass(frozen=True)
class PrintCheck:
    """The print check of one plate: per channel results, the limits, the slicer and the worst layer."""

    channels: tuple[ChannelResult, ...]
    extrusion_width_mm: float
    layer_mm: float
    slicer: str
    layers: int
    nozzle_mm: float = 0.0
    toolpath_scale: float = float("nan")
    toolpath_scale_sd: float = float("nan")
    limits: dict = field(default_factory=lambda: {
        "min_clear_share": MIN_CLEAR_SHARE, "min_clear_nozzle_share": MIN_CLEAR_NOZZLE_SHARE,
        "min_open_share": MIN_OPEN_SHARE, "max_overhang_share": MAX_OVERHANG_SHARE,
        "overhang_percentile": OVERHANG_PERCENTILE})

    @property
    def ok(self) -> bool:
        return all(c.ok for c in self.channels)

    @property
    def failures(self) -> tuple[ChannelResult, ...]:
        return tuple(c for c in self.channels if not c.ok)

    def worst(self) -> ChannelResult:
        """The channel with the smallest clear width for its diameter (a failing one first)."""
        return min(self.channels, key=lambda c: (c.ok, c.clear_share))

    def failure_text(self) -> str:
        """One line per failing channel: its name, the worst layer and what is wrong."""
        return "; ".join(f"{c.id} ({c.part}): {', '.join(c.problems)}" for c in self.failures)

    def to_dict(self) -> dict:
        return {"ok": self.ok, "slicer": self.slicer, "layers": self.layers, "layer_mm": self.layer_mm,
                "nozzle_mm": self.nozzle_mm, "toolpath_scale": self.toolpath_scale,
                "toolpath_scale_sd": self.toolpath_scale_sd,
                "extrusion_width_mm": self.extrusion_width_mm, "limits": self.limits,
                "channels": [asdict(c) for c in self.channels]}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)


def _plane_to_f(placement: Placement, z_bed_mm: float) -> float | None:
    """Height in the part's F of the bed plane ``z_bed_mm``, or None if the part is tilted on the bed."""
    R, t = placement.T_bed_from_F[:3, :3], placement.T_bed_from_F[:3, 3]
    if not np.allclose(R[2, :2], 0.0, atol=1e-9) or not np.allclose(R[:2, 2], 0.0, atol=1e-9):
        return None
    return float((z_bed_mm - t[2]) / R[2, 2])


def nominal_section(channel: CheckedChannel, placement: Placement, z_f_mm: float):
    """The channel's section by the plane z = ``z_f_mm`` of F, as a shapely polygon in bed x, y (mm), and its centre.

    Locally the centreline is its tangent line, so the section is an ellipse:
    semi-axis ``a / |t_z|`` along the tangent's horizontal direction, ``a`` across it.
    """
    c = channel.tube.point_at_z(z_f_mm)[0]
    u = channel.tube.tangents_at_z(z_f_mm)[0]
    a = channel.diameter_mm / 2
    uz = abs(u[2])
    if uz < MIN_TANGENT_Z:
        return None, None
    h = np.hypot(u[0], u[1])
    along = u[:2] / h if h > 1e-12 else np.array([1.0, 0.0])
    across = np.array([-along[1], along[0]])
    phi = np.linspace(0.0, 2 * np.pi, SECTION_VERTICES, endpoint=False)
    pts_f = c[:2] + np.outer(np.cos(phi) * a / uz, along) + np.outer(np.sin(phi) * a, across)
    R, t = placement.T_bed_from_F[:3, :3], placement.T_bed_from_F[:3, 3]
    to_bed = pts_f @ R[:2, :2].T + t[:2]
    centre = c[:2] @ R[:2, :2].T + t[:2]
    return shapely.Polygon(to_bed), centre


def bead_width_mm(width_mm, height_mm: float):
    """The width a bead covers as the slicer spaces it: ``w - h (1 - pi/4)`` (PrusaSlicer's ``Flow::spacing``).

    The slicer models a bead as a rectangle with round sides and places the
    outer edge of this flat width on the part's outline; drawing the full
    ``;WIDTH:`` would narrow every opening by ``h (1 - pi/4)``.
    """
    return np.asarray(width_mm, dtype=float) - height_mm * (1.0 - np.pi / 4)


def paths_near(layer: Layer, bounds, margin_mm: float):
    """The union of the layer's object extrusions (round-capped, :func:`bead_width_mm`) within ``bounds`` + margin."""
    s = layer.segments_mm
    x0, y0, x1, y1 = bounds
    m = margin_mm
    keep = ((np.maximum(s[:, 0], s[:, 2]) >= x0 - m) & (np.minimum(s[:, 0], s[:, 2]) <= x1 + m)
            & (np.maximum(s[:, 1], s[:, 3]) >= y0 - m) & (np.minimum(s[:, 1], s[:, 3]) <= y1 + m)
            & ~np.isin(layer.kind, NOT_OBJECT))
    if not keep.any():
        return shapely.Polygon()
    lines = shapely.linestrings(s[keep].reshape(-1, 2, 2))
    return shapely.union_all(shapely.buffer(lines, bead_width_mm(layer.width_mm[keep], layer.height_mm) / 2,
                                            quad_segs=4))


def inscribed_width_mm(region) -> float:
    """Diameter (mm) of the largest circle inside ``region`` (0 for an empty one)."""
    if region.is_empty or region.area <= 0:
        return 0.0
    parts = getattr(region, "geoms", [region])
    best = 0.0
    for p in parts:
        if p.area > 0:
            best = max(best, shapely.maximum_inscribed_circle(p, 0.005).length)
    return 2.0 * best


def measure_channel(channel: CheckedChannel, placement: Placement, layers, extrusion_width_mm: float):
    """:class:`LayerMeasure` of ``channel`` at every layer whose cutting plane lies inside its part."""
    lo, hi = channel.tube.z_range
    out: list[LayerMeasure] = []
    R = placement.T_bed_from_F[:3, :3]
    previous_open = None
    for layer in layers:
        z_f = _plane_to_f(placement, layer.mid_z_mm)
        if z_f is None or not (lo < z_f < hi):
            previous_open = None
            continue
        section, centre = nominal_section(channel, placement, z_f)
        if section is None:
            previous_open = None
            continue
        paths = paths_near(layer, section.bounds, 2 * extrusion_width_mm)
        opening = section.difference(paths) if not paths.is_empty else section
        ring = section.buffer(WALL_RING_MM).difference(section)
        wall = ring.intersection(paths).area / ring.area if not paths.is_empty else 0.0
        share = opening.area / section.area
        clear = inscribed_width_mm(opening)
        if opening.area > 0:
            c = np.array(opening.centroid.coords[0])
            offset = tuple(float(v) for v in R[:2, :2].T @ (c - centre))
        else:
            offset = (float("nan"), float("nan"))
        overhang = 0.0
        if previous_open is not None and not paths.is_empty:
            overhang = inscribed_width_mm(paths.intersection(previous_open))
        c_f = channel.tube.point_at_z(z_f)[0, :2]
        out.append(LayerMeasure(layer.z_mm, float(share), float(clear), offset, float(overhang),
                                (float(c_f[0]), float(c_f[1])), float(wall)))
        previous_open = opening
    return out


def judge(channel: CheckedChannel, measures, max_overhang_mm: float | None, nozzle_mm: float = 0.0) -> ChannelResult:
    """The verdict on one channel from its layer measures (``max_overhang_mm``: None where nothing sags, as in a
    resin print; ``nozzle_mm``: the FDM nozzle, 0 for none)."""
    d = channel.diameter_mm
    if not measures:
        return ChannelResult(channel.id, channel.part, d, 0, float("nan"), float("nan"), float("nan"), float("nan"),
                             (float("nan"), float("nan")), float("nan"), float("nan"), False,
                             ("no layer of the sliced plate cuts it (the part is missing from the toolpaths)",))
    clear = np.array([m.clear_mm for m in measures])
    share = np.array([m.open_share for m in measures])
    offs = np.array([m.offset_mm for m in measures])
    over = np.array([m.overhang_mm for m in measures])
    k = int(np.argmin(clear))
    over_typical = float(np.percentile(over, OVERHANG_PERCENTILE))
    j = int(np.argmin(np.abs(over - over_typical)))
    finite = np.all(np.isfinite(offs), axis=1)
    max_off = float(np.max(np.hypot(offs[finite, 0], offs[finite, 1]))) if finite.any() else float("nan")
    mean_off = tuple(float(v) for v in offs[finite].mean(axis=0)) if finite.any() else (float("nan"),) * 2
    problems = []
    if clear[k] <= 0.0 or share.min() <= 0.01:
        problems.append(f"closed at layer z = {measures[k].z_mm:g} mm")
    else:
        if clear[k] < MIN_CLEAR_SHARE * d:
            problems.append(f"narrowed to {clear[k]:.2f} mm clear (< {MIN_CLEAR_SHARE:g} x {d:g} mm) at layer "
                            f"z = {measures[k].z_mm:g} mm")
        elif clear[k] < MIN_CLEAR_NOZZLE_SHARE * nozzle_mm:
            problems.append(f"narrower than the {nozzle_mm:g} mm nozzle ({clear[k]:.2f} mm clear) at layer "
                            f"z = {measures[k].z_mm:g} mm: the nozzle's face closes it")
        if share.min() < MIN_OPEN_SHARE:
            i = int(np.argmin(share))
            problems.append(f"open area {share[i]:.0%} of nominal (< {MIN_OPEN_SHARE:.0%}) at layer "
                            f"z = {measures[i].z_mm:g} mm")
    wall = float(np.median([m.wall_share for m in measures]))
    if wall < MIN_WALL_SHARE:
        problems.append(f"not walled in: material covers {wall:.0%} of a {WALL_RING_MM:g} mm ring round it (median "
                        "over its layers): the part is not where the plate places it, or its walls are missing")
    if max_overhang_mm is not None and over_typical > max_overhang_mm:
        problems.append(f"overhang of {over_typical:.2f} mm over its opening (> {MAX_OVERHANG_SHARE:g} x the "
                        f"{max_overhang_mm / MAX_OVERHANG_SHARE:g} mm extrusion) at layer z = {measures[j].z_mm:g} mm: "
                        "its roof sags")
    return ChannelResult(channel.id, channel.part, d, len(measures), measures[k].z_mm, float(clear[k]),
                         float(share.min()), max_off, mean_off, over_typical, measures[j].z_mm,
                         not problems, tuple(problems), wall)


def toolpath_scale(measures) -> tuple[float, float]:
    """The scale about the axis that maps nominal channel centres to the openings' centres, and its SD.

    Least squares over every layer measure (a :class:`LayerMeasure` sequence):
    ``s = sum(c . m) / sum(c . c)`` with ``c`` the nominal centre and ``m = c +
    offset`` in F's x, y; the SD from the residuals' scatter. What a scan's
    calibration factor (``chic-register calibrate``) is compared with.
    """
    c = np.array([m.centre_mm for m in measures], dtype=float).reshape(-1, 2)
    off = np.array([m.offset_mm for m in measures], dtype=float).reshape(-1, 2)
    keep = np.all(np.isfinite(off), axis=1)
    c, m = c[keep], c[keep] + off[keep]
    cc = float(np.sum(c * c))
    if len(c) < 2 or cc <= 0:
        return float("nan"), float("nan")
    s = float(np.sum(c * m)) / cc
    r = m - s * c
    return s, float(np.sqrt(np.sum(r * r) / (2 * len(c) - 1) / cc))


def check_channels(channels, placements: dict[str, Placement], layers, extrusion_width_mm: float,
                   layer_mm: float, nozzle_mm: float = 0.0, slicer: str = "", progress=None) -> PrintCheck:
    """Check every channel (:class:`CheckedChannel`) against the toolpaths ``layers`` of the plate."""
    results, body_measures = [], []
    for ch in channels:
        measures = measure_channel(ch, placements[ch.part], layers, extrusion_width_mm)
        results.append(judge(ch, measures, MAX_OVERHANG_SHARE * extrusion_width_mm, nozzle_mm))
        if ch.part == "body":
            body_measures += measures
        if progress is not None:
            progress(ch.id)
    scale, scale_sd = toolpath_scale(body_measures)
    return PrintCheck(tuple(results), extrusion_width_mm, layer_mm, slicer, len(layers), nozzle_mm, scale, scale_sd)


def measure_channel_raster(channel: CheckedChannel, placement: Placement, stack) -> list[LayerMeasure]:
    """:class:`LayerMeasure` of ``channel`` in a resin print's layer masks (a
    :class:`~chic_design.printing.sla_layers.SlaStack`): what of its nominal section stays uncured."""
    from scipy.ndimage import distance_transform_edt  # loaded only for resin prints

    lo, hi = channel.tube.z_range
    R = placement.T_bed_from_F[:3, :3]
    px = min(abs(stack.dx_mm), abs(stack.dy_mm))
    out = []
    for k, z_top in enumerate(stack.z_top_mm):
        z_f = _plane_to_f(placement, float(z_top - stack.height_mm[k] / 2))
        if z_f is None or not (lo < z_f < hi):
            continue
        section, centre = nominal_section(channel, placement, z_f)
        if section is None:
            continue
        ring = section.buffer(WALL_RING_MM)
        x0, y0, x1, y1 = ring.bounds
        (r0, r1), (c0, c1) = (np.sort(v) for v in stack.pixel_of(np.array([x0, x1]), np.array([y0, y1])))
        rows = np.arange(max(int(np.floor(r0)) - 1, 0), min(int(np.ceil(r1)) + 2, stack.masks.shape[1]))
        cols = np.arange(max(int(np.floor(c0)) - 1, 0), min(int(np.ceil(c1)) + 2, stack.masks.shape[2]))
        if rows.size == 0 or cols.size == 0:
            continue
        rr, cc = np.meshgrid(rows, cols, indexing="ij")
        x, y = stack.x0_mm + cc * stack.dx_mm, stack.y0_mm + rr * stack.dy_mm
        inside = shapely.contains_xy(section, x, y)
        if not inside.any():
            continue
        around = shapely.contains_xy(ring, x, y) & ~inside
        cured = stack.masks[k][rr, cc]
        wall = float(cured[around].mean()) if around.any() else 0.0
        opening = inside & ~cured
        share = opening.sum() / inside.sum()
        clear = 2.0 * float(distance_transform_edt(np.pad(opening, 1)).max()) * px if opening.any() else 0.0
        if opening.any():
            c = np.array([x[opening].mean(), y[opening].mean()])
            offset = tuple(float(v) for v in R[:2, :2].T @ (c - centre))
        else:
            offset = (float("nan"), float("nan"))
        c_f = channel.tube.point_at_z(z_f)[0, :2]
        out.append(LayerMeasure(float(z_top), float(share), clear, offset, 0.0, (float(c_f[0]), float(c_f[1])),
                                wall))
    return out


def check_channels_raster(channels, placements: dict[str, Placement], stack, layer_mm: float, slicer: str = "",
                          progress=None) -> PrintCheck:
    """Check every channel against a resin print's layer masks (no beads: nothing overhangs or sags)."""
    results, body_measures = [], []
    for ch in channels:
        measures = measure_channel_raster(ch, placements[ch.part], stack)
        results.append(judge(ch, measures, None, 0.0))
        if ch.part == "body":
            body_measures += measures
        if progress is not None:
            progress(ch.id)
    scale, scale_sd = toolpath_scale(body_measures)
    return PrintCheck(tuple(results), 0.0, layer_mm, slicer, len(stack.z_top_mm), 0.0, scale, scale_sd)
