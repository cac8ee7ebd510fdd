"""The distortion hunt's cases: slices as real scanners show them (scale, gradient non-linearity, shading, tissue).

:func:`distorted_case` builds one from a hunt case (:mod:`chic_register.studies.damage`) and
:func:`apparent_pose` is the pose its image shows, against which a solve is judged: the pose the solver's own
model fits to the tubes' exact crossings, moved where the scanner shows them.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from chic_register.fit.refine import refine
from chic_register.imaging.scanner import ScannerEffects, apply_scanner_effects, body_footprint, image_centre_mm
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.pose import invert
from chic_register.model.slices import Slice
from chic_register.model.tube_model import plane_crossings, prepare_geometry
from chic_register.studies.damage import Case, build_case

#: How far (mm, per in-plane axis) the isocentre lies from the image's centre: a field of view is set about it.
ISOCENTRE_OFFSET_MM = 20.0


def random_effects(rng: np.random.Generator, sl: Slice | None = None) -> ScannerEffects:
    """Effects as clinical scanners show them: a scale of 0.1-1 % per axis (either sign), a non-linearity of 0-4 mm
    at 100 mm, shading up to 60 % and up to six tissue regions; about an isocentre within
    :data:`ISOCENTRE_OFFSET_MM` of the centre of ``sl`` (the scanner's origin without a slice)."""
    scale = rng.uniform(0.001, 0.01, 2) * rng.choice([-1.0, 1.0], 2)
    effects = ScannerEffects((float(scale[0]), float(scale[1])), float(rng.uniform(0.0, 4.0)),
                             float(rng.uniform(0.0, 0.6)), int(rng.integers(0, 7)))
    if sl is None:
        return effects
    du, dv = rng.uniform(-ISOCENTRE_OFFSET_MM, ISOCENTRE_OFFSET_MM, 2)
    iso = image_centre_mm(sl) + du * np.asarray(sl.col_dir, float) + dv * np.asarray(sl.row_dir, float)
    return dataclasses.replace(effects, isocentre_mm=tuple(float(v) for v in iso))


def apparent_pose(geom: FiducialGeometry, T_scanner_from_fiducial: np.ndarray, sl: Slice,
                  effects: ScannerEffects) -> np.ndarray:
    """The ``T_scanner_from_fiducial`` the image of ``sl`` under ``effects`` shows: the pose refined (the solver's
    Gauss-Newton) on the tubes' exact crossings with the slice, each moved where the scanner shows it."""
    model, _ = prepare_geometry(geom)
    S = sl.T_scanner_from_image()
    X = invert(np.asarray(T_scanner_from_fiducial, float))
    q, _, _, inside = plane_crossings(model, X @ S)
    k = np.flatnonzero(inside)
    if k.size < 3:
        return np.asarray(T_scanner_from_fiducial, float)
    u, v = np.asarray(sl.col_dir, float), np.asarray(sl.row_dir, float)
    world = (S @ np.c_[q[k], np.zeros(k.size), np.ones(k.size)].T).T[:, :3]
    shown = world + effects.displacement_mm(world, u, v)
    xy = np.full((len(model.ids), 2), np.nan)
    xy[k] = np.c_[(shown - S[:3, 3]) @ u, (shown - S[:3, 3]) @ v]
    blobs = xy[k]
    assign = np.full(len(model.ids), -1)
    assign[k] = np.arange(k.size)
    fit = refine(model, [blobs], [S], X, gates_mm=(), final_iters=8, assign0=[assign])
    return invert(fit.T_F_from_scanner)


def distorted_case(case: Case, geom: FiducialGeometry, rng: np.random.Generator):
    """``(slice, apparent T_scanner_from_fiducial, effects)`` of a hunt case drawn with scanner effects."""
    sl, T_true, _ = build_case(case, geom)
    effects = random_effects(rng, sl)
    return (*distort(sl, T_true, geom, effects, rng), effects)


def distort(sl: Slice, T_scanner_from_fiducial: np.ndarray, geom: FiducialGeometry, effects: ScannerEffects,
            rng: np.random.Generator) -> tuple[Slice, np.ndarray]:
    """``(sl as a scanner with effects shows it, the pose that image shows)``: a simulated MR slice (the fluid at
    1) of ``geom`` at ``T_scanner_from_fiducial``, its tissue kept out of the fiducial's body."""
    body = body_footprint(sl, T_scanner_from_fiducial, 0.5 * geom.body.outer_diameter, geom.body.length)
    pixels = apply_scanner_effects(sl, effects, rng, signal=1.0, no_tissue=body)
    return dataclasses.replace(sl, pixels=pixels), apparent_pose(geom, T_scanner_from_fiducial, sl, effects)
