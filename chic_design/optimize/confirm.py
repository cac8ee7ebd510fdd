"""Confirm finalists by simulation: simulated slices at the required poses, registered, errors measured.

Uses the project's simulation study (:func:`chic_register.evaluate.run_study`)
with cases taken from the requirements (three depths across the required
range, at tilt 0 and at the highest required tilt with a random azimuth),
Rician noise at the required SNR, the required pixel size and slice
thickness. The measured errors are reported beside the predicted bound.
"""

from __future__ import annotations

import math

import numpy as np

from chic_register.evaluate import StudyCase, run_study

from ..layout import fiducial_geometry
from ..spec import parse_spec
from .requirements import Requirements

DEPTHS = 3


def study_cases(req: Requirements) -> list[StudyCase]:
    d0, d1 = req.required.depth_mm
    t1 = req.required.tilt_deg[1]
    cases = []
    for z in np.linspace(d0, d1, DEPTHS):
        cases.append(StudyCase("normal", f"z{z:g}", float(z), 0.0))
        if t1 > 0:
            cases.append(StudyCase("tilted", f"z{z:g}-t{t1:g}", float(z), float(t1), random_azimuth=True))
    return cases


def image_shape(outer_diameter_mm: float, tilt_deg: float, pixel_mm: float) -> tuple[int, int]:
    """A square field of view holding the body's section at ``tilt_deg`` with a margin."""
    side = 1.4 * outer_diameter_mm / math.cos(math.radians(tilt_deg)) / pixel_mm + 16
    n = int(math.ceil(side / 8.0) * 8)
    return (n, n)


def _rms(a: np.ndarray) -> float | None:
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a**2))) if a.size else None


def _max(a: np.ndarray) -> float | None:
    a = a[np.isfinite(a)]
    return float(np.max(np.abs(a))) if a.size else None


def confirm_design(spec_data: dict, req_data: dict, draws: int, seed: int) -> dict:
    """Measured depth, normal-vector and twist errors (RMS, max) and no-locks of one design."""
    req = Requirements.model_validate(req_data)
    spec = parse_spec(spec_data, "<candidate>")
    geom = fiducial_geometry(spec)
    px = req.imaging.pixel_size
    res = run_study(geom, draws=draws, seed=seed, noise="rician", snr=req.imaging.snr,
                    slice_thickness_mm=req.imaging.slice_thickness, pixel_spacing_mm=(px, px),
                    shape=image_shape(spec.body.outer_diameter, req.required.tilt_deg[1], px),
                    cases=study_cases(req))
    n = res.axial_mm.size
    locked = int(np.isfinite(res.axial_mm).sum())
    return {"slices": n, "no_lock": n - locked, "depth_rms_mm": _rms(res.axial_mm),
            "depth_max_mm": _max(res.axial_mm), "normal_rms_deg": _rms(res.normal_deg),
            "normal_max_deg": _max(res.normal_deg), "twist_rms_deg": _rms(res.twist_deg),
            "twist_max_deg": _max(res.twist_deg), "settings": res.settings}
