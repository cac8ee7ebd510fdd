"""Predicted precision of a candidate over the required depth/tilt range (the search's third objective).

The bound itself lives in :mod:`chic_register.precision.crlb` (Cramér-Rao lower bound of
the pose from the image model). This module only chooses where to evaluate it:
``DEPTH_SAMPLES`` depths across ``required.depth_mm`` at the lowest and the
highest required tilt, the tilted ones at ``AZIMUTHS_DEG`` (a tilt toward a
diametric tube and one between two), and reports the worst case of each
quantity (a design is as good as its worst required pose). The same bounds
also predict the solver's own error estimate (:mod:`.trust`), worst over the poses.
"""

from __future__ import annotations

import numpy as np

from chic_design.optimize.requirements import Requirements
from chic_design.optimize.trust import SOLVER_OVER_CRLB, predicted_solver_error, solver_limits
from chic_register.model.geometry import FiducialGeometry
from chic_register.precision.crlb import Protocol, pose_crlb

DEPTH_SAMPLES = 3
AZIMUTHS_DEG = (0.0, 90.0)
QUALITY = "fast"  # the bound's renderer sampling during the search (within ~3 % of "default")


def sample_poses(req: Requirements) -> list[tuple[float, float, float]]:
    """(depth_mm, tilt_deg, azimuth_deg) poses the bound is evaluated at."""
    d0, d1 = req.required.depth_mm
    t0, t1 = req.required.tilt_deg
    poses = []
    for z in np.linspace(d0, d1, DEPTH_SAMPLES):
        for t in sorted({float(t0), float(t1)}):
            for a in (AZIMUTHS_DEG if t > 0 else (0.0,)):
                poses.append((float(z), t, a))
    return poses


def protocol_of(req: Requirements):
    """The bound's imaging protocol from the requirements (slices ``slice_thickness`` apart by default)."""
    im = req.imaging
    spacing = im.slice_spacing if im.slice_spacing is not None else im.slice_thickness
    return Protocol(pixel_size_mm=im.pixel_size, slice_thickness_mm=im.slice_thickness, snr=im.snr,
                    n_slices=im.n_slices, slice_spacing_mm=spacing)


def method(req: Requirements) -> str:
    """How the third objective was computed, in words (for the report)."""
    poses = sample_poses(req)
    depths = sorted({z for z, _, _ in poses})
    tilts = sorted({t for _, t, _ in poses})
    return (f"Cramér-Rao bound (chic_register.precision.crlb, renderer quality '{QUALITY}'), worst TRE over {len(poses)} "
            f"poses: depths {', '.join(f'{z:g}' for z in depths)} mm x tilts {', '.join(f'{t:g}' for t in tilts)} "
            f"deg (tilted ones at azimuths {', '.join(f'{a:g}' for a in AZIMUTHS_DEG)} deg), twist 0, "
            f"{req.imaging.n_slices} slice(s); the solver's 3-sigma error predicted as the bound's worst "
            f"direction x {SOLVER_OVER_CRLB:g} (measured) x 3")


def predicted_precision(geom: FiducialGeometry, req: Requirements) -> dict:
    """Worst case over :func:`sample_poses` of the bound's SDs and TRE at the target (mm, deg), and of the
    solver's predicted 3-sigma error (``solver_tre_mm`` at the frame centre, ``solver_rot_deg``; :mod:`.trust`)."""
    protocol = protocol_of(req)
    target = np.asarray(req.required.target_mm, dtype=float)
    limits = solver_limits()
    worst = {"tre_mm": 0.0, "sd_depth_mm": 0.0, "sd_normal_deg": 0.0, "sd_twist_deg": 0.0,
             "solver_tre_mm": 0.0, "solver_rot_deg": 0.0}
    at, solver_at, solver_excess = None, None, -1.0
    for z, t, a in sample_poses(req):
        try:
            b = pose_crlb(geom, z, t, a, 0.0, protocol, target_F_mm=target, quality=QUALITY)
        except ValueError:  # the slices do not determine the pose
            return {**{k: float("inf") for k in worst}, "worst_pose": [z, t, a], "method": "crlb"}
        s_tre, s_rot = predicted_solver_error(b.covariance, geom.body.length, limits)
        vals = {"tre_mm": float(b.tre_mm), "sd_depth_mm": float(b.sd_depth_mm),
                "sd_normal_deg": float(b.sd_normal_deg), "sd_twist_deg": float(b.sd_twist_deg),
                "solver_tre_mm": s_tre, "solver_rot_deg": s_rot}
        if not all(np.isfinite(v) for v in vals.values()):
            return {**{k: float("inf") for k in worst}, "worst_pose": [z, t, a], "solver_worst_pose": [z, t, a],
                    "method": "crlb"}
        if vals["tre_mm"] > worst["tre_mm"]:
            at = [z, t, a]
        excess = max(s_tre / limits.tre_mm, s_rot / limits.rot_deg)
        if excess > solver_excess:
            solver_at, solver_excess = [z, t, a], excess
        worst = {k: max(worst[k], vals[k]) for k in worst}
    return {**worst, "worst_pose": at, "solver_worst_pose": solver_at, "method": "crlb"}
