"""The solver's reuse of work already done (memos, the joint pass's model) gives the same numbers as doing it again."""

from __future__ import annotations

import numpy as np

from chic_register import section
from chic_register.pose import invert
from chic_register.section import fit_sections, joint_windows, section_model, section_windows, tube_frames
from chic_register.simulate import simulate_slice
from chic_register.solve import plane_crossings, prepare_geometry
from chic_register.tube_model import TubeModel, _crossing_jacobian, _exp_se3


def _near_end(neuro_geometry, seed=4):
    """A noisy slice near the body's end (helices close to their straight tubes: shared pixels) and its pose."""
    sim = simulate_slice(neuro_geometry, 5.0, 10.0, 30.0, 0.0, slice_thickness_mm=2.0, noise="rician", snr=20,
                         rng=np.random.default_rng(seed))
    T = invert(sim.truth.T_scanner_from_fiducial) @ sim.slice.T_scanner_from_image()
    return np.asarray(sim.slice.pixels, float), T


def test_joint_pass_reusing_the_first_draw_equals_drawing_again(neuro_geometry, monkeypatch):
    model, _ = prepare_geometry(neuro_geometry)
    pixels, T = _near_end(neuro_geometry)
    found = plane_crossings(model, T, margin_mm=1e-9)[3]
    args = (model, T, np.where(found, 0, -1), pixels, (0.5, 0.5), 2.0, 0.05)
    reused, _ = fit_sections(*args)
    whole = section.section_model
    monkeypatch.setattr(section, "_model_reusing", lambda model, T, q, tan, win, shape, *rest: whole(
        model, T, q, tan, win, *rest[:-1]))  # every pixel drawn again
    again, _ = fit_sections(*args)
    assert reused.fitted.sum() >= 8 and np.array_equal(reused.fitted, again.fitted)
    for a, b in ((reused.position_mm, again.position_mm), (reused.info, again.info), (reused.gain, again.gain)):
        assert np.array_equal(a, b, equal_nan=True)  # bit for bit


def test_model_taken_from_an_earlier_draw_is_the_whole_draw(neuro_geometry):
    model, _ = prepare_geometry(neuro_geometry)
    pixels, T = _near_end(neuro_geometry)
    q, tan, _, found = plane_crossings(model, T, margin_mm=1e-9)
    todo = np.flatnonzero(found)
    geo = (pixels.shape, (0.5, 0.5), 2.0)
    win = section_windows(model, q, tan, found, todo, *geo)
    jw = joint_windows(model, q, tan, found, todo, *geo, found.copy())[0]
    assert jw.owner.size > win.owner.size  # shared pixels: some to draw anew
    drawn = section_model(model, T, q, tan, win, (0.5, 0.5), 2.0)
    got = section._model_reusing(model, T, q, tan, jw, pixels.shape, (0.5, 0.5), 2.0, 5, True, (win, drawn))
    want = section_model(model, T, q, tan, jw, (0.5, 0.5), 2.0)
    assert all(np.array_equal(g, w) for g, w in zip(got, want))


def test_plane_crossings_memo_hands_out_fresh_arrays(neuro_geometry):
    model, _ = prepare_geometry(neuro_geometry)
    _, T = _near_end(neuro_geometry)
    fresh_model = TubeModel.from_geometry(neuro_geometry)  # its own (empty) memo
    for margin in (0.0, 1e-9, 5.0):
        first = plane_crossings(model, T, margin_mm=margin)
        for a in first:
            a[...] = 0  # a caller scribbling on its result
        again = plane_crossings(model, T, margin_mm=margin)
        want = plane_crossings(fresh_model, T.copy(), margin_mm=margin)
        assert all(np.array_equal(a, w) for a, w in zip(again, want))
    frames = tube_frames(model, T, *plane_crossings(model, T, margin_mm=1e-9)[:2])
    assert not any(f.flags.writeable for f in frames)  # shared by later calls: read-only


def test_crossing_jacobian_is_the_crossings_derivative(neuro_geometry):
    model, _ = prepare_geometry(neuro_geometry)
    _, T = _near_end(neuro_geometry)
    q, tan, _, found = plane_crossings(model, T, margin_mm=1e-9)
    J = _crossing_jacobian(q[found], tan[found])
    h = 1e-6
    for i in range(6):
        xi = np.zeros(6)
        xi[i] = h
        up = plane_crossings(model, T @ _exp_se3(xi), margin_mm=1e-9)[0][found]
        down = plane_crossings(model, T @ _exp_se3(-xi), margin_mm=1e-9)[0][found]
        assert np.allclose((up - down) / (2 * h), J[:, :, i], atol=1e-4)
