"""The print's named tolerances, each with its reason: what ``printcheck`` holds the toolpaths to and what
``check`` predicts from the design before anything is sliced (:func:`print_violations`)."""

from __future__ import annotations

import numpy as np

from chic_design.feasibility.records import Finding, Overhang

#: Narrowest clear width allowed, as a share of the channel diameter: at 0.7 d the fluid's section keeps half
#: its area, so a slice's blob keeps most of its signal and the shape the solver fits.
MIN_CLEAR_SHARE = 0.7
#: Narrowest clear width allowed, as a share of the nozzle's diameter: the nozzle's face is wider than its
#: orifice and presses the bead looping round a narrower hole into it, so it prints closed although the
#: toolpaths leave it open.
MIN_CLEAR_NOZZLE_SHARE = 1.0
#: Least open area allowed, as a share of the nominal section (the same half of the fluid).
MIN_OPEN_SHARE = 0.5
#: Largest overhang over a channel's opening, as a share of the extrusion width: an extrusion with less than
#: half its width on the layer below is unsupported (PrusaSlicer's own overhang rule) and sags.
MAX_OVERHANG_SHARE = 0.5
#: The overhang judged is this percentile of a channel's layers: one layer's value carries the slicer's polygon
#: noise (a few hundredths of a mm), while a roof sags only where it overhangs layer after layer.
OVERHANG_PERCENTILE = 90
#: A channel must be walled in: material over at least this share of a ring of :data:`WALL_RING_MM` round its
#: section (median over its layers; channels that meet others or the bore stay far above it). An opening in
#: empty space would pass every other test: this is what catches a part the slicer did not put where the
#: plate says.
MIN_WALL_SHARE = 0.5
WALL_RING_MM = 0.5


def print_violations(settings, geometry, overhangs: tuple[Overhang, ...], port_diameter_mm: float) -> list[Finding]:
    """What the print check will fail, foreseen from the design: a channel or fill port narrower than the
    nozzle, and a channel whose lean makes each layer overhang its opening by more than half a bead
    (``h tan(beta)`` at layer height ``h``). Nothing for a resin printer (no nozzle, no beads)."""
    if settings.is_resin:
        return []
    out = []
    nozzle = settings.nozzle_mm * MIN_CLEAR_NOZZLE_SHARE
    for t in geometry.tubes:
        if t.diameter < nozzle:
            out.append(Finding("narrower_than_nozzle", f"channel {t.id} ({t.diameter:g} mm) is narrower than the "
                               f"{settings.nozzle_mm:g} mm nozzle: it prints closed; widen channels.diameter or "
                               "choose a finer print.nozzle_diameter", t.id))
    if 0 < port_diameter_mm < nozzle:
        out.append(Finding("narrower_than_nozzle", f"the fill ports ({port_diameter_mm:g} mm) are narrower than the "
                           f"{settings.nozzle_mm:g} mm nozzle: they print closed", "caps.fill_port_diameter"))
    limit = MAX_OVERHANG_SHARE * settings.extrusion_width_mm
    for o in overhangs:
        step = settings.layer_mm * float(np.tan(np.radians(o.max_overhang_deg)))
        if step > limit:
            out.append(Finding("overhang_for_layer", f"channel {o.tube_id} leans {o.max_overhang_deg:.1f} deg: at "
                               f"{settings.layer_mm:g} mm layers its roof overhangs {step:.2f} mm per layer, more "
                               f"than half the {settings.extrusion_width_mm:g} mm bead ({limit:.3f} mm); lower "
                               "print.layer_height", o.tube_id))
    return out
