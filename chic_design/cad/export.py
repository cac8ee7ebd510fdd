"""Writing the parts: each as STL, STEP and 3MF (mm, in F, named), plus ``assembly.step``."""

from __future__ import annotations

from pathlib import Path

from build123d import Mesher, export_step

from chic_design.cad.parts import FiducialParts
from chic_register.io.stl import declare_space

#: Export tessellation: chord deviation <= 0.01 mm, angle between facet normals <= 0.15 rad
#: (the output checks' volume tolerance, :data:`chic_design.verify.VOLUME_REL_TOL`, rests on it).
STL_TOLERANCE_MM = 0.01
STL_ANGULAR_TOLERANCE_RAD = 0.15


def export_parts(parts: FiducialParts, folder: Path, name: str) -> list[str]:
    """Write each part as STL, STEP and 3MF plus ``assembly.step`` into ``folder``; returns the file names."""
    written = []
    for part_name, part in parts.items():
        part.label = part_name
        if not export_step(part, folder / f"{part_name}.step"):
            raise OSError(f"{folder / part_name}.step: STEP export failed")
        # one tessellation for both mesh files: the STL and the 3MF hold the same triangles
        mesher = Mesher()
        mesher.add_shape(part, linear_deflection=STL_TOLERANCE_MM,
                         angular_deflection=STL_ANGULAR_TOLERANCE_RAD, part_number=part_name)
        mesher.write(str(folder / f"{part_name}.3mf"))
        mesher.write(str(folder / f"{part_name}.stl"))
        declare_space(folder / f"{part_name}.stl")  # SPACE=LPS: Slicer reads F as the .tfm expects
        written += [f"{part_name}.stl", f"{part_name}.step", f"{part_name}.3mf"]
    if not export_step(parts.assembly(name), folder / "assembly.step"):
        raise OSError(f"{folder}/assembly.step: STEP export failed")
    return written + ["assembly.step"]
