"""Slices with lost pixels (zeros, NaNs, specks, extreme values) register to the right pose or are refused with a
reason; the lost pixels are left out of the section fit.
"""

import numpy as np
import pytest

from chic_register.detect.dropout import fill_dropouts
from chic_register.imaging.simulate import simulate_slice
from chic_register.pipeline.register import register


def test_a_slice_with_dropouts_registers_and_says_so(neuro_geometry):
    """Round trip: a tilted slice with 25 % of its pixels zeroed locks to the right pose once they are filled."""
    sim = simulate_slice(neuro_geometry, 25, 30, 40, 10, slice_thickness_mm=2.0, noise="rician", snr=40.0, rng=5)
    px = np.array(sim.slice.pixels, float)
    px[np.random.default_rng(3).random(px.shape) < 0.25] = 0.0
    from dataclasses import replace

    reg = register([replace(sim.slice, pixels=px)], neuro_geometry)
    s, t = reg.slices[0], sim.truth.angles
    assert s.filled_pixels > 0 and reg.slices[0].to_dict()["filled_pixels"] == s.filled_pixels
    assert abs(s.depth_mm - t.depth_mm) < 0.2 and abs(s.tilt_deg - t.tilt_deg) < 0.3


def test_nan_pixels_are_filled_and_the_slice_registers(neuro_geometry):
    """2 % NaN pixels (a processing step's holes, handed over as an array): filled from their finite neighbours
    (the detector found no candidate at all before), and the slice registers to the right pose."""
    from dataclasses import replace

    sim = simulate_slice(neuro_geometry, 25, 30, 40, 10, slice_thickness_mm=2.0, noise="rician", snr=40.0, rng=5)
    px = np.array(sim.slice.pixels, float)
    holes = np.random.default_rng(3).random(px.shape) < 0.02
    px[holes] = np.nan
    filled, n = fill_dropouts(px)
    assert n == holes.sum() and np.all(np.isfinite(filled))
    reg = register([replace(sim.slice, pixels=px)], neuro_geometry)
    s, t = reg.slices[0], sim.truth.angles
    assert s.filled_pixels >= holes.sum()
    assert abs(s.depth_mm - t.depth_mm) < 0.2 and abs(s.tilt_deg - t.tilt_deg) < 0.3


def test_bright_specks_are_removed_and_the_slice_registers(neuro_geometry):
    """3 % hot pixels at the fluid's level or above (impulse noise): each stands alone above its neighbours' median
    and is replaced by it; the slice registers to the right pose (it was refused before). A plain slice is left
    exactly as it is."""
    from dataclasses import replace

    sim = simulate_slice(neuro_geometry, 25, 30, 40, 10, slice_thickness_mm=2.0, noise="rician", snr=40.0, rng=5)
    plain = np.array(sim.slice.pixels, float)
    assert fill_dropouts(plain)[1] == 0
    rng = np.random.default_rng(8)
    px = plain.copy()
    hot = rng.random(px.shape) < 0.03
    px[hot] = plain.max() * rng.uniform(0.8, 1.5, hot.sum())
    filled, n = fill_dropouts(px)
    assert n >= 0.9 * hot.sum() and np.sum(filled > 1.2 * plain.max()) < 0.02 * hot.sum()  # (a few on sections stay)
    reg = register([replace(sim.slice, pixels=px)], neuro_geometry)
    s, t = reg.slices[0], sim.truth.angles
    assert s.filled_pixels >= 0.9 * hot.sum()
    assert abs(s.depth_mm - t.depth_mm) < 0.2 and abs(s.tilt_deg - t.tilt_deg) < 0.3


@pytest.mark.parametrize("value", [100.0, 1e300, -1e300])
def test_one_extreme_pixel_is_filled_and_the_slice_registers(neuro_geometry, value):
    """One corrupt pixel far beyond the fluid's level (100x it, or a float's extreme, either sign) would set the
    detector's threshold for the whole image (one candidate found, or a crash beyond single precision): it alone
    is filled and the slice registers to the right pose. A speck 5x the fluid's level is left to the detector."""
    from dataclasses import replace

    sim = simulate_slice(neuro_geometry, 25, 30, 40, 10, slice_thickness_mm=2.0, noise="rician", snr=20.0, rng=5)
    plain = np.array(sim.slice.pixels, float)
    px = plain.copy()
    px[10, 200] = value * plain.max()
    filled, n = fill_dropouts(px)
    assert n == 1 and filled[10, 200] == pytest.approx(np.median(plain[9:12, 199:202]), abs=0.5 * plain.max())
    assert np.array_equal(np.delete(filled.ravel(), 10 * px.shape[1] + 200), np.delete(plain.ravel(), 10 * px.shape[1] + 200))
    reg = register([replace(sim.slice, pixels=px)], neuro_geometry)
    s, t = reg.slices[0], sim.truth.angles
    assert s.filled_pixels == 1
    assert abs(s.depth_mm - t.depth_mm) < 0.2 and abs(s.tilt_deg - t.tilt_deg) < 0.3
    px[10, 200] = 5.0 * plain.max()
    assert fill_dropouts(px)[1] == 0


