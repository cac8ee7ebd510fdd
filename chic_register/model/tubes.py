"""Tube centrelines in the fiducial frame F: the ``Tube`` protocol and its two kinds.

A tube is a fluid channel that shows in an image: a straight ``line``
(:class:`LineTube`, any direction) or a ``helix`` about the z axis of F
(:class:`HelixTube`). The CAD model sweeps its channels along these objects,
the geometry file is written from them, and the solver, simulator, renderer
and design checks ask them about their geometry through the methods of
:class:`Tube` (plane crossings, tangents, extension, sampling, the reach of a
slab's section) instead of switching on the kind. Importable from
:mod:`chic_register.model.geometry` too.
"""

from __future__ import annotations

import abc
import functools
import math
from dataclasses import dataclass, field, replace

import numpy as np

from chic_register.util.roots import bracketed_root


def _vec3(values) -> tuple[float, float, float]:
    a = np.asarray(values, dtype=float).reshape(3)
    return (float(a[0]), float(a[1]), float(a[2]))


class Tube(abc.ABC):
    """What every tube offers; :class:`LineTube` and :class:`HelixTube` implement it.

    Fields every kind has: ``id``, ``role``, ``diameter`` (mm), ``kind``
    (``"line"`` / ``"helix"``). Centreline parameters ``t`` run over [0, 1]
    from one end to the other; ``curved`` says whether the centreline bends
    (a straight one is exact from two points, needs no root refinement and
    no re-projection).
    """

    curved: bool = False

    @property
    @abc.abstractmethod
    def length_mm(self) -> float:
        """Arc length of the centreline."""

    @property
    @abc.abstractmethod
    def z_range(self) -> tuple[float, float]:
        """Lowest and highest z (mm) of the centreline."""

    @abc.abstractmethod
    def points(self, t) -> np.ndarray:
        """Centreline points at parameters ``t``; shape (N, 3)."""

    @abc.abstractmethod
    def tangents(self, t) -> np.ndarray:
        """Unit tangents at parameters ``t``; shape (N, 3)."""

    @abc.abstractmethod
    def point_at_z(self, z_mm) -> np.ndarray:
        """Centreline points at heights ``z_mm``; shape (N, 3)."""

    @abc.abstractmethod
    def tangents_at_z(self, z_mm) -> np.ndarray:
        """Unit tangents at heights ``z_mm``; shape (N, 3)."""

    @abc.abstractmethod
    def extended(self, ext_mm: float) -> "Tube":
        """The same centreline continued by ``ext_mm`` of arc length past both ends."""

    @abc.abstractmethod
    def intersect_plane(self, origin, normal) -> np.ndarray:
        """Every crossing of the centreline (within its extent) with a plane; shape (K, 3)."""

    @abc.abstractmethod
    def bracket_params(self, eps_mm: float = 1e-6) -> np.ndarray:
        """Parameters where plane crossings are bracketed (a hair beyond both ends); shape (K,), increasing."""

    @abc.abstractmethod
    def section_params(self, origin, normal, margin_mm: float) -> np.ndarray:
        """Parameters of the centreline points about which the plane's section of the tube is drawn; shape (K,)."""

    @abc.abstractmethod
    def fluid_volume_mm3(self, z_lo_mm: float, z_hi_mm: float) -> float:
        """Fluid volume between two heights (mm^3): pi a^2 times the centreline length there."""

    @abc.abstractmethod
    def sweep_path(self, builder):
        """The centreline as a CAD edge: ``builder.line(p0, p1)`` or ``builder.helix(...)`` (see cad.py)."""

    @abc.abstractmethod
    def describe(self) -> tuple[str, str, str]:
        """Kind, angle(s) (degrees) and pitch as text, for the design report's tube table."""

    @abc.abstractmethod
    def to_dict(self) -> dict:
        """The tube's entry of the geometry file."""

    def sample(self, step_mm: float = 0.5) -> np.ndarray:
        """Centreline polyline with points no more than ``step_mm`` apart; shape (N, 3)."""
        n = max(2, int(math.ceil(self.length_mm / step_mm)) + 1)
        return self.points(np.linspace(0.0, 1.0, n))

    def slab_reach_mm(self, cos_beta, slice_mm: float, scale: float = 1.0):
        """:func:`slab_reach_mm` for this tube's radius."""
        return slab_reach_mm(self.diameter / 2, cos_beta, slice_mm, scale)


