"""From an N-localizer spec to its rods as tube objects in frame F (``family: nlocalizer``).

Frame F of an N-localizer (docs/interfaces.md section 1): mm; origin at the
centre of the box's bottom face (the plane where the vertical rods start), +z
along the vertical rods, x and y in the cross-section. For the Leksell presets
F is aligned so that for a head-first supine patient x = patient Left,
y = Posterior, z = Superior: F's axes are the scanner's LPS axes, and the
bottom face z = 0 is the inferior edge of the localizer box.

Each plate (azimuth a, distance d, width w) has its rod plane at distance d
along the outward normal n = (cos a, sin a); seen from outside with z up, its
right end lies along r = z x n = (-sin a, cos a). Its rods:

- ``<plate>_a``: the vertical rod at the left end, ``d n - (w/2) r``, z = 0..height (role axial);
- ``<plate>_d``: the diagonal, from the ``diagonal_from`` end at z = 0 to the other end at z = height
  (role diagonal);
- ``<plate>_b``: the vertical rod at the right end, ``d n + (w/2) r`` (role axial);
- with ``edge_rods``, ``<plate>_bottom`` and ``<plate>_top``: from the left end to the right end at
  z = 0 and z = height (role other; they lie in axial planes and never show as dots).

Example (designs/leksell-g-ct.yaml): the right plate (normal -x) has its rods at
x = -95, y = +60 (``right_a``) and y = -60 (``right_b``), its diagonal from
(-95, -60, 0) to (-95, 60, 120); at height z the diagonal crosses y = -60 + z on
both plates.

Leksell coordinates (Elekta, Leksell Stereotactic System instructions for use;
Sedrak, Alaminos-Bouza and Srivastava, Cureus 12(6): e8578, 2020): X from the
patient's right to left, Y from posterior to anterior, Z from superior to
inferior, the frame centre at (100, 100, 100) mm; with F as above
X = 100 + x, Y = 100 - y, Z = 100 + height/2 - z (:func:`leksell_from_fiducial`).
"""

from __future__ import annotations

import numpy as np

from chic_design.families.nlocalizer.spec import NLocalizerSpec, PlateSpec
from chic_register.model.body import Body, FrameCoordinates
from chic_register.model.tubes import LineTube

LEKSELL_AXES = ("X from the patient's right to left, Y from posterior to anterior, Z from superior to inferior; "
                "frame centre at (100, 100, 100) mm")
LEKSELL_REFERENCE = ("Elekta, Leksell Stereotactic System instructions for use; Sedrak M, Alaminos-Bouza AL, "
                     "Srivastava S. Coordinate Systems for Navigating Stereotactic Space: How Not to Get Lost. "
                     "Cureus 12(6): e8578 (2020)")


def plate_end_xy(plate: PlateSpec, end: str) -> np.ndarray:
    """(x, y) in mm of the plate's vertical rod at its ``"left"`` or ``"right"`` end seen from outside."""
    sign = 1.0 if end == "right" else -1.0
    return np.round(plate.distance * plate.normal + sign * plate.width / 2 * plate.right, 9) + 0.0  # no -0.0


def plate_tubes(spec: NLocalizerSpec, plate: PlateSpec) -> tuple[LineTube, ...]:
    """One plate's rods: ``_a`` (left end), ``_d`` (diagonal), ``_b`` (right end), then the edge rods if any."""
    h, d = spec.frame.height, spec.rods.diameter
    left, right = plate_end_xy(plate, "left"), plate_end_xy(plate, "right")
    lo, hi = (left, right) if plate.diagonal_from == "left" else (right, left)
    tubes = [
        LineTube(f"{plate.name}_a", "axial", (*left, 0.0), (*left, h), d),
        LineTube(f"{plate.name}_d", "diagonal", (*lo, 0.0), (*hi, h), d),
        LineTube(f"{plate.name}_b", "axial", (*right, 0.0), (*right, h), d),
    ]
    if spec.edge_rods:
        tubes += [LineTube(f"{plate.name}_bottom", "other", (*left, 0.0), (*right, 0.0), d),
                  LineTube(f"{plate.name}_top", "other", (*left, h), (*right, h), d)]
    return tuple(tubes)


def nlocalizer_tubes(spec: NLocalizerSpec) -> tuple[LineTube, ...]:
    """All rods, plate by plate in the spec's order."""
    return tuple(t for p in spec.plates for t in plate_tubes(spec, p))


def ring_planes_mm(spec: NLocalizerSpec) -> np.ndarray | None:
    """Distances (x, y) of the rectangular ring's wall planes from the axis, or None if a plate is not along x or y.

    An axis with plates has its walls at their distance (opposite plates share it
    when printed; a commercial frame's farther one counts); an axis without
    plates has them a wall beyond the other plates' rod ends.
    """
    if any(p.axis is None for p in spec.plates):
        return None
    ends = max(p.width / 2 for p in spec.plates)
    return np.array([max((p.distance for p in spec.plates if p.axis == k), default=ends + spec.frame.wall)
                     for k in (0, 1)])


def nlocalizer_body(spec: NLocalizerSpec) -> Body:
    """The body: a rectangular ring ``Body.box`` whose walls (``frame.wall``) are centred on the rod planes.

    For plates along x and y this is the printed frame. Plates at other azimuths (a
    commercial frame only) get a box enclosing every plate around the largest
    centred square inside all of them.
    """
    w, h = spec.frame.wall, spec.frame.height
    planes = ring_planes_mm(spec)
    if planes is not None:
        return Body.box(h, 2 * planes + w, 2 * planes - w)
    corners = np.array([p.distance * p.normal + a * (p.width + w) / 2 * p.right + b * w / 2 * p.normal
                        for p in spec.plates for a in (-1, 1) for b in (-1, 1)])
    outer = 2 * np.max(np.abs(corners), axis=0)
    inner = min((p.distance - w / 2) / (abs(p.normal[0]) + abs(p.normal[1])) for p in spec.plates)
    return Body.box(h, outer, (2 * inner, 2 * inner))


def leksell_from_fiducial(height_mm: float) -> np.ndarray:
    """T_frame_from_fiducial of the Leksell coordinates: X = 100 + x, Y = 100 - y, Z = 100 + height/2 - z."""
    return np.array([[1.0, 0.0, 0.0, 100.0], [0.0, -1.0, 0.0, 100.0], [0.0, 0.0, -1.0, 100.0 + height_mm / 2],
                     [0.0, 0.0, 0.0, 1.0]])


def nlocalizer_frame_coordinates(spec: NLocalizerSpec) -> FrameCoordinates | None:
    """The spec's ``coordinates`` as the geometry file's ``frame_coordinates`` (None without the section)."""
    c = spec.coordinates
    if c is None:
        return None
    if c.system == "leksell":
        return FrameCoordinates("leksell", leksell_from_fiducial(spec.frame.height), LEKSELL_AXES,
                                c.reference or LEKSELL_REFERENCE)
    return FrameCoordinates(c.system, np.asarray(c.T_frame_from_fiducial, dtype=float), "", c.reference)

