"""The paper's closed-form first guess (chic_register.guess.hypotheses) on hand-made blob centres.

No image: the blob centres are the tubes' exact centreline crossings with a plane at a known pose (image frame = the
plane's frame), so the ellipse through them is the cylinder's cut and the closed form must give that pose back.
"""

from __future__ import annotations

import numpy as np
import pytest

from chic_register.guess.ellipse import fit_ellipse_robust
from chic_register.guess.hypotheses import ellipse_layout, initial_hypotheses
from chic_register.model.pose import slice_frame
from chic_register.model.tube_model import plane_crossings, prepare_geometry


def _crossings(model, pose):
    T_F_from_I = slice_frame(*pose)
    q, _, _, inside = plane_crossings(model, T_F_from_I)
    return T_F_from_I, q[inside]


@pytest.mark.parametrize("pose", [(25.0, 20.0, 40.0, 10.0), (15.0, 35.0, 200.0, -30.0), (35.0, 0.0, 0.0, 60.0)])
def test_the_best_closed_form_guess_is_the_pose_of_exact_crossings(neuro_geometry, pose):
    """Nine exact crossings (neuro's tubes all on the 12.5 mm circle): the ellipse holds all nine, and the first guess
    is the true pose to rounding (the others are the sign choices' mirror poses, tens of degrees away)."""
    model, _ = prepare_geometry(neuro_geometry)
    T, xy = _crossings(model, pose)
    assert len(xy) == 9
    ell, inliers = fit_ellipse_robust(xy, 12.5)
    assert inliers.all()
    hyps = initial_hypotheses(model, xy, ell)
    assert 1 <= len(hyps) <= 6
    np.testing.assert_allclose(hyps[0], T, atol=1e-6)


def test_stray_blobs_off_the_ellipse_do_not_move_the_guess(neuro_geometry):
    """The same crossings shuffled, with two stray blobs (one at the ellipse's centre, one far outside): the robust
    ellipse leaves exactly the strays out and the first guess is still the pose."""
    model, _ = prepare_geometry(neuro_geometry)
    T, xy = _crossings(model, (22.0, 25.0, 120.0, -15.0))
    order = np.random.default_rng(0).permutation(len(xy))
    centre = xy.mean(axis=0)
    blobs = np.vstack([xy[order], centre, centre + (40.0, -35.0)])
    ell, inliers = fit_ellipse_robust(blobs, 12.5, tol_mm=0.5)
    assert inliers.tolist() == [True] * 9 + [False, False]
    hyps = initial_hypotheses(model, blobs[inliers], ell)
    np.testing.assert_allclose(hyps[0], T, atol=1e-6)


def test_no_blob_no_guess(neuro_geometry):
    model, _ = prepare_geometry(neuro_geometry)
    _, xy = _crossings(model, (25.0, 20.0, 40.0, 10.0))
    ell, _ = fit_ellipse_robust(xy, 12.5)
    assert initial_hypotheses(model, np.zeros((0, 2)), ell) == []


def test_the_closed_form_holds_for_chic_designs_only(neuro_geometry, needle_geometry, z001):
    """Axial lines and helices on one cylinder (both CHIC designs): the closed form applies; the Z-frame's diagonals
    rule it out (the generic first guess takes it)."""
    assert ellipse_layout(prepare_geometry(neuro_geometry)[0])
    assert ellipse_layout(prepare_geometry(needle_geometry)[0])
    assert not ellipse_layout(prepare_geometry(z001)[0])