def slab_reach_mm(radius_mm, cos_beta, slice_mm: float, scale: float = 1.0):
    """Arc length either side of a plane crossing over which a tube meets a slab about the plane.

    A ball of radius ``radius_mm`` on the centreline at arc length s from the
    crossing is ``s cos(beta)`` from the plane (``cos_beta`` = |tangent . normal|,
    floored at 1e-3); it reaches the slab of thickness ``slice_mm`` while
    ``s <= (radius + slice / 2) / cos(beta)``. Times ``scale`` (a safety factor).
    """
    return scale * (radius_mm + 0.5 * slice_mm) / np.maximum(cos_beta, 1e-3)


@dataclass(frozen=True)
class LineTube(Tube):
    """A straight channel: centreline from ``p0`` to ``p1`` (mm, frame F)."""

    id: str
    role: str
    p0: tuple[float, float, float]
    p1: tuple[float, float, float]
    diameter: float
    kind: str = field(default="line", init=False)
    curved = False

    def __post_init__(self):
        object.__setattr__(self, "p0", _vec3(self.p0))
        object.__setattr__(self, "p1", _vec3(self.p1))

    @functools.cached_property
    def direction(self) -> np.ndarray:
        """Unit vector from p0 to p1, shape (3,) (computed once: the renderer asks for it per section; read-only)."""
        d = np.subtract(self.p1, self.p0)
        d = d / np.linalg.norm(d)
        d.flags.writeable = False
        return d

    @functools.cached_property
    def length_mm(self) -> float:
        return float(np.linalg.norm(np.subtract(self.p1, self.p0)))

    @property
    def z_range(self) -> tuple[float, float]:
        return (min(self.p0[2], self.p1[2]), max(self.p0[2], self.p1[2]))

    @functools.cached_property
    def _ends(self) -> tuple[np.ndarray, np.ndarray]:
        """``(p0, p1 - p0)`` as arrays (computed once; read-only)."""
        p0, d = np.asarray(self.p0, dtype=float), np.subtract(self.p1, self.p0)
        p0.flags.writeable = d.flags.writeable = False
        return p0, d

    def points(self, t) -> np.ndarray:
        """Centreline points at parameters ``t`` in [0, 1]; shape (N, 3)."""
        p0, d = self._ends
        return line_points(p0, d, np.atleast_1d(np.asarray(t, dtype=float)))

    def tangents(self, t) -> np.ndarray:
        """Unit tangents at parameters ``t``; shape (N, 3)."""
        n = np.size(t)
        return np.broadcast_to(self.direction, (n, 3)).copy()

    def point_at_z(self, z_mm) -> np.ndarray:
        """Centreline points at heights ``z_mm`` (the line must not be horizontal); shape (N, 3)."""
        dz = self.p1[2] - self.p0[2]
        if abs(dz) < 1e-12:
            raise ValueError(f"tube {self.id} is horizontal: no unique point at a given z")
        return self.points((np.atleast_1d(z_mm) - self.p0[2]) / dz)

    def tangents_at_z(self, z_mm) -> np.ndarray:
        """Unit tangents at heights ``z_mm`` (toward p1); shape (N, 3)."""
        return np.tile(self.direction, (np.atleast_1d(z_mm).size, 1))

    def extended(self, ext_mm: float) -> "LineTube":
        """The same line continued by ``ext_mm`` of length past both ends."""
        d = self.direction
        return LineTube(self.id, self.role, np.asarray(self.p0) - ext_mm * d, np.asarray(self.p1) + ext_mm * d,
                        self.diameter)

    def intersect_plane(self, origin, normal) -> np.ndarray:
        """Where the centreline crosses the plane through ``origin`` with ``normal``.

        Returns shape (K, 3), K = 0 or 1: empty when the crossing lies outside
        the tube's extent or the line is parallel to the plane.
        """
        n = np.asarray(normal, dtype=float)
        p0 = np.asarray(self.p0)
        d = np.subtract(self.p1, self.p0)
        denom = float(n @ d)
        if abs(denom) < 1e-12:
            return np.empty((0, 3))
        t = float(n @ (np.asarray(origin, dtype=float) - p0)) / denom
        if t < -1e-12 or t > 1 + 1e-12:
            return np.empty((0, 3))
        return (p0 + t * d)[None, :]

    def bracket_params(self, eps_mm: float = 1e-6) -> np.ndarray:
        """The two ends, a hair beyond (a line crosses a plane at most once)."""
        eps = eps_mm / max(self.length_mm, 1e-9)
        return np.array([-eps, 1.0 + eps])

    def section_params(self, origin, normal, margin_mm: float) -> np.ndarray:
        """The crossing, clipped to the segment, whenever the tube reaches the plane (also when parallel to it).

        Exact for a line whatever point of it is used; ``margin_mm`` is not
        needed (the tube is reached when an end is within its radius). Shape (0,) or (1,).
        """
        d0 = float(normal @ (np.asarray(self.p0) - origin))
        d1 = float(normal @ (np.asarray(self.p1) - origin))
        if d0 * d1 > 0 and min(abs(d0), abs(d1)) > 0.5 * self.diameter:
            return np.empty(0)
        u = d0 / (d0 - d1) if abs(d0 - d1) > 1e-12 else 0.5
        return np.array([min(1.0, max(0.0, u))])

    def fluid_volume_mm3(self, z_lo_mm: float, z_hi_mm: float) -> float:
        """Exact for a straight channel cut by parallel planes (Cavalieri)."""
        a = self.diameter / 2
        dz = abs(self.direction[2])
        return math.pi * a * a * (z_hi_mm - z_lo_mm) / dz

    def sweep_path(self, builder):
        return builder.line(tuple(self.p0), tuple(self.p1))

    def describe(self) -> tuple[str, str, str]:
        """``line``, the angle of p0 about the axis, no pitch."""
        a0 = math.degrees(math.atan2(self.p0[1], self.p0[0])) % 360
        return "line", f"{a0:.1f}", "-"

    def to_dict(self) -> dict:
        return {
            "id": self.id,
            "role": self.role,
            "kind": "line",
            "p0": list(self.p0),
            "p1": list(self.p1),
            "diameter": float(self.diameter),
        }


