"""Two fiducials in one scan: each registered without the other's sections, and one expressed in the other's frame.

A CHIC fiducial on a tool inside a stereotactic frame shows both in the same
slices. Registered alone, each sees the other's sections as bright blobs:
extra candidates that may be taken for its own tubes, and strays where its
own tubes run that its verification rightly refuses. :func:`register_frames`
registers each geometry alone first; then every locked one's predicted
sections are cut out of the slices (:func:`mask_sections`: the pixels set to
their surroundings' level and marked ``lost``, so no stage reads them) and
the others are registered again on what is left, in turns, until the poses
settle (two rounds). A fiducial that locks only once the other's sections are
gone is found that way too.

:func:`relative_pose` then gives the first fiducial's pose in the second's
frame (its stereotactic coordinates when the geometry names them) and the
covariance of its target point there, from both poses' covariances
(independent measurements of the same image: their errors add).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from chic_register.errors import NoLock
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.pose import invert
from chic_register.model.pose_params import default_target
from chic_register.model.slices import Slice
from chic_register.pipeline.register import register
from chic_register.pipeline.results import Registration
from chic_register.precision.points import PointUncertainty, point_covariance_F, rotate_covariance

#: The cut-out around each predicted section: its half-length across the plane (half a diameter over the cosine
#: of the tube's angle to the normal, at most :data:`MAX_STRETCH` diameters) plus this many diameters for the blur
#: real images add (blobs 1.5-2.5 diameters wide), plus two pixels.
BLUR_DIAMETERS = 1.0
MAX_STRETCH = 4.0
#: Rounds of registering each fiducial on the slices without the others' sections.
ROUNDS = 2


@dataclass(frozen=True)
class FrameResult:
    """One geometry's outcome in a multi-fiducial scan: its registration, or the reason it has none."""

    geometry: FiducialGeometry
    registration: Registration | None
    reason: str = ""

    @property
    def ok(self) -> bool:
        return self.registration is not None


@dataclass(frozen=True)
class RelativePose:
    """Fiducial A in the frame of fiducial B.

    ``T_b_from_a`` (4x4, mm) maps F_A to B's frame: its stereotactic
    coordinates (``frame`` names the system) when B's geometry has
    ``frame_coordinates``, else F_B. ``target_a_mm`` (3,) is A's target point
    (its tool tip, else its body centre) in F_A, ``target_b_mm`` (3,) the same
    point in B's frame, ``covariance_mm2`` (3, 3) its covariance there from both
    poses' covariances; ``sigma_mm`` (3,) the 1-sigma per axis and ``tre_mm``
    the RMS 3-D error.
    """

    T_b_from_a: np.ndarray
    frame: str
    target_a_mm: np.ndarray
    target_b_mm: np.ndarray
    covariance_mm2: np.ndarray

    @property
    def sigma_mm(self) -> np.ndarray:
        return PointUncertainty(self.covariance_mm2).sigma_mm

    @property
    def tre_mm(self) -> float:
        return PointUncertainty(self.covariance_mm2).rms_mm

    def to_dict(self) -> dict:
        return {"frame": self.frame,
                "T_frame_from_fiducial": [[float(v) for v in row] for row in self.T_b_from_a],
                "target_F_mm": [float(v) for v in self.target_a_mm],
                "target_frame_mm": [float(v) for v in self.target_b_mm],
                "sigma_mm": [float(v) for v in self.sigma_mm],
                "predicted_tre_mm": round(self.tre_mm, 6),
                "covariance_mm2": [[float(v) for v in row] for row in self.covariance_mm2]}


def section_mask(sl: Slice, geom: FiducialGeometry, T_scanner_from_fiducial: np.ndarray) -> np.ndarray:
    """Boolean (rows, cols): the pixels of ``sl`` within reach of a section of ``geom`` at its pose."""
    T_F_from_I = invert(np.asarray(T_scanner_from_fiducial, float)) @ sl.T_scanner_from_image()
    o, n = T_F_from_I[:3, 3], T_F_from_I[:3, 2]
    T_I_from_F = invert(T_F_from_I)
    rows, cols = sl.shape
    rs, cs = sl.pixel_spacing_mm
    rr, cc = np.mgrid[0:rows, 0:cols]
    mask = np.zeros(sl.shape, bool)
    for tube in geom.tubes:
        d = float(tube.diameter)
        for p in tube.intersect_plane(o, n):
            u = np.asarray(tube.tangents_at_z(p[2]), float).reshape(-1, 3)[0]
            cos = abs(float(np.dot(u, n))) / max(float(np.linalg.norm(u)), 1e-12)
            half = 0.5 * d * min(1.0 / max(cos, 1e-6), MAX_STRETCH) + BLUR_DIAMETERS * d + 2 * max(rs, cs)
            q = T_I_from_F[:3, :3] @ p + T_I_from_F[:3, 3]
            mask |= np.hypot((cc * cs - q[0]), (rr * rs - q[1])) <= half
    return mask


