"""Monte Carlo check that reported pose covariances are calibrated (used by the tests and the benchmark).

Simulated slices at known poses are registered; each pose error
``delta`` (with ``T_est = T_true @ exp(delta)``, order
:data:`chic_register.precision.crlb.PARAMETER_ORDER`) is normalised by the covariance
reported with it. Calibrated covariances give squared Mahalanobis lengths
with a chi-square distribution of 6 degrees of freedom (mean 6), and a
predicted TRE whose RMS matches the measured one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from chic_register.detect.blobs import centres_xy_mm, detect_blobs
from chic_register.errors import NoLock
from chic_register.fit.refine import refine
from chic_register.imaging.simulate import simulate_slice
from chic_register.model.body import Body
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.pose import invert
from chic_register.model.tube_model import prepare_geometry
from chic_register.model.tubes import LineTube
from chic_register.pipeline.register import register
from chic_register.precision.uncertainty import mahalanobis2, registration_uncertainty, target_point


def z001_geometry(diameter_mm: float = 3.0) -> FiducialGeometry:
    """3D Slicer's z001 Z-frame as seven ``line`` tubes: a 60 mm cube, axial rods at x, y = +-30, diagonals on
    the faces x = +30 (from (30, 30, 0) to (30, -30, 60)), y = +30 and x = -30 (docs/interfaces.md section 1)."""
    rods = [("A0", (30, 30, 0), (30, 30, 60)), ("A1", (30, -30, 0), (30, -30, 60)),
            ("A2", (-30, 30, 0), (-30, 30, 60)), ("A3", (-30, -30, 0), (-30, -30, 60)),
            ("Z0", (30, 30, 0), (30, -30, 60)), ("Z1", (-30, 30, 0), (30, 30, 60)),
            ("Z2", (-30, -30, 0), (-30, 30, 60))]
    tubes = [LineTube(i, "other", p0, p1, diameter_mm) for i, p0, p1 in rods]
    return FiducialGeometry("zframe-z001", Body(60.0, 90.0, 0.0), tubes)


def pose_error(T_true: np.ndarray, T_est: np.ndarray) -> np.ndarray:
    """``delta`` (deg, mm) with ``T_est = T_true @ exp(delta)`` (rotation vector, then translation)."""
    from scipy.spatial.transform import Rotation  # deferred: loads scipy only when used (one-shot start-up)

    D = invert(np.asarray(T_true, float)) @ np.asarray(T_est, float)
    return np.concatenate([np.degrees(Rotation.from_matrix(D[:3, :3]).as_rotvec()), D[:3, 3]])


@dataclass(frozen=True)
class Calibration:
    """Summary of a Monte Carlo run: squared Mahalanobis lengths and TREs per locked draw."""

    mahalanobis2: np.ndarray
    tre_mm: np.ndarray
    predicted_tre_mm: np.ndarray
    n_no_lock: int

    @property
    def mahalanobis_mean(self) -> float:
        return float(np.mean(self.mahalanobis2))

    @property
    def tre_ratio(self) -> float:
        """Predicted over measured RMS TRE (1 when calibrated)."""
        return math.sqrt(np.mean(self.predicted_tre_mm ** 2) / np.mean(self.tre_mm ** 2))


def run_calibration(geom: FiducialGeometry, poses, draws_per_pose: int, seed: int, *, snr: float = 20.0,
                    solver: str = "register", target_F_mm=None, prior: bool = False) -> Calibration:
    """Simulate ``draws_per_pose`` Rician slices at each (depth, tilt, azimuth, twist) and compare errors with
    the reported covariance. ``solver``: ``"register"`` (the full solver) or ``"refine"`` (detection and the
    solver's Gauss-Newton refinement started at the truth). ``prior``: give ``register`` the true pose as its
    orientation prior (what resolves a self-symmetric layout such as the Z-frame; see ``SolveOptions.prior``)."""
    model, _ = prepare_geometry(geom)
    target = target_point(geom, target_F_mm)
    rng = np.random.default_rng(seed)
    m2, tre, pred, fails = [], [], [], 0
    for pose in poses:
        for _ in range(int(draws_per_pose)):
            sim = simulate_slice(geom, *pose, noise="rician", snr=snr, rng=rng)
            sl = sim.slice
            if solver == "register":
                try:
                    extra = {"prior": sim.truth.T_scanner_from_fiducial} if prior else {}
                    reg = register([sl], geom, target_F_mm=target, **extra)
                except NoLock:
                    fails += 1
                    continue
                T_est, u = reg.T_scanner_from_fiducial, reg.uncertainty
            else:
                blobs = detect_blobs(sl.pixels, sl.pixel_spacing_mm, float(np.median(model.diameter_mm)))
                xy, S = centres_xy_mm(blobs, sl), sl.T_scanner_from_image()
                fit = refine(model, [xy], [S], invert(sim.truth.T_scanner_from_fiducial))
                u = registration_uncertainty(model, fit, [xy], [S], [sl], [blobs], target)
                T_est = invert(fit.T_F_from_scanner)
            d = pose_error(sim.truth.T_scanner_from_fiducial, T_est)
            m2.append(mahalanobis2(d, u.covariance))
            D = invert(sim.truth.T_scanner_from_fiducial) @ T_est
            p = np.asarray(target)
            tre.append(float(np.linalg.norm(D[:3, :3] @ p + D[:3, 3] - p)))
            pred.append(u.predicted_tre_mm)
    return Calibration(np.array(m2), np.array(tre), np.array(pred), fails)
