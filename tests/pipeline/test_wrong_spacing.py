"""A wrong pixel spacing (one axis stretched, or the whole image scaled as by a print's scale error) is refused,
named along the right axis, never locked off the truth.
"""

from __future__ import annotations

import pytest

from chic_register.errors import NoLock
from chic_register.model.slices import Slice
from chic_register.pipeline.register import register
from chic_register.studies.damage import pose_error
from tests.helpers import register_outcome, run_hunt_case, simulate_square


@pytest.mark.parametrize("spacing", [(0.5, 0.56), (0.56, 0.5), (0.45, 0.5)])
def test_a_wrong_pixel_spacing_is_refused(neuro_geometry, spacing):
    sim = simulate_square(neuro_geometry, 25, 30, 40, 10, noise="rician", snr=40, seed=5)
    assert register_outcome(neuro_geometry, sim, spacing=spacing) == "no_lock"


@pytest.mark.parametrize("tilt, declared, axis", [(0, (0.53, 0.5), "rows"), (30, (0.5, 0.53), "columns")])
def test_a_stretch_the_pose_absorbs_is_seen_in_the_positions(neuro_geometry, tilt, declared, axis):
    """A 6 % spacing error that a tilted pose fits to 0.1 px (the section aspect cannot see it) is named by the
    positions' stretch test, along the right axis; the same slice with its true spacing does not trigger it."""
    sim = simulate_square(neuro_geometry, 25, tilt, 40, 10, noise="rician", snr=20, seed=5)
    with pytest.raises(NoLock, match=f"stretched -\\d+\\.\\d % along its {axis}") as info:
        register([Slice(sim.slice.pixels, declared, slice_thickness_mm=2.0, source="stretched")], neuro_geometry)
    assert info.value.detail["stretch_p"] < 1e-3
    right = Slice(sim.slice.pixels, (0.5, 0.5), slice_thickness_mm=2.0, source="right")
    try:
        register([right], neuro_geometry)
    except NoLock as exc:
        assert "stretched" not in exc.reason


def test_hunt_case_223_wrong_spacing_at_high_tilt_is_refused():
    """The last false lock of the 5000-case hunt (seed 0): a 12.6 % row-spacing error at 58.5 deg tilt, which the
    section fit would lock 5.4 mm off with a 0.05 mm residual, is refused by the stretch test."""
    out = run_hunt_case(223)
    assert out["outcome"] == "no_lock" and "stretched" in out["reason"], out


@pytest.mark.parametrize("spacing", [(0.5, 0.56), (0.45, 0.5)])
def test_a_wrong_pixel_spacing_is_refused_at_low_snr(neuro_geometry, spacing):
    sim = simulate_square(neuro_geometry, 25, 45, 40, 10, noise="rician", snr=8, seed=5)
    assert register_outcome(neuro_geometry, sim, spacing=spacing) == "no_lock"


def test_an_isotropic_scale_is_named_with_the_spacing_that_registers_it(neuro_geometry):
    """A slice declared 1 % too coarse along both axes (as a print 1 % too large, or a gradient calibration off by
    that much, looks): refused as a scale of the whole image, naming the spacing that would register it; declared so, the
    slice locks on the true pose."""
    import re

    sim = simulate_square(neuro_geometry, 25, 30, 40, 10, noise="rician", snr=30, seed=5)
    with pytest.raises(NoLock, match="scaled -\\d\\.\\d\\d % along both axes") as info:
        register([Slice(sim.slice.pixels, (0.505, 0.505), slice_thickness_mm=2.0, source="scaled")], neuro_geometry)
    assert "fiducial is that much larger than its geometry file says" in info.value.reason
    rs, cs = map(float, re.search(r"pixel spacing of (\S+) x (\S+) mm \(row, col\)", info.value.reason).groups())
    assert rs == pytest.approx(0.5, rel=0.003) and cs == pytest.approx(0.5, rel=0.003)
    reg = register([Slice(sim.slice.pixels, (rs, cs), slice_thickness_mm=2.0, source="rescaled")], neuro_geometry)
    tre, rot = pose_error(reg.T_scanner_from_fiducial, sim.truth.T_scanner_from_fiducial, neuro_geometry.body.length)
    assert tre < 0.2 and rot < 0.3


def test_a_stretch_within_a_scanners_calibration_is_named_as_one_slice_not_telling_it_from_a_tilt(neuro_geometry):
    """A 0.6 % stretch (a gradient calibration, not a wrong spacing) that moves one slice's pose: refused with the
    remedy (several slices), not blamed on the pixel spacing; a 6 % one still is."""
    sim = simulate_square(neuro_geometry, 25, 30, 40, 10, noise="rician", snr=40, seed=5)
    with pytest.raises(NoLock, match="cannot tell that stretch from a tilt: register several slices") as info:
        register([Slice(sim.slice.pixels, (0.5, 0.503), slice_thickness_mm=2.0, source="calibration")],
                 neuro_geometry)
    assert "pixel spacing looks wrong" not in info.value.reason
    with pytest.raises(NoLock, match="pixel spacing looks wrong"):
        register([Slice(sim.slice.pixels, (0.5, 0.53), slice_thickness_mm=2.0, source="spacing")], neuro_geometry)