def mask_sections(sl: Slice, mask: np.ndarray) -> Slice:
    """``sl`` with the pixels of ``mask`` set to the median of the ring around them and marked ``lost``."""
    if not mask.any():
        return sl
    from scipy import ndimage as ndi  # deferred: only a scan with two fiducials needs it

    ring = ndi.binary_dilation(mask, iterations=3) & ~mask
    pixels = np.array(sl.pixels, dtype=float, copy=True)
    level = float(np.median(pixels[ring])) if ring.any() else float(np.median(pixels))
    pixels[mask] = level
    lost = mask if sl.lost is None else (sl.lost | mask)
    return dataclasses.replace(sl, pixels=pixels, lost=lost)


def _without(slices: list[Slice], others: list[tuple[FiducialGeometry, Registration]]) -> list[Slice]:
    out = []
    for sl in slices:
        m = np.zeros(sl.shape, bool)
        for g, reg in others:
            m |= section_mask(sl, g, reg.T_scanner_from_fiducial)
        out.append(mask_sections(sl, m))
    return out


def register_frames(slices: list[Slice], geometries: list[FiducialGeometry], *, options_for=None,
                    **kwargs) -> list[FrameResult]:
    """Register each of ``geometries`` on the same ``slices``, none taking another's sections (module docstring).

    ``options_for(i)`` may give geometry ``i`` its own
    :class:`~chic_register.options.SolveOptions` (a frame's prior); other
    keyword arguments go to :func:`~chic_register.pipeline.register.register`
    for all. Returns one :class:`FrameResult` per geometry, in order.
    """
    if len(geometries) < 2:
        raise ValueError("register_frames needs two or more geometries")

    def solve(i: int, on: list[Slice]) -> FrameResult:
        opts = options_for(i) if options_for is not None else None
        try:
            return FrameResult(geometries[i], register(on, geometries[i], options=opts, **kwargs))
        except NoLock as exc:
            return FrameResult(geometries[i], None, exc.reason)

    results = [solve(i, slices) for i in range(len(geometries))]
    for _ in range(ROUNDS):
        before = [r.registration for r in results]
        for i in range(len(geometries)):
            others = [(r.geometry, r.registration) for j, r in enumerate(results) if j != i and r.ok]
            if others:
                again = solve(i, _without(slices, others))
                if again.ok or not results[i].ok:
                    results[i] = again
                else:  # locked with the others' sections present, not without them: they were its own
                    results[i] = FrameResult(geometries[i], None,
                                             f"locked only on sections another fiducial explains ({again.reason})")
        if all(a is b for a, b in zip(before, [r.registration for r in results])):
            break
    return results


def relative_pose(a: Registration, geom_a: FiducialGeometry, b: Registration, geom_b: FiducialGeometry,
                  target_a_mm=None) -> RelativePose:
    """Fiducial A (``a``, ``geom_a``) in B's frame, with its target point's covariance there (:class:`RelativePose`).

    A point ``p`` of F_A is ``u = T_sB^-1 T_sA p`` in F_B; perturbing A's pose
    moves it by ``R_BA (r_A x p + t_A)``, perturbing B's by ``-(r_B x u + t_B)``
    (the pose parameters of :mod:`chic_register.model.pose_params`); the two
    covariances add, and B's frame coordinates turn the result by their rotation.
    """
    Ta, Tb = np.asarray(a.T_scanner_from_fiducial, float), np.asarray(b.T_scanner_from_fiducial, float)
    T_B_from_A = invert(Tb) @ Ta
    frame = geom_b.frame_coordinates
    M = frame.T_frame_from_fiducial if frame is not None else np.eye(4)
    p = np.asarray(target_a_mm if target_a_mm is not None else default_target(geom_a), float)
    u = T_B_from_A[:3, :3] @ p + T_B_from_A[:3, 3]
    if a.uncertainty is None or b.uncertainty is None:
        C = np.full((3, 3), np.nan)
    else:  # in F_B: A's point error turned into B's axes, plus B's own at that point
        C = (rotate_covariance(point_covariance_F(a.uncertainty.covariance, p), T_B_from_A[:3, :3])
             + point_covariance_F(b.uncertainty.covariance, u))
    name = frame.system if frame is not None else f"F of {geom_b.name}"
    return RelativePose(M @ T_B_from_A, name, p, M[:3, :3] @ u + M[:3, 3], rotate_covariance(C, M[:3, :3]))
