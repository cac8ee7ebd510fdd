"""The fiducial's body (its cross-section and surfaces) and the optional tool frame.

The parts of a geometry file besides its tubes (docs/interfaces.md section 2):
``body`` (a round annulus for CHIC, a square frame for the Z-frame, a
rectangular box for an N-localizer), ``tool`` (the tool tip's frame in F) and
``frame_coordinates`` (a stereotactic frame's own coordinate system). :mod:`chic_register.model.geometry` builds
and validates them; both are importable from there too.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Body cross-sections: a round annulus (CHIC), a square frame (Z-frame) or a rectangular box (N-localizer).
BODY_SHAPES = ("annulus", "square", "box")


@dataclass(frozen=True)
class Body:
    """The body: ``length`` along z from 0, and its cross-section (mm).

    ``shape="annulus"`` (CHIC): a ring of ``outer_diameter`` / ``inner_diameter``.
    ``shape="square"`` (Z-frame): a square frame of outside side ``outer_side``
    around a square bore of side ``inner_side``, both centred on the z axis;
    its ``outer_diameter`` is then the circumscribed circle of the outside and
    ``inner_diameter`` the circle inscribed in the bore, so a reader that knows
    only circles still gets one enclosing the body and one inside the bore.
    ``shape="box"`` (N-localizer): a rectangular frame, outside ``outer_size``
    (x, y) around a bore ``inner_size`` (x, y), both centred on the z axis;
    the diameters as for the square.
    """

    length: float
    outer_diameter: float
    inner_diameter: float
    shape: str = "annulus"
    outer_side: float | None = None
    inner_side: float | None = None
    outer_size: tuple[float, float] | None = None
    inner_size: tuple[float, float] | None = None

    @classmethod
    def square(cls, length: float, outer_side: float, inner_side: float) -> "Body":
        """A square frame body (see the class docstring for its diameters)."""
        return cls(float(length), float(outer_side) * math.sqrt(2.0), float(inner_side), "square",
                   float(outer_side), float(inner_side))

    @classmethod
    def box(cls, length: float, outer_size, inner_size) -> "Body":
        """A rectangular frame body: outside ``outer_size`` = (x, y) mm around a bore ``inner_size``."""
        (ox, oy), (ix, iy) = (tuple(float(v) for v in outer_size), tuple(float(v) for v in inner_size))
        return cls(float(length), math.hypot(ox, oy), min(ix, iy), "box", outer_size=(ox, oy), inner_size=(ix, iy))

    @property
    def outer_half_mm(self) -> np.ndarray | None:
        """Half the outside width along x and y of a square or box body, (2,); None for an annulus."""
        if self.shape == "square":
            return np.array([self.outer_side, self.outer_side]) / 2
        if self.shape == "box":
            return np.array(self.outer_size) / 2
        return None

    @property
    def inner_half_mm(self) -> np.ndarray | None:
        """Half the bore's width along x and y of a square or box body, (2,); None for an annulus."""
        if self.shape == "square":
            return np.array([self.inner_side, self.inner_side]) / 2
        if self.shape == "box":
            return np.array(self.inner_size) / 2
        return None

    def bore_gap_mm(self, xy) -> np.ndarray:
        """Distance (mm) from in-body points ``xy`` (N, 2) to the bore surface; shape (N,)."""
        xy = np.atleast_2d(np.asarray(xy, dtype=float))
        h = self.inner_half_mm
        if h is not None:
            return np.hypot(np.maximum(np.abs(xy[:, 0]) - h[0], 0.0), np.maximum(np.abs(xy[:, 1]) - h[1], 0.0))
        return np.hypot(xy[:, 0], xy[:, 1]) - self.inner_diameter / 2

    def outside_gap_mm(self, xy) -> np.ndarray:
        """Distance (mm) from in-body points ``xy`` (N, 2) to the outside surface; shape (N,)."""
        xy = np.atleast_2d(np.asarray(xy, dtype=float))
        h = self.outer_half_mm
        if h is not None:
            return np.min(h[None, :] - np.abs(xy), axis=1)
        return self.outer_diameter / 2 - np.hypot(xy[:, 0], xy[:, 1])

    @property
    def outline_area_mm2(self) -> float:
        """Area enclosed by the outside surface in a section across z."""
        h = self.outer_half_mm
        if h is not None:
            return float(4 * h[0] * h[1])
        return math.pi * self.outer_diameter ** 2 / 4

    @property
    def bore_area_mm2(self) -> float:
        """Area of the bore in a section across z."""
        h = self.inner_half_mm
        if h is not None:
            return float(4 * h[0] * h[1])
        return math.pi * self.inner_diameter ** 2 / 4

    def to_dict(self) -> dict:
        out = {
            "length": float(self.length),
            "outer_diameter": float(self.outer_diameter),
            "inner_diameter": float(self.inner_diameter),
        }
        if self.shape == "square":  # CHIC files keep their content (and hash) unchanged
            out.update(shape=self.shape, outer_side=float(self.outer_side), inner_side=float(self.inner_side))
        elif self.shape == "box":
            out.update(shape=self.shape, outer_size=[float(v) for v in self.outer_size],
                       inner_size=[float(v) for v in self.inner_size])
        return out


