"""Running PrusaSlicer's command line on a plate: G-code out, with the settings the plate carries.

``--dont-arrange`` keeps every part where the plate put it, so the toolpaths
and the plate's placements share one bed frame.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

from chic_design.errors import SlicerError

#: The slicer's executable names, as Debian and PrusaSlicer's AppImage install it.
SLICER_NAMES = ("prusa-slicer", "PrusaSlicer", "prusaslicer")
#: Slicing a 200 mm part at fine layers takes minutes at most; beyond this the slicer is stuck.
SLICE_TIMEOUT_S = 900


def find_slicer() -> str | None:
    """Path of PrusaSlicer's executable on the PATH, or None."""
    for name in SLICER_NAMES:
        found = shutil.which(name)
        if found:
            return found
    return None


def slicer_version(exe: str) -> str:
    """The slicer's version line (``PrusaSlicer-2.5.0...``), or "" if it does not say."""
    try:
        out = subprocess.run([exe, "--help"], capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return ""
    for line in (out.stdout + out.stderr).splitlines():
        if line.startswith("PrusaSlicer-"):
            return line.split()[0]
    return ""


def _last_error(text: str) -> str:
    lines = [ln.strip() for ln in text.splitlines() if ln.strip() and "[trace]" not in ln and "=>" not in ln]
    return lines[-1] if lines else "no message"


def slice_plate(plate_path, out_path, exe: str | None = None, sla: bool = False) -> Path:
    """Slice ``plate_path`` (a project 3MF) to ``out_path``: G-code, or with ``sla`` a ``.sl1`` of layer images."""
    exe = exe or find_slicer()
    if exe is None:
        raise SlicerError("prusa-slicer is not on the PATH; install PrusaSlicer (Debian: apt-get install "
                          "prusa-slicer) to slice the plate")
    plate_path, out_path = Path(plate_path), Path(out_path)
    action = "--export-sla" if sla else "--export-gcode"
    cmd = [exe, action, "--dont-arrange", str(plate_path), "--output", str(out_path)]
    try:
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=SLICE_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise SlicerError(f"{plate_path}: prusa-slicer did not finish within {SLICE_TIMEOUT_S} s") from None
    except OSError as exc:
        raise SlicerError(f"{exe}: cannot run the slicer ({exc.strerror or exc})") from None
    if run.returncode != 0 or not out_path.is_file():
        raise SlicerError(f"{plate_path}: prusa-slicer failed (exit {run.returncode}): "
                          f"{_last_error(run.stderr + run.stdout)}")
    return out_path
