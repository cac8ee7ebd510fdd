"""Pose conventions: slice angles (depth, tilt, azimuth, twist) and rigid transforms.

A slice frame S has its x and y axes in the image plane (x = direction of
increasing column, y = increasing row) and z = x × y, the image normal.

The slice pose relative to the fiducial frame F is given by four numbers
(docs/interfaces.md section 4):

- ``depth_mm``: z in F where the fiducial axis crosses the image plane;
- ``tilt_deg``: angle between the image normal and the fiducial axis, in [0, 90];
- ``azimuth_deg``: direction in F's xy plane toward which the normal leans;
- ``twist_deg``: rotation of the image about the fiducial axis.

They define ``R_F_from_S = Rz(azimuth) Ry(tilt) Rz(twist - azimuth)`` and an
S origin at ``(0, 0, depth_mm)``: at tilt 0, twist is simply the angle of the
image x axis from F's +x. When an image's normal points down the fiducial axis
(z of S against +z of F), the angles are reported for the equivalent frame
``(x, -y, -z)``, so tilt stays in [0, 90].
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from chic_register.options import SolveOptions


def rot_z(angle_deg: float) -> np.ndarray:
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_y(angle_deg: float) -> np.ndarray:
    a = math.radians(angle_deg)
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rigid(R: np.ndarray, t) -> np.ndarray:
    """4x4 homogeneous transform from rotation ``R`` (3x3) and translation ``t`` (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float)
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a 4x4 rigid transform."""
    R = T[:3, :3]
    return rigid(R.T, -R.T @ T[:3, 3])


def apply(T: np.ndarray, points) -> np.ndarray:
    """Apply a 4x4 transform to points of shape (N, 3) (or (3,))."""
    p = np.asarray(points, dtype=float)
    return p @ T[:3, :3].T + T[:3, 3]


def wrap_deg(angle_deg: float) -> float:
    """Wrap an angle to (-180, 180]."""
    a = (angle_deg + 180.0) % 360.0 - 180.0
    return 180.0 if a == -180.0 else a


@dataclass(frozen=True)
class SliceAngles:
    """Where a slice cuts the fiducial (see module docstring)."""

    depth_mm: float
    tilt_deg: float
    azimuth_deg: float
    twist_deg: float


def slice_frame(depth_mm: float, tilt_deg: float, azimuth_deg: float = 0.0, twist_deg: float = 0.0) -> np.ndarray:
    """``T_F_from_S`` (4x4) of the slice with these angles, S origin on the fiducial axis."""
    R = rot_z(azimuth_deg) @ rot_y(tilt_deg) @ rot_z(twist_deg - azimuth_deg)
    return rigid(R, (0.0, 0.0, depth_mm))


def _upward(T_F_from_S: np.ndarray):
    """``(R, n, p)``: the frame's rotation, turned half about its x axis when its normal points down (n_z < 0),
    that normal (R's third column) and the frame's origin, all in F."""
    R = np.asarray(T_F_from_S[:3, :3], dtype=float)
    p = np.asarray(T_F_from_S[:3, 3], dtype=float)
    if R[2, 2] < 0:
        R = R @ np.diag([1.0, -1.0, -1.0])
    return R, R[:, 2], p


def _depth(n: np.ndarray, p: np.ndarray) -> float:
    """Where the plane through ``p`` with normal ``n`` crosses the z axis (mm); NaN when parallel to it."""
    return float(n @ p / n[2]) if abs(n[2]) > 1e-9 else float("nan")


def slice_depth_mm(T_F_from_S: np.ndarray) -> float:
    """``slice_angles(T_F_from_S).depth_mm`` alone (the trust check's question, without the angles' work)."""
    _, n, p = _upward(T_F_from_S)
    return _depth(n, p)


def slice_angles(T_F_from_S: np.ndarray) -> SliceAngles:
    """Inverse of :func:`slice_frame` for any frame S of the image plane (any origin in it).

    ``depth_mm`` is NaN when the plane is parallel to the axis.
    """
    R, n, p = _upward(T_F_from_S)
    tilt = math.degrees(math.acos(min(1.0, max(-1.0, n[2]))))
    depth = _depth(n, p)
    azimuth = math.degrees(math.atan2(n[1], n[0])) if math.hypot(n[0], n[1]) > 1e-12 else 0.0
    M = rot_y(-tilt) @ rot_z(-azimuth) @ R
    gamma = math.degrees(math.atan2(M[1, 0], M[0, 0]))
    return SliceAngles(depth, tilt, wrap_deg(azimuth), wrap_deg(azimuth + gamma))


def rotation_deg(R1: np.ndarray, R2: np.ndarray) -> float:
    """Angle (degrees) of the rotation between two 3x3 rotations."""
    return math.degrees(math.acos(min(1.0, max(-1.0, (float(np.trace(R1.T @ R2)) - 1) / 2))))


def near_prior(T_F_from_scanner: np.ndarray, opts: "SolveOptions") -> bool:
    """True without a prior, else when the pose's rotation lies within ``prior_max_deg`` of the prior's."""
    if opts.prior is None:
        return True
    R_prior = np.asarray(opts.prior, float)[:3, :3]  # R_scanner_from_fiducial
    return rotation_deg(T_F_from_scanner[:3, :3].T, R_prior) <= opts.prior_max_deg
