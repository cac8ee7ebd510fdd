"""From a Z-frame spec to its rods as tube objects in frame F (``family: zframe``).

Frame F of a Z-frame (docs/interfaces.md section 1): +z along the axial rods, origin
on the frame's central axis in the plane of its bottom face, x and y as in
configuration ``z001`` of 3D Slicer's ZFrameRegistration. With the default spec
(side 60, height 60) the rods are z001's seven fiducials shifted by +30 mm in z:

- axial rods ``A0..A3`` at the corners (30, -30), (30, 30), (-30, 30), (-30, -30);
- diagonal ``Z+x`` on face x = +30 from (30, 30, 0) to (30, -30, 60),
  ``Z+y`` on face y = +30 from (-30, 30, 0) to (30, 30, 60),
  ``Z-x`` on face x = -30 from (-30, -30, 0) to (-30, 30, 60).

Tubes are listed in z001's order (corner, diagonal of the next face, corner, ...).
The CAD channels are swept along these same objects.
"""

from __future__ import annotations

from chic_design.families.zframe.spec import FACES, ZFrameSpec
from chic_register.model.body import Body
from chic_register.model.tubes import LineTube

#: Corner unit signs (x, y), counter-clockwise from (+, -) as z001's fiducials 1, 3, 5, 7.
CORNERS = ((1, -1), (1, 1), (-1, 1), (-1, -1))
#: Per face: (corner index at its counter-clockwise end, corner index at its clockwise end).
#: Face +x joins corners 0 (+,-) and 1 (+,+); going counter-clockwise (seen from +z) along it
#: runs from corner 0 to corner 1, so its counter-clockwise end is corner 1.
FACE_CORNERS = {"+x": (1, 0), "+y": (2, 1), "-x": (3, 2), "-y": (0, 3)}


def corner_xy(spec: ZFrameSpec, k: int) -> tuple[float, float]:
    """Centre (x, y) in mm of the axial rod at corner ``k`` (see :data:`CORNERS`)."""
    h = spec.frame.side / 2
    sx, sy = CORNERS[k]
    return (sx * h, sy * h)


def axial_rod(spec: ZFrameSpec, k: int) -> LineTube:
    """Axial rod ``Ak`` at corner ``k``, from the bottom face to the top face."""
    x, y = corner_xy(spec, k)
    return LineTube(f"A{k}", "axial", (x, y, 0.0), (x, y, spec.frame.height), spec.rods.diameter)


def diagonal_rod(spec: ZFrameSpec, face: str) -> LineTube:
    """Diagonal rod ``Z<face>``: from one corner of ``face`` at the bottom to the other at the top.

    As z001: from the face's counter-clockwise-end corner (seen from +z) at z = 0
    to its clockwise-end corner at z = height; reversed if the face is listed in
    ``diagonals.reversed_faces``.
    """
    lo, hi = FACE_CORNERS[face]
    if face in spec.diagonals.reversed_faces:
        lo, hi = hi, lo
    (x0, y0), (x1, y1) = corner_xy(spec, lo), corner_xy(spec, hi)
    return LineTube(f"Z{face}", "diagonal", (x0, y0, 0.0), (x1, y1, spec.frame.height), spec.rods.diameter)


def zframe_tubes(spec: ZFrameSpec) -> tuple[LineTube, ...]:
    """All rods in z001's order: A0, Z+x, A1, Z+y, A2, Z-x, A3, Z-y (diagonals only where listed)."""
    tubes = []
    for k, face in enumerate(FACES):  # face FACES[k] lies between corners k and k + 1
        tubes.append(axial_rod(spec, k))
        if face in spec.diagonals.faces:
            tubes.append(diagonal_rod(spec, face))
    return tuple(tubes)


def zframe_body(spec: ZFrameSpec) -> Body:
    """The square frame: outside ``frame.side + frame.wall``, bore ``frame.side - frame.wall``."""
    return Body.square(spec.frame.height, spec.outer_side, spec.inner_side)
