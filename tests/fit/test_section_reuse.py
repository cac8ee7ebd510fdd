"""The section fit's reuse of work already done (the joint pass's windows and model) gives the same numbers as doing
it again.
"""

from __future__ import annotations

import numpy as np
import pytest

from chic_register.fit import section
from chic_register.fit.section import fit_sections, section_model
from chic_register.fit.windows import joint_windows, section_windows
from chic_register.model.tube_model import plane_crossings, prepare_geometry, section_extent
from tests.helpers import near_end_slice


@pytest.mark.parametrize("rician_sigma", [0.0, 0.05])
def test_joint_pass_reusing_the_first_draw_equals_drawing_again(neuro_geometry, monkeypatch, rician_sigma):
    model, _ = prepare_geometry(neuro_geometry)
    pixels, T = near_end_slice(neuro_geometry)
    found = plane_crossings(model, T, margin_mm=1e-9)[3]
    args = (model, T, np.where(found, 0, -1), pixels, (0.5, 0.5), 2.0, 0.05)
    reused, win = fit_sections(*args, rician_sigma=rician_sigma)
    assert win.shared  # the joint pass has work, on the windows the first fit drew ahead
    real = section.joint_pass
    # (fit_sections' positional arguments: ..., n_pix, reach, at_crossing, rician_sigma, ahead): nothing handed on,
    # the joint windows chosen and every pixel drawn again
    monkeypatch.setattr(section, "joint_pass", lambda *a: real(*a[:19], None, None, a[21], None))
    again, _ = fit_sections(*args, rician_sigma=rician_sigma)
    # and from windows given (no reach): the joint pass takes the first draw's pixels where it has them
    monkeypatch.setattr(section, "joint_pass", real)
    given, _ = fit_sections(*args, windows=win, rician_sigma=rician_sigma)
    assert reused.fitted.sum() >= 8
    for other in (again, given):
        assert np.array_equal(reused.fitted, other.fitted)
        for a, b in ((reused.position_mm, other.position_mm), (reused.info, other.info), (reused.gain, other.gain)):
            assert np.array_equal(a, b, equal_nan=True)  # bit for bit


def test_window_pixels_pairs_are_every_pixel_against_every_tube(neuro_geometry):
    model, _ = prepare_geometry(neuro_geometry)
    pixels, T = near_end_slice(neuro_geometry)
    q, tan, _, found = plane_crossings(model, T, margin_mm=1e-9)
    todo = np.flatnonzero(found)
    reach = section.window_pixels(model, q, tan, found, todo, pixels.shape, (0.5, 0.5), 2.0, 1.5)
    # the definition, pixel by tube: within a pixel of another found tube's section box (its tube's width across)
    half_len, _, u = section_extent(model, tan, 2.0)
    u = np.where((np.abs(u).sum(axis=1) > 0)[:, None], u, [1.0, 0.0])
    dx = (reach.cols * 0.5)[:, None] - q[:, 0][None]
    dy = (reach.rows * 0.5)[:, None] - q[:, 1][None]
    along, across = np.abs(dx * u[:, 0] + dy * u[:, 1]), np.abs(dx * u[:, 1] - dy * u[:, 0])
    hit = (along < half_len + 0.5) & (across < 0.5 * model.diameter_mm + 0.5) & found[None]
    hit[np.arange(reach.own.size), reach.own] = False
    p, o = np.nonzero(hit)
    assert p.size > 0 and np.array_equal(reach.pair_p, p) and np.array_equal(reach.pair_o, o)
    own = np.arange(reach.own.size), reach.own
    far = (along[own] > half_len[reach.own] + 0.75) | (across[own] > 0.5 * model.diameter_mm[reach.own] + 0.75)
    assert far.any() and np.array_equal(reach.far, far)


def test_model_taken_from_an_earlier_draw_is_the_whole_draw(neuro_geometry):
    model, _ = prepare_geometry(neuro_geometry)
    pixels, T = near_end_slice(neuro_geometry)
    q, tan, _, found = plane_crossings(model, T, margin_mm=1e-9)
    todo = np.flatnonzero(found)
    geo = (pixels.shape, (0.5, 0.5), 2.0)
    win = section_windows(model, q, tan, found, todo, *geo)
    jw = joint_windows(model, q, tan, found, todo, *geo, found.copy())[0]
    assert jw.owner.size > win.owner.size  # shared pixels: some to draw anew
    drawn = section_model(model, T, q, tan, win, (0.5, 0.5), 2.0)
    got = section.model_reusing(model, T, q, tan, jw, pixels.shape, (0.5, 0.5), 2.0, 5, True, (win, drawn))
    want = section_model(model, T, q, tan, jw, (0.5, 0.5), 2.0)
    assert all(np.array_equal(g, w) for g, w in zip(got, want))


def test_section_model_without_slopes_is_the_same_level(neuro_geometry):
    model, _ = prepare_geometry(neuro_geometry)
    pixels, T = near_end_slice(neuro_geometry)
    q, tan, _, found = plane_crossings(model, T, margin_mm=1e-9)
    win = section_windows(model, q, tan, found, np.flatnonzero(found), pixels.shape, (0.5, 0.5), 2.0)
    for exact in (True, False):
        S, Sx, Sy = section_model(model, T, q, tan, win, (0.5, 0.5), 2.0, 5, exact)
        level, no_x, no_y = section_model(model, T, q, tan, win, (0.5, 0.5), 2.0, 5, exact, slopes=False)
        assert ((S > 0) & (S < 1)).sum() > 50 and np.abs(Sx).max() > 0
        assert np.array_equal(level, S) and no_x is None and no_y is None
