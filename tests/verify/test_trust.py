"""The trust checks (chic_register.verify.trust) on hand-made fits: residuals, matched tubes, depth and rivals.

Each fit is built by hand at a known pose of neuro (9 tubes, H0-H2 the helices that give the depth) for one
0.5 mm-pixel slice, so every limit is worked out from the defaults: an RMS of 0.5 px = 0.25 mm, a single residual of
1.5 px = 0.75 mm, at least 6 tubes with 2 helices.
"""

from __future__ import annotations

import numpy as np
import pytest

from chic_register.errors import AmbiguousFit, NoLock
from chic_register.fit.refine import Fit
from chic_register.model.pose import slice_frame
from chic_register.model.slices import Slice
from chic_register.model.tube_model import prepare_geometry
from chic_register.options import SolveOptions
from chic_register.verify.trust import check_trust, depth_tube_name

POSE = slice_frame(25.0, 20.0, 40.0, 10.0)  # T_F_from_scanner, the image frame being the scanner's
SLICE = Slice(np.zeros((64, 64)), (0.5, 0.5), slice_thickness_mm=2.0, source="hand")


def hand_fit(residuals_mm, tubes=range(9), T=POSE) -> Fit:
    """A fit at ``T`` matching ``tubes`` (indices into neuro's D0-D3, H0-H2, O0, O1) with these residuals."""
    tubes = list(tubes)
    a = np.full(9, -1)
    a[tubes] = tubes
    r = np.full(9, np.nan)
    r[tubes] = residuals_mm
    return Fit(T, [a], [r], [np.ones(9, bool)], len(tubes), float(np.sqrt(np.mean(np.square(residuals_mm)))))


@pytest.fixture(scope="module")
def model(neuro_geometry):
    return prepare_geometry(neuro_geometry)[0]


def test_depth_tubes_are_named_by_their_shape(z001, neuro_geometry):
    assert depth_tube_name(prepare_geometry(z001)[0]) == "diagonal"
    assert depth_tube_name(prepare_geometry(neuro_geometry)[0]) == "helical"


def test_a_fit_within_every_limit_is_trusted(model):
    assert check_trust(hand_fit(np.full(9, 0.05)), [], model, [SLICE], SolveOptions()) is None


def test_a_residual_rms_beyond_half_a_pixel_is_refused(model):
    with pytest.raises(NoLock, match=r"hand: residual RMS 0\.300 mm exceeds 0\.5 px \(0\.250 mm\)") as info:
        check_trust(hand_fit(np.full(9, 0.3)), [], model, [SLICE], SolveOptions())
    assert info.value.detail == {"residual_rms_mm": 0.3}


def test_one_residual_beyond_the_limit_is_refused(model):
    """Eight tubes 0.02 mm off and one 0.8 mm (RMS 0.267 mm, within a 1 px RMS limit here): that one tube alone is
    beyond 1.5 px = 0.75 mm."""
    fit = hand_fit(np.r_[np.full(8, 0.02), 0.8])
    with pytest.raises(NoLock, match=r"hand: a tube residual of 0\.800 mm exceeds 1\.5 px") as info:
        check_trust(fit, [], model, [SLICE], SolveOptions(max_rms_px=1.0))
    assert info.value.detail == {"max_residual_mm": 0.8}
    assert check_trust(hand_fit(np.r_[np.full(8, 0.02), 0.7]), [], model, [SLICE], SolveOptions(max_rms_px=1.0)) is None


@pytest.mark.parametrize("tubes, message", [
    ([0, 1, 2, 4, 5], "only 5 tubes matched (2 helical); need at least 6 with 2 helical"),
    ([0, 1, 2, 3, 4, 7, 8], "only 7 tubes matched (1 helical); need at least 6 with 2 helical"),
])
def test_too_few_tubes_or_too_few_helices_are_refused(model, tubes, message):
    with pytest.raises(NoLock) as info:
        check_trust(hand_fit(np.full(len(tubes), 0.05), tubes), [], model, [SLICE], SolveOptions())
    assert info.value.reason == message and info.value.detail == {"n_tubes": len(tubes)}


def test_a_slice_crossing_the_axis_beyond_the_body_is_refused(model):
    with pytest.raises(NoLock, match=r"crosses the fiducial axis at depth -3\.0 mm, outside the body \[0, 50\] mm"):
        check_trust(hand_fit(np.full(9, 0.05), T=slice_frame(-3.0, 0.0, 0.0, 0.0)), [], model, [SLICE], SolveOptions())


def test_a_distinct_rival_as_good_is_ambiguous_and_a_near_one_is_not(model):
    """A rival 2 deg off in twist with the same tubes and RMS makes the fit ambiguous (asking for a prior); one 0.3 deg
    off is the same pose (within 1 mm and 1 deg)."""
    fit = hand_fit(np.full(9, 0.05))
    rival = hand_fit(np.full(9, 0.05), T=slice_frame(25.0, 20.0, 40.0, 12.0))
    with pytest.raises(AmbiguousFit, match=r"two distinct poses match 9 and 9 tubes .*--prior"):
        check_trust(fit, [rival], model, [SLICE], SolveOptions())
    near = hand_fit(np.full(9, 0.05), T=slice_frame(25.0, 20.0, 40.0, 10.3))
    assert check_trust(fit, [near], model, [SLICE], SolveOptions()) is None
