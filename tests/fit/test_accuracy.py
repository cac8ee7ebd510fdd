"""Accuracy models of the fit (chic_register.fit.accuracy): centroid offsets of curved sections, template shifts,
and a section pulled off alone left out of the fit.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from chic_register.fit.refine import assign_blobs
from chic_register.imaging.simulate import simulate_slice
from chic_register.model.pose import invert, rigid, slice_frame
from chic_register.model.tube_model import TubeModel, plane_crossings, prepare_geometry
from chic_register.studies.damage import pose_error


def test_centroid_offsets_predict_the_detected_centres_at_the_true_pose(neuro_geometry):
    # steep cut, thick slice: curved helix sections and touching blobs; at the true pose the model's
    # centroids must land on the detector's centres (the crossings alone are off by up to a pixel)
    from chic_register.detect.blobs import detect_blobs
    from chic_register.fit.accuracy import centroid_offsets
    from chic_register.fit.refine import assign_blobs

    sim = simulate_slice(neuro_geometry, 25, 60, 75, 20, slice_thickness_mm=2.0)
    b = detect_blobs(sim.slice.pixels, sim.slice.pixel_spacing_mm, 3.0)
    xy = np.stack([b.centres_rc[:, 1] * 0.5, b.centres_rc[:, 0] * 0.5], axis=1)
    model = TubeModel.from_geometry(neuro_geometry)
    T_F_from_I = invert(sim.truth.T_scanner_from_fiducial) @ sim.slice.T_scanner_from_image()
    q, _, _, inside = plane_crossings(model, T_F_from_I)
    a = assign_blobs(q, inside, xy, 1.5)
    off, pure = centroid_offsets(neuro_geometry.tubes, model, T_F_from_I, a, b.footprints, (0.5, 0.5), 2.0,
                                 purity=True)
    k = np.flatnonzero(a >= 0)
    before = np.linalg.norm(q[k] - xy[a[k]], axis=1)
    after = np.linalg.norm(q[k] + off[k] - xy[a[k]], axis=1)
    assert before.max() > 0.1  # mm: the bias is there...
    assert after.max() < 0.005  # ...and the model explains it
    assert np.all((pure > 0) & (pure <= 1.0 + 1e-9))


def _true_setup(geom, sim):
    from chic_register.detect.blobs import detect_blobs

    b = detect_blobs(sim.slice.pixels, sim.slice.pixel_spacing_mm, 3.0)
    xy = np.stack([b.centres_rc[:, 1] * 0.5, b.centres_rc[:, 0] * 0.5], axis=1)
    model = TubeModel.from_geometry(geom)
    T_F_from_I = invert(sim.truth.T_scanner_from_fiducial) @ sim.slice.T_scanner_from_image()
    q, _, _, inside = plane_crossings(model, T_F_from_I)
    return model, b, xy, T_F_from_I, q, assign_blobs(q, inside, xy, 1.5)


def test_template_shifts_find_a_known_in_plane_shift(neuro_geometry):
    # noise-free: at the true pose every template sits on its section (shift 0, gain 1); with the pose
    # moved by delta in the image plane, every template must report that the sections lie delta away
    from chic_register.fit.accuracy import template_shifts

    sim = simulate_slice(neuro_geometry, 20, 30, 40, 15, slice_thickness_mm=0.0)
    model, b, _, T, _, a = _true_setup(neuro_geometry, sim)
    k = a >= 0
    assert k.sum() == 9
    shift, gain, ok = template_shifts(neuro_geometry.tubes, model, T, a, sim.slice.pixels, b.footprints,
                                      (0.5, 0.5), 0.0)
    assert ok[k].all() and not ok[~k].any()
    assert np.abs(shift[k]).max() < 0.003 and np.allclose(gain[k], 1.0, atol=0.01)
    delta = np.array([0.06, -0.04])  # mm, image x and y
    moved = T @ rigid(np.eye(3), np.array([delta[0], delta[1], 0.0]))  # image coordinates shifted by -delta
    shift, _, ok = template_shifts(neuro_geometry.tubes, model, moved, a, sim.slice.pixels, b.footprints,
                                   (0.5, 0.5), 0.0)
    assert ok[k].all()
    assert np.abs(shift[k] - delta).max() < 0.006, shift[k]  # first order: within a tenth of the shift


def test_template_fit_is_more_precise_than_the_centroid(neuro_geometry):
    # the same noisy slices (uniform +-0.05), evaluated at the true pose: the template positions scatter
    # clearly less than the centroid model's (about 0.33 vs 0.5 noise sigmas in pixels)
    from chic_register.fit.accuracy import centroid_offsets, template_shifts

    rng = np.random.default_rng(7)
    tpl, cen = [], []
    for _ in range(12):
        sim = simulate_slice(neuro_geometry, 25, 0, 0, 30, slice_thickness_mm=0.0, noise="uniform",
                             noise_level=0.05, rng=rng)
        model, b, xy, T, q, a = _true_setup(neuro_geometry, sim)
        k = np.flatnonzero(a >= 0)
        shift, _, ok = template_shifts(neuro_geometry.tubes, model, T, a, sim.slice.pixels, b.footprints,
                                       (0.5, 0.5), 0.0)
        off, _ = centroid_offsets(neuro_geometry.tubes, model, T, a, b.footprints, (0.5, 0.5), 0.0)
        assert ok[k].all()
        tpl.append(shift[k])
        cen.append(xy[a[k]] - off[k] - q[k])
    tpl, cen = np.concatenate(tpl), np.concatenate(cen)
    rms_tpl, rms_cen = float(np.sqrt(np.mean(tpl**2))), float(np.sqrt(np.mean(cen**2)))
    assert rms_tpl < 0.8 * rms_cen, (rms_tpl, rms_cen)


def test_a_section_pulled_off_alone_is_left_out_and_the_pose_refitted(neuro_geometry):
    """Hand-made section measurements at the true crossings, one moved 0.3 mm against a 0.01 mm noise: that tube is
    left out and the refit lands on the truth; with every section where it belongs, none is."""
    from chic_register.fit.accuracy import drop_section_outliers
    from chic_register.fit.refine import refine
    from chic_register.model.tube_model import plane_crossings
    from chic_register.options import SolveOptions

    model = prepare_geometry(neuro_geometry)[0]
    T_F_from_S = slice_frame(20.0, 25.0, 40.0, 10.0)
    q, _, _, inside = plane_crossings(model, T_F_from_S)
    K = len(model.ids)
    xy = q[:, :2].copy()
    L = np.repeat(np.eye(2)[None] / 0.01, K, axis=0)  # 0.01 mm sigma in x and y
    rng = np.random.default_rng(3)
    xy += rng.normal(0.0, 0.01, xy.shape)
    moved = 4
    xy[moved] += (0.3, 0.0)
    S = np.eye(4)
    assign = [np.where(inside, np.arange(K), -1)]
    fit = refine(model, [xy], [S], T_F_from_S, gates_mm=(), final_iters=6, assign0=assign, strict_ends=False,
                 weights=[L])
    fit = dataclasses.replace(fit, measurements=[(xy, L, 0.01)])
    out = drop_section_outliers(model, fit, [S], SolveOptions())
    assert out is not fit and out.assignments[0][moved] == -1 and out.n_matched == fit.n_matched - 1
    _, rot_before = pose_error(invert(fit.T_F_from_scanner), invert(T_F_from_S), model.length_mm)
    _, rot_after = pose_error(invert(out.T_F_from_scanner), invert(T_F_from_S), model.length_mm)
    assert rot_after < 0.5 * rot_before
    xy[moved] -= (0.3, 0.0)
    clean = refine(model, [xy], [S], T_F_from_S, gates_mm=(), final_iters=6, assign0=assign, strict_ends=False,
                   weights=[L])
    clean = dataclasses.replace(clean, measurements=[(xy, L, 0.01)])
    assert drop_section_outliers(model, clean, [S], SolveOptions()) is clean