def test_pixels_beyond_single_precision_are_refused_with_a_reason(neuro_geometry):
    """A whole image scaled to 1e120 (a rescale slope gone wrong): no_lock saying so, not a crash."""
    from dataclasses import replace

    from chic_register.errors import NoLock

    sim = simulate_slice(neuro_geometry, 25, 30, 40, 10, slice_thickness_mm=2.0, noise="rician", snr=20.0, rng=5)
    with pytest.raises(NoLock, match="pixel values reach 1.*e\\+120"):
        register([replace(sim.slice, pixels=np.asarray(sim.slice.pixels, float) * 1e120)], neuro_geometry)


@pytest.mark.parametrize("fill", [np.nan, np.inf, -np.inf])
def test_an_image_with_no_finite_pixel_is_refused_quietly(neuro_geometry, fill):
    """Nothing to fill from: no_lock with its reason, no exception and no numpy warning."""
    import warnings

    from chic_register.errors import NoLock
    from chic_register.model.slices import Slice

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert fill_dropouts(np.full((64, 64), fill))[1] == 0
        with pytest.raises(NoLock, match="candidate"):
            register([Slice(np.full((64, 64), fill), (0.5, 0.5), slice_thickness_mm=2.0, source="x")], neuro_geometry)


def test_one_extreme_pixel_in_a_noise_free_render_is_filled(neuro_geometry):
    """A mostly-zero image (no noise to measure) with one corrupt pixel: that pixel alone is filled (the render's
    sections, partial-volume rims included, are left as they are) and the slice registers."""
    from dataclasses import replace

    sim = simulate_slice(neuro_geometry, 25, 30, 40, 10, slice_thickness_mm=2.0, rng=5)
    plain = np.array(sim.slice.pixels, float)
    assert (plain == 0).mean() > 0.9 and fill_dropouts(plain)[1] == 0
    px = plain.copy()
    px[5, 5] = 1e6
    filled, n = fill_dropouts(px)
    assert n == 1 and np.array_equal(filled, plain)
    reg = register([replace(sim.slice, pixels=px)], neuro_geometry)
    assert abs(reg.slices[0].tilt_deg - sim.truth.angles.tilt_deg) < 0.3


def test_lost_pixels_are_left_out_of_the_section_fit(neuro_geometry, monkeypatch):
    """A tilted slice with 30 % of its pixels zeroed: the section fit leaves the lost pixels out (their filled values
    are a smoothed guess), so the pose is within a few hundredths of a degree of the truth and locks; fitted with
    the filled values as if measured, the same slice is refused as imprecise."""
    from chic_register.detect import dropout
    from chic_register.errors import ImprecisePose
    from chic_register.model.slices import Slice

    sim = simulate_slice(neuro_geometry, 22.0, 20.0, 35.0, 10.0, shape=(200, 200), pixel_spacing_mm=(0.5, 0.5),
                         slice_thickness_mm=1.5, noise="rician", snr=40.0, image_position=(0.0, 0.0, 0.0),
                         rng=np.random.default_rng(7))
    px = np.array(sim.slice.pixels)
    px[np.random.default_rng(8).random(px.shape) < 0.3] = 0.0
    sl = Slice(px, (0.5, 0.5), slice_thickness_mm=1.5)
    reg = register([sl], neuro_geometry)
    dR = reg.T_scanner_from_fiducial[:3, :3].T @ np.asarray(sim.truth.T_scanner_from_fiducial)[:3, :3]
    assert np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2, -1, 1))) < 0.1
    assert reg.slices[0].filled_pixels > 0
    marked = dropout.lost_pixels
    monkeypatch.setattr(dropout, "lost_pixels", lambda p: marked(p)[:2] + (None,))
    with pytest.raises(ImprecisePose):
        register([sl], neuro_geometry)


def test_a_section_whose_window_cannot_locate_it_both_ways_is_left_out(neuro_geometry, monkeypatch):
    """Lost pixels can leave a tube's window a single row: its section is then located along the row only (a
    singular information matrix). That tube is left out of the section fit, and the pose still locks on the rest
    (its Cholesky factor would raise otherwise)."""
    import dataclasses

    from chic_register.fit import section

    sim = simulate_slice(neuro_geometry, 22.0, 20.0, 35.0, 10.0, shape=(200, 200), pixel_spacing_mm=(0.5, 0.5),
                         slice_thickness_mm=1.5, noise="rician", snr=40.0, rng=np.random.default_rng(7))
    real = section.fit_sections

    def one_thin_window(*args, **kwargs):
        sf, windows = real(*args, **kwargs)
        k = int(np.flatnonzero(sf.fitted)[0])
        info = sf.info.copy()
        info[k] = [[info[k, 0, 0], 0.0], [0.0, 0.0]]  # no information across the row
        return dataclasses.replace(sf, info=info), windows

    monkeypatch.setattr(section, "fit_sections", one_thin_window)
    reg = register([sim.slice], neuro_geometry, verify=False)
    assert reg.slices[0].n_tubes >= 6
