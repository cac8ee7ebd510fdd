"""Reading a resin slicer's layer images back: PrusaSlicer's ``.sl1`` archive, one PNG mask per layer.

The archive holds ``prusaslicer.ini`` (the display: size in mm and pixels,
orientation, mirroring; the layer heights) and ``<job>NNNNN.png`` layers, lit
pixels where resin cures. :func:`read_sla_layers` gives the masks with the bed
coordinates of their pixel centres, so a channel's section in bed mm can be
compared with what cures (:func:`chic_design.printing.check.measure_channel_raster`).
"""

from __future__ import annotations

import io
import re
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from chic_design.errors import PrintFileError

#: A pixel cures when its grey level is at least this share of white (the slicer anti-aliases the edges).
CURED_LEVEL = 0.5


@dataclass(frozen=True)
class SlaStack:
    """The layers of a resin print: ``masks`` (L, rows, cols) bool, cured; ``z_top_mm`` (L,) each layer's top.

    Pixel (r, c) has its centre at bed ``x = x0 + c * dx``, ``y = y0 + r * dy`` (mm; ``dx``, ``dy`` may be
    negative where the display is mirrored or its rows run down the bed).
    """

    masks: np.ndarray
    z_top_mm: np.ndarray
    height_mm: np.ndarray
    x0_mm: float
    dx_mm: float
    y0_mm: float
    dy_mm: float

    def pixel_of(self, x_mm, y_mm) -> tuple[np.ndarray, np.ndarray]:
        """Fractional (row, col) of bed points."""
        return (np.asarray(y_mm) - self.y0_mm) / self.dy_mm, (np.asarray(x_mm) - self.x0_mm) / self.dx_mm


def _ini(text: str) -> dict[str, str]:
    out = {}
    for line in text.splitlines():
        if " = " in line:
            k, v = line.split(" = ", 1)
            out[k.strip()] = v.strip()
    return out


def read_sla_layers(path) -> SlaStack:
    """The cured masks of a ``.sl1`` archive, in layer order, with their bed geometry."""
    from PIL import Image  # the PNG decoder: loaded only when a resin print is read

    path = Path(path)
    try:
        with zipfile.ZipFile(path) as z:
            cfg = _ini(z.read("prusaslicer.ini").decode("utf-8", "replace"))
            names = sorted(n for n in z.namelist() if re.fullmatch(r".*\d{5}\.png", n) and "/" not in n)
            masks = [np.asarray(Image.open(io.BytesIO(z.read(n))).convert("L")) >= 255 * CURED_LEVEL for n in names]
    except (OSError, zipfile.BadZipFile, KeyError) as exc:
        raise PrintFileError(f"{path}: not a PrusaSlicer .sl1 archive ({exc})") from None
    if not masks:
        raise PrintFileError(f"{path}: the archive holds no layer images")
    w, h = float(cfg["display_width"]), float(cfg["display_height"])
    nx, ny = int(cfg["display_pixels_x"]), int(cfg["display_pixels_y"])
    if cfg.get("display_orientation", "landscape") != "landscape":
        raise PrintFileError(f"{path}: portrait displays are not read; the plate sets a landscape display")
    px, py = w / nx, h / ny
    # rows run from the back of the bed (y = h) forward; a mirrored x runs from x = w leftwards
    mirror_x = cfg.get("display_mirror_x", "0") == "1"
    mirror_y = cfg.get("display_mirror_y", "0") == "1"
    x0, dx = (w - px / 2, -px) if mirror_x else (px / 2, px)
    y0, dy = (py / 2, py) if mirror_y else (h - py / 2, -py)
    first = float(cfg.get("initial_layer_height", cfg["layer_height"]))
    layer = float(cfg["layer_height"])
    heights = np.array([first] + [layer] * (len(masks) - 1))
    return SlaStack(np.stack(masks), np.cumsum(heights), heights, x0, dx, y0, dy)