def rigid_4x4(values) -> np.ndarray | None:
    """``values`` as a proper rigid 4x4 matrix (last row 0 0 0 1), or None."""
    try:
        T = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        return None
    if T.shape != (4, 4) or not np.all(np.isfinite(T)) or not np.allclose(T[3], [0, 0, 0, 1]):
        return None
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        return None
    return T


@dataclass(frozen=True, eq=False)
class ToolFrame:
    """The tool's frame relative to F: ``T_fiducial_from_tool`` (4x4, mm); its origin is the tool tip.

    Optional key ``tool`` of the geometry file (written only when the spec
    has a tool, so files without it keep their hash).
    """

    T_fiducial_from_tool: np.ndarray

    def __post_init__(self):
        T = rigid_4x4(self.T_fiducial_from_tool)
        if T is None:
            raise ValueError("tool.T_fiducial_from_tool must be a rigid 4x4 matrix (rotation, translation, 0 0 0 1)")
        object.__setattr__(self, "T_fiducial_from_tool", T)

    @classmethod
    def tip_offset(cls, tip_offset_mm: float) -> "ToolFrame":
        """A tool whose axes are F's and whose tip is on the axis at z = ``tip_offset_mm``."""
        T = np.eye(4)
        T[2, 3] = float(tip_offset_mm)
        return cls(T)

    @property
    def tip_mm(self) -> np.ndarray:
        """The tip in F (mm)."""
        return self.T_fiducial_from_tool[:3, 3].copy()

    def to_dict(self) -> dict:
        return {"T_fiducial_from_tool": [[float(v) for v in row] for row in self.T_fiducial_from_tool]}



#: Stereotactic coordinate systems a geometry file may name (``frame_coordinates.system``).
FRAME_SYSTEMS = ("leksell", "brw", "custom")


@dataclass(frozen=True, eq=False)
class FrameCoordinates:
    """A stereotactic frame's own coordinate system: optional key ``frame_coordinates`` of the geometry file.

    ``T_frame_from_fiducial`` (4x4, rigid, mm) maps points of F to the frame's
    coordinates (Leksell: X, Y, Z with the frame centre at (100, 100, 100));
    ``system`` names the convention (:data:`FRAME_SYSTEMS`), ``axes`` says in
    words where each axis points and ``reference`` where the convention is
    defined.
    """

    system: str
    T_frame_from_fiducial: np.ndarray
    axes: str = ""
    reference: str = ""

    def __post_init__(self):
        if self.system not in FRAME_SYSTEMS:
            raise ValueError(f"frame_coordinates.system is {self.system!r}; allowed: {', '.join(FRAME_SYSTEMS)}")
        T = rigid_4x4(self.T_frame_from_fiducial)
        if T is None:
            raise ValueError("frame_coordinates.T_frame_from_fiducial must be a rigid 4x4 matrix "
                             "(orthonormal rotation, det +1, last row 0 0 0 1)")
        object.__setattr__(self, "T_frame_from_fiducial", T)

    def to_frame_mm(self, points_f_mm) -> np.ndarray:
        """Points of F (N, 3) in the frame's coordinates (N, 3)."""
        p = np.atleast_2d(np.asarray(points_f_mm, dtype=float))
        return p @ self.T_frame_from_fiducial[:3, :3].T + self.T_frame_from_fiducial[:3, 3]

    def to_dict(self) -> dict:
        return {"system": self.system,
                "T_frame_from_fiducial": [[float(v) for v in row] for row in self.T_frame_from_fiducial],
                "axes": self.axes, "reference": self.reference}