@dataclass(frozen=True)
class HelixTube(Tube):
    """A helical channel about the z axis of F.

    The centreline at height z (``z0 <= z <= z1``) is at angle
    ``theta0_deg + pitch_deg_per_mm * (z - z0)`` and distance ``radius`` from the axis.
    """

    id: str
    role: str
    radius: float
    theta0_deg: float
    pitch_deg_per_mm: float
    z0: float
    z1: float
    diameter: float
    kind: str = field(default="helix", init=False)
    curved = True

    @property
    def z_range(self) -> tuple[float, float]:
        return (self.z0, self.z1)

    @property
    def length_mm(self) -> float:
        """Arc length of the centreline."""
        slope = self.radius * math.radians(self.pitch_deg_per_mm)
        return (self.z1 - self.z0) * math.hypot(1.0, slope)

    @property
    def theta1_deg(self) -> float:
        """Angle of the centreline at ``z1``."""
        return self.angle_deg_at(self.z1)

    def angle_deg_at(self, z_mm):
        """Centreline angle (degrees, unwrapped) at height ``z_mm``."""
        return self.theta0_deg + self.pitch_deg_per_mm * (np.asarray(z_mm, dtype=float) - self.z0)

    def z_at_angle(self, theta_deg):
        """Inverse of :meth:`angle_deg_at`: the height where the centreline has angle ``theta_deg``."""
        return self.z0 + (np.asarray(theta_deg, dtype=float) - self.theta0_deg) / self.pitch_deg_per_mm

    def point_at_z(self, z_mm) -> np.ndarray:
        """Centreline points at heights ``z_mm``; shape (N, 3)."""
        z = np.atleast_1d(np.asarray(z_mm, dtype=float))
        return helix_points(self.radius, self.theta0_deg, self.pitch_deg_per_mm, self.z0, z)

    def points(self, t) -> np.ndarray:
        """Centreline points at parameters ``t`` in [0, 1] (z = z0 + t (z1 - z0)); shape (N, 3)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return self.point_at_z(self.z0 + t * (self.z1 - self.z0))

    def tangents(self, t) -> np.ndarray:
        """Unit tangents (pointing toward increasing z) at parameters ``t``; shape (N, 3)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return helix_tangents(self.radius, self.theta0_deg, self.pitch_deg_per_mm, self.z0, self.z1, t)

    def tangents_at_z(self, z_mm) -> np.ndarray:
        """Unit tangents at heights ``z_mm`` (toward increasing z); shape (N, 3)."""
        return self.tangents((np.atleast_1d(np.asarray(z_mm, dtype=float)) - self.z0) / (self.z1 - self.z0))

    def extended(self, ext_mm: float) -> "HelixTube":
        """The same helix continued by ``ext_mm`` of arc length past both ends (memoised: the renderer asks
        for the same extension of each tube per section drawn)."""
        return _extended_helix(self, float(ext_mm))

    @functools.cached_property
    def _scan(self) -> tuple[np.ndarray, np.ndarray]:
        """``(zs, points)``: the heights :meth:`intersect_plane` brackets its crossings on and the centreline
        points there (the same for every plane: computed once; read-only)."""
        turns = abs(self.pitch_deg_per_mm) * (self.z1 - self.z0) / 360.0
        zs = np.linspace(self.z0, self.z1, int(64 * max(1.0, turns)) + 2)
        pts = self.point_at_z(zs)
        zs.flags.writeable = pts.flags.writeable = False
        return zs, pts

    def intersect_plane(self, origin, normal) -> np.ndarray:
        """Every crossing of the centreline with the plane through ``origin`` with ``normal``.

        Returns shape (K, 3), sorted by z. A helix can cross a steep plane
        more than once; all crossings inside ``[z0, z1]`` are returned.
        """
        n = np.asarray(normal, dtype=float)
        o = np.asarray(origin, dtype=float)
        r, th0, pitch, z0 = self.radius, self.theta0_deg, self.pitch_deg_per_mm, self.z0

        def f(z):  # n . (point_at_z(z) - o), as point_at_z computes it, on a scalar (math's radians, cos and sin:
            # numpy's, without the per-call cost of a ufunc on one number)
            th = math.radians(th0 + pitch * (z - z0))
            return float(n @ (np.array([r * math.cos(th), r * math.sin(th), z]) - o))

        zs, pts = self._scan
        vals = (pts - o) @ n
        roots = []
        a, b = vals[:-1], vals[1:]
        for i in np.flatnonzero((a == 0.0) | (a * b < 0)).tolist():  # a sign change (or a zero) in [zs[i], zs[i+1])
            if a[i] == 0.0:
                roots.append(zs[i])
            else:
                roots.append(bracketed_root(f, zs[i], zs[i + 1], a[i], b[i], xtol=1e-12))
        if vals[-1] == 0.0:
            roots.append(zs[-1])
        if not roots:
            return np.empty((0, 3))
        return self.point_at_z(np.array(roots))

    def bracket_params(self, eps_mm: float = 1e-6) -> np.ndarray:
        """Samples no more than 2 mm apart (at least 9), a hair beyond both ends."""
        eps = eps_mm / max(self.length_mm, 1e-9)
        n = max(9, int(math.ceil(self.length_mm / 2.0)) + 1)
        return np.linspace(-eps, 1.0 + eps, n)

    def section_params(self, origin, normal, margin_mm: float) -> np.ndarray:
        """Crossings of the centreline extended by ``margin_mm`` at both ends (so a plane cutting the
        tube's end near its face still draws the cut part); parameters may lie outside [0, 1]."""
        pts = self.extended(margin_mm).intersect_plane(origin, normal)
        return (pts[:, 2] - self.z0) / (self.z1 - self.z0)

    def fluid_volume_mm3(self, z_lo_mm: float, z_hi_mm: float) -> float:
        """Exact to within the helix's curvature (radius of curvature >> channel radius)."""
        a = self.diameter / 2
        part = replace(self, theta0_deg=float(self.angle_deg_at(z_lo_mm)), z0=z_lo_mm, z1=z_hi_mm)
        return math.pi * a * a * part.length_mm

    def sweep_path(self, builder):
        return builder.helix(pitch=360.0 / abs(self.pitch_deg_per_mm), height=self.z1 - self.z0,
                             radius=self.radius, lefthand=self.pitch_deg_per_mm < 0,
                             theta0_deg=self.theta0_deg, z0=self.z0)

    def describe(self) -> tuple[str, str, str]:
        """``helix``, its start and end angles, its pitch (deg/mm)."""
        return "helix", f"{self.theta0_deg:.1f} -> {float(self.theta1_deg):.1f}", f"{self.pitch_deg_per_mm:+.4g}"

    def to_dict(self) -> dict:
        return {
            "id": self.id,
            "role": self.role,
            "kind": "helix",
            "radius": float(self.radius),
            "theta0_deg": float(self.theta0_deg),
            "pitch_deg_per_mm": float(self.pitch_deg_per_mm),
            "z0": float(self.z0),
            "z1": float(self.z1),
            "diameter": float(self.diameter),
        }


