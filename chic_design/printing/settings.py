"""What the printer is told: the slicer settings a fiducial's channels need, each with its reason.

A channel of 1.5-3 mm in a 30 mm part is what a slicer's perimeters, gap fill
and sagging overhangs close or narrow. The settings here are chosen from the
design (its smallest channel, the spec's ``print`` section) so that the walls
around the channels are solid, no support grows inside a channel, and the
outer wall's seam sits away from the channels. :func:`prusa_config` turns
them into PrusaSlicer's keys (``Metadata/Slic3r_PE.config`` of a project 3MF).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from chic_register.model.geometry import FiducialGeometry

#: FDM layer height as a share of the smallest channel's diameter: ten layers across a channel keep its
#: stair-stepped roof within a tenth of the diameter of round.
LAYERS_PER_CHANNEL = 10
#: FDM layer height limits as shares of the nozzle: below a quarter the flow is too small to meter, above
#: half the layers bond poorly (PrusaSlicer's own profiles stay within 0.25-0.75 x nozzle).
MIN_LAYER_SHARE, MAX_LAYER_SHARE = 0.25, 0.5
#: FDM extrusion width as a multiple of the nozzle (PrusaSlicer's default 0.45 mm for a 0.4 mm nozzle).
WIDTH_PER_NOZZLE = 1.125
#: Perimeters around every contour, channels included: three loops (about 1.3 mm) make the channel wall a
#: smooth, closed ring before any infill touches it.
PERIMETERS = 3
#: Resin layer height (mm): the usual 0.05 mm of masked-SLA printers.
RESIN_LAYER_MM = 0.05
#: Layer heights are rounded down to this step (mm), as printers' profiles list them.
LAYER_STEP_MM = 0.01

#: The FDM printer the plate is set up for: an Original Prusa MK3S-sized bed (mm).
FDM_BED_MM = (250.0, 210.0)
FDM_MAX_HEIGHT_MM = 210.0
#: The resin printer: a generic 8.9" 4K masked-SLA display (mm, pixels).
RESIN_DISPLAY_MM = (192.0, 120.0)
RESIN_DISPLAY_PX = (3840, 2400)
RESIN_MAX_HEIGHT_MM = 200.0


@dataclass(frozen=True)
class PrintSettings:
    """The settings of one design's print, and why each was chosen.

    ``extrusion_width_mm`` is 0 for resin; ``bed_mm`` is the bed (FDM) or display (resin) size.
    """

    printer: str
    layer_mm: float
    first_layer_mm: float
    nozzle_mm: float
    extrusion_width_mm: float
    perimeters: int
    bed_mm: tuple[float, float]
    max_height_mm: float
    reasons: dict[str, str] = field(default_factory=dict)

    @property
    def is_resin(self) -> bool:
        return self.printer == "resin"


def smallest_channel_mm(geometry: FiducialGeometry) -> float:
    """Diameter (mm) of the narrowest channel."""
    return min(t.diameter for t in geometry.tubes)


def auto_layer_mm(smallest_mm: float, nozzle_mm: float) -> float:
    """FDM layer height (mm) for a smallest channel of ``smallest_mm``: a tenth of it, within the nozzle's range."""
    lo, hi = MIN_LAYER_SHARE * nozzle_mm, MAX_LAYER_SHARE * nozzle_mm
    h = min(max(smallest_mm / LAYERS_PER_CHANNEL, lo), hi)
    return math.floor(h / LAYER_STEP_MM + 1e-9) * LAYER_STEP_MM


