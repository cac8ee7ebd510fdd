"""Confirm finalists by simulation: simulated slices at the required poses, registered, errors measured.

Study cases from the requirements (three depths across the required range,
at tilt 0 and at the highest required tilt with a random azimuth), each a
series of the required protocol (``n_slices`` parallel slices, Rician noise
at the required SNR, the pixel size and slice thickness), registered by the
solver with its default options, as a user would: a design confirms only if
the solver trusts its poses. The measured errors are reported beside the
predicted bound.
"""

from __future__ import annotations

import math

import numpy as np

from chic_design.families import family_of
from chic_design.optimize.requirements import Requirements
from chic_design.spec import parse_spec
from chic_register.errors import ImprecisePose, NoLock
from chic_register.imaging.simulate import simulate_slice
from chic_register.model.pose import invert, slice_angles, wrap_deg
from chic_register.pipeline.register import register
from chic_register.studies.evaluate import StudyCase, normal_angle_deg

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


def simulate_parallel(geom, depth_mm: float, tilt_deg: float, azimuth_deg: float, twist_deg: float, n_slices: int,
                      spacing_mm: float, pixel_mm: float, thickness_mm: float, snr: float, rng, shape=None):
    """``n_slices`` parallel simulated slices ``spacing_mm`` apart (along their normal), centred on the pose, one
    fiducial pose in the scanner (a series as :class:`chic_register.precision.crlb.Protocol` models it), Rician noise."""
    shape = shape or image_shape(geom.body.outer_diameter, tilt_deg, pixel_mm)
    step = spacing_mm / math.cos(math.radians(tilt_deg))  # along the axis between parallel planes
    sims, truth = [], None
    for k in range(int(n_slices)):
        z = depth_mm + (k - (n_slices - 1) / 2.0) * step
        sim = simulate_slice(geom, z, tilt_deg, azimuth_deg, twist_deg, shape=shape,
                             pixel_spacing_mm=(pixel_mm, pixel_mm), slice_thickness_mm=thickness_mm,
                             noise="rician", snr=snr, rng=rng, T_scanner_from_fiducial=truth)
        truth = sim.truth.T_scanner_from_fiducial
        sims.append(sim)
    return sims


def _rms(a: np.ndarray) -> float | None:
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a**2))) if a.size else None


def _max(a: np.ndarray) -> float | None:
    a = a[np.isfinite(a)]
    return float(np.max(np.abs(a))) if a.size else None


def confirm_design(spec_data: dict, req_data: dict, draws: int, seed: int) -> dict:
    """Measured depth, normal-vector and twist errors (RMS, max) and refusals of one design.

    Each draw simulates the required protocol's ``n_slices`` parallel slices at a study pose and registers
    them with the solver's default options, as ``chic-register solve`` would (every trust check on, the
    precision limits included): a refused draw counts in ``no_lock`` (``imprecise``: refused only as too
    imprecise to trust). Errors are those of the middle slice's pose.
    """
    req = Requirements.model_validate(req_data)
    spec = parse_spec(spec_data, "<candidate>")
    geom = family_of(spec).geometry(spec)
    im = req.imaging
    spacing = im.slice_spacing if im.slice_spacing is not None else im.slice_thickness
    shape = image_shape(spec.body.outer_diameter, req.required.tilt_deg[1], im.pixel_size)
    rng = np.random.default_rng(seed)
    cases = study_cases(req)
    axial, normal, twist = (np.full((len(cases), draws), np.nan) for _ in range(3))
    imprecise, reasons = 0, {}
    for i, c in enumerate(cases):
        for k in range(draws):
            az = float(rng.uniform(0.0, 360.0)) if c.random_azimuth else 0.0
            sims = simulate_parallel(geom, c.depth_mm, c.tilt_deg, az, c.twist_deg, im.n_slices, spacing,
                                     im.pixel_size, im.slice_thickness, im.snr, rng, shape)
            try:
                reg = register([s.slice for s in sims], geom)
            except NoLock as exc:
                imprecise += isinstance(exc, ImprecisePose)
                why = exc.reason.removeprefix("<simulated>: ")
                kind = why.split(":")[0] if isinstance(exc, ImprecisePose) else why.split(" (")[0].split(" with ")[0]
                reasons[kind] = reasons.get(kind, 0) + 1
                continue
            m = len(sims) // 2
            sl, truth = sims[m].slice, sims[m].truth
            T_F_from_I = invert(reg.T_scanner_from_fiducial) @ sl.T_scanner_from_image()
            T_true = invert(truth.T_scanner_from_fiducial) @ sl.T_scanner_from_image()
            got = slice_angles(T_F_from_I)
            axial[i, k] = got.depth_mm - truth.angles.depth_mm
            normal[i, k] = normal_angle_deg(T_F_from_I, T_true)
            twist[i, k] = wrap_deg(got.twist_deg - truth.angles.twist_deg)
    n = axial.size
    locked = int(np.isfinite(axial).sum())
    by_case = {c.label: int(np.isfinite(axial[i]).sum()) for i, c in enumerate(cases)}
    return {"slices": n, "no_lock": n - locked, "imprecise": imprecise, "refusals": reasons, "locked_by_case": by_case,
            "depth_rms_mm": _rms(axial), "depth_max_mm": _max(axial), "normal_rms_deg": _rms(normal),
            "normal_max_deg": _max(normal), "twist_rms_deg": _rms(twist), "twist_max_deg": _max(twist),
            "settings": {"geometry": geom.name, "draws": draws, "seed": seed, "noise": "rician", "snr": im.snr,
                         "slice_thickness_mm": im.slice_thickness, "pixel_spacing_mm": [im.pixel_size] * 2,
                         "n_slices": im.n_slices, "slice_spacing_mm": spacing, "shape": list(shape),
                         "register_options": "default (chic-register solve)"}}
