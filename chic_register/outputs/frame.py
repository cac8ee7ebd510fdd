"""A pose in a stereotactic frame's own coordinates, and points mapped between the scanner and the frame.

A geometry with ``frame_coordinates`` (:class:`~chic_register.model.body.FrameCoordinates`)
fixes ``T_frame_from_fiducial``; a registration gives ``T_scanner_from_fiducial``.
Together: ``T_frame_from_scanner = T_frame_from_fiducial @ inverse(T_scanner_from_fiducial)``
(scanner LPS mm -> frame mm). ``solve`` reports it (:func:`frame_report`),
``chic-register map`` maps points with it (:func:`map_points`), each with the
position uncertainty the pose's covariance gives it
(:mod:`chic_register.precision.points`): the frame is rigid to the fiducial,
so only the pose is uncertain.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from chic_register.model.body import FrameCoordinates
from chic_register.model.pose import apply, invert
from chic_register.precision.points import PointUncertainty, point_covariance_F, rotate_covariance

#: The directions ``map`` converts to.
DIRECTIONS = ("frame", "scanner")
_LPS_TO_RAS_3 = np.diag([-1.0, -1.0, 1.0])


def _rows(T) -> list:
    return [[float(v) for v in row] for row in np.asarray(T)]


@dataclass(frozen=True, eq=False)
class FramePose:
    """The registration in a frame's coordinates: ``T_frame_from_scanner`` (scanner LPS mm -> frame mm), its
    inverse, and the frame's description (``system``, ``axes``, ``reference``)."""

    frame: FrameCoordinates
    T_scanner_from_fiducial: np.ndarray

    @property
    def system(self) -> str:
        return self.frame.system

    @property
    def T_frame_from_scanner(self) -> np.ndarray:
        return self.frame.T_frame_from_fiducial @ invert(np.asarray(self.T_scanner_from_fiducial, dtype=float))

    @property
    def T_scanner_from_frame(self) -> np.ndarray:
        return invert(self.T_frame_from_scanner)

    def to_dict(self) -> dict:
        return {"system": self.frame.system, "axes": self.frame.axes, "reference": self.frame.reference,
                "T_frame_from_fiducial": _rows(self.frame.T_frame_from_fiducial),
                "T_frame_from_scanner": _rows(self.T_frame_from_scanner),
                "T_scanner_from_frame": _rows(self.T_scanner_from_frame)}


def frame_report(reg, geom, target_F_mm=None) -> dict | None:
    """The ``frame_coordinates`` object of ``solve --json`` for a registration ``reg`` of ``geom``; None when
    the geometry names no frame. With ``target_F_mm`` (3,): also ``target_frame_mm``, that point of F in the
    frame's coordinates."""
    frame = getattr(geom, "frame_coordinates", None)
    if frame is None:
        return None
    out = FramePose(frame, reg.T_scanner_from_fiducial).to_dict()
    if target_F_mm is not None:
        out["target_F_mm"] = [float(v) for v in target_F_mm]
        out["target_frame_mm"] = [float(v) for v in frame.to_frame_mm(target_F_mm)[0]]
    return out


@dataclass(frozen=True, eq=False)
class MappedPoint:
    """One point in both coordinate systems: ``frame_mm`` (3,) and ``scanner_lps_mm`` (3,); ``covariance_F_mm2``
    (3x3, F's axes) is its position uncertainty from the pose (None when the pose has no covariance)."""

    label: str
    frame_mm: np.ndarray
    scanner_lps_mm: np.ndarray
    covariance_F_mm2: np.ndarray | None

    def position_mm(self, system: str, frame_system: str) -> np.ndarray:
        """The position in ``system``: ``LPS``, ``RAS`` or the frame's name ``frame_system``."""
        if system == frame_system:
            return self.frame_mm
        return self.scanner_lps_mm * np.diag(_LPS_TO_RAS_3) + 0.0 if system == "RAS" else self.scanner_lps_mm


def map_points(points_mm, to: str, T_scanner_from_fiducial, frame: FrameCoordinates, covariance_deg_mm=None,
               labels=None) -> list[MappedPoint]:
    """Map ``points_mm`` (N, 3) to the frame's coordinates (``to="frame"``, points in scanner LPS) or to the
    scanner's LPS (``to="scanner"``, points in frame coordinates); each with its covariance in F's axes under
    the pose covariance ``covariance_deg_mm`` (6x6, :data:`~chic_register.model.pose_params.PARAMETER_ORDER`)."""
    if to not in DIRECTIONS:
        raise ValueError(f"to is {to!r}; allowed: {', '.join(DIRECTIONS)}")
    P = np.atleast_2d(np.asarray(points_mm, dtype=float)).reshape(-1, 3)
    T_sf = np.asarray(T_scanner_from_fiducial, dtype=float)
    T_frF = frame.T_frame_from_fiducial
    if to == "frame":
        p_F = apply(invert(T_sf), P)
        frame_mm, scanner_mm = apply(T_frF, p_F), P
    else:
        p_F = apply(invert(T_frF), P)
        frame_mm, scanner_mm = P, apply(T_sf, p_F)
    labels = list(labels) if labels is not None else [f"P{i + 1}" for i in range(len(P))]
    cov = None if covariance_deg_mm is None else np.asarray(covariance_deg_mm, dtype=float)
    frame_mm, scanner_mm = frame_mm + 0.0, scanner_mm + 0.0  # no -0.0 in the files
    return [MappedPoint(labels[i], frame_mm[i], scanner_mm[i],
                        None if cov is None else point_covariance_F(cov, p_F[i])) for i in range(len(P))]


def point_uncertainty(point: MappedPoint, system: str, frame: FrameCoordinates,
                      T_scanner_from_fiducial) -> PointUncertainty | None:
    """``point``'s uncertainty in the axes of ``system`` (``LPS``, ``RAS`` or ``frame.system``); None without a
    covariance."""
    if point.covariance_F_mm2 is None:
        return None
    if system == frame.system:
        R = frame.T_frame_from_fiducial[:3, :3]
    else:
        R = np.asarray(T_scanner_from_fiducial, dtype=float)[:3, :3]
        if system == "RAS":
            R = _LPS_TO_RAS_3 @ R
    return PointUncertainty(rotate_covariance(point.covariance_F_mm2, R))
