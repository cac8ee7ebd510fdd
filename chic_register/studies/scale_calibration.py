"""Calibrate a geometry file to one printed fiducial on one scanner: its scale, measured from a volume.

A volume (or several slices) determines the image's scale along its rows and
columns (:mod:`chic_register.fit.scale`), which is the print's size against
its geometry file times the scanner's gradient calibration. Both stay as they
are from scan to scan, so a geometry file scaled by it registers later single
slices, which cannot tell a scale from a tilt, without one.
"""

from __future__ import annotations

import datetime
import math

import numpy as np

from chic_register.errors import NoLock
from chic_register.model.geometry import FiducialGeometry, scaled_geometry
from chic_register.pipeline.results import Registration
from chic_register.version import __version__


def calibration_factor(reg: Registration) -> tuple[float, float]:
    """``(factor, sd)``: the length factor of F that registers ``reg``'s images rigidly (the inverse-variance mean
    of its in-plane scale corrections, ``1 / (1 + s)``), and its standard deviation. :class:`NoLock` for a
    registration of one slice (it reads a scale as a tilt) or without a scale estimate."""
    if len(reg.slices) < 2 or reg.scale is None:
        raise NoLock("calibration needs a volume or several slices that register together: one slice alone reads "
                     "the image's scale as a tilt", {"n_slices": len(reg.slices)})
    s, sd = np.asarray(reg.scale.scale[:2], float), np.asarray(reg.scale.scale_sd[:2], float)
    if not np.all(np.isfinite(sd) & (sd > 0)):
        raise NoLock("the image's scale is not determined by these slices")
    w = 1.0 / sd**2
    mean, mean_sd = float(np.sum(w * s) / np.sum(w)), float(1.0 / math.sqrt(np.sum(w)))
    factor = 1.0 / (1.0 + mean)
    return factor, mean_sd * factor**2


def calibrated_geometry(geom: FiducialGeometry, reg: Registration, scans: list[str]) -> FiducialGeometry:
    """``geom`` scaled by :func:`calibration_factor` of ``reg`` (the registration of ``scans``), the calibration
    recorded in its ``source``."""
    factor, sd = calibration_factor(reg)
    record = {
        "scans": [str(p) for p in scans],
        "slices_used": len(reg.slices),
        "date": datetime.date.today().isoformat(),
        "generator": f"chic-register {__version__}",
        "factor": round(factor, 7),
        "factor_sd": round(sd, 7),
        "image_scale": reg.scale.to_dict(),
        "from_geometry_sha256": geom.to_dict()["sha256"],
    }
    return scaled_geometry(geom, factor, record)