def print_settings(spec, geometry: FiducialGeometry) -> PrintSettings:
    """The settings for ``spec``'s ``print`` section (printer, nozzle, layer height) and its channels."""
    p = spec.print
    d_min = smallest_channel_mm(geometry)
    if p.printer == "resin":
        layer = p.layer_height if p.layer_height is not None else RESIN_LAYER_MM
        return PrintSettings(
            "resin", layer, layer, 0.0, 0.0, 0, RESIN_DISPLAY_MM, RESIN_MAX_HEIGHT_MM,
            reasons={"layer height": ("print.layer_height" if p.layer_height is not None
                                      else f"{RESIN_LAYER_MM:g} mm, the usual masked-SLA layer"),
                     "supports": "none: the body stands on an end face and the caps on their plates; a support "
                                 "inside a channel cannot be removed",
                     "vents": "a groove in the body's bottom end face from each channel out through the side "
                              "wall: the build plate seals the channels' lower ends, and the grooves let air in at "
                              "each peel; the bottom cap's glue fills them",
                     "channels": "open at both end faces once off the plate, so uncured resin drains from every "
                                 "channel; rinse them with a syringe of IPA before curing"})
    layer = p.layer_height if p.layer_height is not None else auto_layer_mm(d_min, p.nozzle_diameter)
    width = round(WIDTH_PER_NOZZLE * p.nozzle_diameter, 3)
    reasons = {
        "layer height": ("print.layer_height" if p.layer_height is not None else
                         f"smallest channel {d_min:g} mm / {LAYERS_PER_CHANNEL}, within "
                         f"{MIN_LAYER_SHARE:g}-{MAX_LAYER_SHARE:g} x the {p.nozzle_diameter:g} mm nozzle"),
        "perimeters": f"{PERIMETERS} loops around every contour, each channel's too: a closed ring before infill",
        "infill": "100 % rectilinear: the walls between channels and surfaces are solid, so nothing leaks",
        "supports": "none: the body stands on an end face, the caps on their plates; a support inside a "
                    "channel cannot be removed",
        "seam": "at the rear of each loop; the body is turned so the rear of its outer wall is farthest "
                "from every channel",
    }
    return PrintSettings("fdm", layer, max(layer, 0.2), p.nozzle_diameter, width, PERIMETERS, FDM_BED_MM,
                         FDM_MAX_HEIGHT_MM, reasons)


def _bed_shape(bed_mm) -> str:
    w, h = bed_mm
    return f"0x0,{w:g}x0,{w:g}x{h:g},0x{h:g}"


def prusa_config(settings: PrintSettings, bed_mm: tuple[float, float] | None = None) -> dict[str, str]:
    """PrusaSlicer's configuration keys for ``settings`` (its ``; key = value`` lines); ``bed_mm`` overrides the bed."""
    bed = _bed_shape(bed_mm or settings.bed_mm)
    if settings.is_resin:
        w, h = bed_mm or settings.bed_mm
        px = settings.bed_mm[0] / RESIN_DISPLAY_PX[0]
        return {
            "printer_technology": "SLA", "printer_model": "", "bed_shape": bed,
            "display_width": f"{w:g}", "display_height": f"{h:g}",
            "display_pixels_x": str(round(w / px)), "display_pixels_y": str(round(h / px)),
            "display_orientation": "landscape", "max_print_height": f"{settings.max_height_mm:g}",
            "layer_height": f"{settings.layer_mm:g}", "initial_layer_height": f"{settings.first_layer_mm:g}",
            "supports_enable": "0", "pad_enable": "0", "hollowing_enable": "0",
            "exposure_time": "2.5", "initial_exposure_time": "25", "faded_layers": "5",
            "elefant_foot_compensation": "0.2",
        }
    w = f"{settings.extrusion_width_mm:g}"
    return {
        "printer_technology": "FFF", "printer_model": "", "bed_shape": bed,
        "max_print_height": f"{settings.max_height_mm:g}", "gcode_flavor": "marlin2",
        "nozzle_diameter": f"{settings.nozzle_mm:g}", "filament_diameter": "1.75",
        # PETG: watertight walls, and it tolerates the contrast agents and gels channels are filled with
        "filament_type": "PETG", "temperature": "240", "first_layer_temperature": "230",
        "bed_temperature": "90", "first_layer_bed_temperature": "85",
        "layer_height": f"{settings.layer_mm:g}", "first_layer_height": f"{settings.first_layer_mm:g}",
        "extrusion_width": w, "perimeter_extrusion_width": w, "external_perimeter_extrusion_width": w,
        "infill_extrusion_width": w, "solid_infill_extrusion_width": w, "top_infill_extrusion_width": w,
        "first_layer_extrusion_width": w,
        "perimeters": str(settings.perimeters), "fill_density": "100%", "fill_pattern": "rectilinear",
        "top_fill_pattern": "rectilinear", "bottom_fill_pattern": "rectilinear",
        "top_solid_layers": "5", "bottom_solid_layers": "4", "infill_every_layers": "1",
        "ensure_vertical_shell_thickness": "1", "gap_fill_enabled": "1", "thin_walls": "0",
        "support_material": "0", "support_material_auto": "0", "overhangs": "1",
        "seam_position": "rear", "external_perimeters_first": "0", "xy_size_compensation": "0",
        "elefant_foot_compensation": "0.2", "skirts": "1", "skirt_distance": "3", "brim_width": "0",
        "complete_objects": "0", "gcode_label_objects": "1",
    }
