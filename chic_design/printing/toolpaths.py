"""Reading a slicer's G-code back as what the nozzle lays down: per layer, the extrusion segments and their widths.

PrusaSlicer annotates its G-code: ``;LAYER_CHANGE``, ``;Z:`` (the layer's
top), ``;HEIGHT:``, ``;TYPE:`` (perimeter, infill, ...) and ``;WIDTH:`` (the
extrusion width in mm). A move is an extrusion when it moves in x or y and
the extruder advances (absolute ``M82`` or relative ``M83`` distances, with
``G92 E`` resets). Arcs (``G2``/``G3``, only with arc fitting on) are refused.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from chic_design.errors import PrintFileError

#: The extrusion kinds PrusaSlicer names after ``;TYPE:`` (index = the kind code of :class:`Layer`).
KINDS = ("Perimeter", "External perimeter", "Overhang perimeter", "Internal infill", "Solid infill",
         "Top solid infill", "Bridge infill", "Gap fill", "Skirt/Brim", "Support material",
         "Support material interface", "Ironing", "Custom", "Other")
KIND_CODE = {k: i for i, k in enumerate(KINDS)}


@dataclass(frozen=True)
class Layer:
    """One printed layer: ``segments_mm`` (N, 4) as x0, y0, x1, y1; ``width_mm`` (N,); ``kind`` (N,) into :data:`KINDS`.

    ``z_mm`` is the top of the layer (the nozzle height), ``height_mm`` its thickness.
    """

    z_mm: float
    height_mm: float
    segments_mm: np.ndarray
    width_mm: np.ndarray
    kind: np.ndarray

    @property
    def mid_z_mm(self) -> float:
        """Height (mm) of the plane the slicer cut this layer's outline from."""
        return self.z_mm - self.height_mm / 2


def _words(line: str) -> dict[str, float]:
    out = {}
    for w in line.split(";", 1)[0].split()[1:]:
        if len(w) > 1:
            try:
                out[w[0]] = float(w[1:])
            except ValueError:
                pass
    return out


def read_toolpaths(path) -> tuple[Layer, ...]:
    """The extrusions of a PrusaSlicer G-code file, layer by layer (layers with no extrusion left out)."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8", errors="replace").splitlines()
    except OSError as exc:
        raise PrintFileError(f"{path}: cannot read the G-code ({exc.strerror or exc})") from None
    layers: list[Layer] = []
    x = y = 0.0
    e = 0.0
    relative_e = False
    z_top, height = None, None
    kind, width = KIND_CODE["Other"], 0.0
    segs: list[tuple[float, float, float, float]] = []
    widths: list[float] = []
    kinds: list[int] = []
    saw_layer = False

    def flush():
        if z_top is not None and segs:
            layers.append(Layer(z_top, height if height is not None else z_top,
                                np.asarray(segs, dtype=float), np.asarray(widths), np.asarray(kinds, dtype=np.int8)))
        segs.clear()
        widths.clear()
        kinds.clear()

    for line in lines:
        if not line:
            continue
        c = line[0]
        if c == ";":
            if line.startswith(";LAYER_CHANGE"):
                flush()
                saw_layer = True
            elif line.startswith(";Z:"):
                z_top = float(line[3:])
            elif line.startswith(";HEIGHT:"):
                height = float(line[8:])
            elif line.startswith(";TYPE:"):
                kind = KIND_CODE.get(line[6:].strip(), KIND_CODE["Other"])
            elif line.startswith(";WIDTH:"):
                width = float(line[7:])
            continue
        if c != "G" and c != "M":
            continue
        head = line.split(None, 1)[0]
        if head in ("G1", "G0"):
            w = _words(line)
            nx, ny = w.get("X", x), w.get("Y", y)
            extruded = False
            if "E" in w:
                de = w["E"] if relative_e else w["E"] - e
                e = e + w["E"] if relative_e else w["E"]
                extruded = de > 0
            if extruded and (nx != x or ny != y) and head == "G1":
                segs.append((x, y, nx, ny))
                widths.append(width)
                kinds.append(kind)
            x, y = nx, ny
        elif head == "G92":
            w = _words(line)
            if "E" in w:
                e = w["E"]
        elif head == "M83":
            relative_e = True
        elif head == "M82":
            relative_e = False
        elif head in ("G2", "G3"):
            raise PrintFileError(f"{path}: arc moves (G2/G3) are not read; slice with arc fitting off")
    flush()
    if not saw_layer:
        raise PrintFileError(f"{path}: no ';LAYER_CHANGE' marks: not a PrusaSlicer G-code file")
    return tuple(layers)