def line_points(p0, d, t: np.ndarray) -> np.ndarray:
    """Points (N, 3) ``p0 + t d`` of straight centrelines at parameters ``t`` (N,) (:class:`LineTube`'s formula;
    ``p0``, ``d`` (3,), or (N, 3): one line per point)."""
    return p0 + t[:, None] * d


def helix_points(radius, theta0_deg, pitch_deg_per_mm, z0, z: np.ndarray) -> np.ndarray:
    """Centreline points (N, 3) at heights ``z`` (N,) of helices about the z axis (:class:`HelixTube`'s formula;
    the parameters numbers, or arrays (N,): one helix per point)."""
    th = np.radians(theta0_deg + pitch_deg_per_mm * (z - z0))
    out = np.empty((z.size, 3))
    np.multiply(radius, np.cos(th), out=out[:, 0])
    np.multiply(radius, np.sin(th), out=out[:, 1])
    out[:, 2] = z
    return out


def helix_tangents(radius, theta0_deg, pitch_deg_per_mm, z0, z1, t: np.ndarray) -> np.ndarray:
    """Unit tangents (N, 3) toward increasing z at parameters ``t`` (N,) (``z = z0 + t (z1 - z0)``) of helices
    about the z axis (:class:`HelixTube`'s formula; the parameters numbers, or arrays (N,))."""
    th = np.radians(theta0_deg + pitch_deg_per_mm * ((z0 + t * (z1 - z0)) - z0))
    w = np.radians(pitch_deg_per_mm) * radius
    v = np.empty((th.size, 3))
    np.multiply(-w, np.sin(th), out=v[:, 0])
    np.multiply(w, np.cos(th), out=v[:, 1])
    v[:, 2] = 1.0
    return v / np.sqrt(np.add.reduce(v * v, axis=1, keepdims=True))  # (np.linalg.norm's own sum)


@functools.lru_cache(maxsize=256)
def _extended_helix(tube: HelixTube, ext_mm: float) -> HelixTube:
    """:meth:`HelixTube.extended`, memoised on the (frozen, hashable) tube and the extension."""
    dz = ext_mm * (tube.z1 - tube.z0) / tube.length_mm
    return HelixTube(tube.id, tube.role, tube.radius, float(tube.angle_deg_at(tube.z0 - dz)),
                     tube.pitch_deg_per_mm, tube.z0 - dz, tube.z1 + dz, tube.diameter)


def sample_centreline(tube: Tube, step_mm: float = 0.5) -> np.ndarray:
    """Centreline polyline with points no more than ``step_mm`` apart: ``tube.sample(step_mm)``; shape (N, 3)."""
    return tube.sample(step_mm)
