"""The lock stage (chic_register.pipeline.locking.lock_slices): each slice's own pose, or why it has none.

A two-slice series of the same placement: a blank slice (all zeros: no blob) and a tilted neuro slice (depth 25 mm,
tilt 30 deg, Rician SNR 40).
"""

from __future__ import annotations

import numpy as np
import pytest

from chic_register.detect.blobs import detect_blobs
from chic_register.detect.detected import DetectedSlice
from chic_register.errors import NoLock
from chic_register.imaging.simulate import simulate_slice
from chic_register.model.pose import invert
from chic_register.model.slices import Slice
from chic_register.model.tube_model import prepare_geometry
from chic_register.options import SolveOptions
from chic_register.pipeline.locking import lock_slices


@pytest.fixture(scope="module")
def series(neuro_geometry):
    """(model, [the blank slice, the neuro slice] as detected, the true T_scanner_from_fiducial)."""
    model, _ = prepare_geometry(neuro_geometry)
    sim = simulate_slice(neuro_geometry, 25, 30, 40, 10, slice_thickness_mm=2.0, noise="rician", snr=40, rng=5)
    sl = sim.slice
    blank = Slice(np.zeros(np.shape(sl.pixels)), sl.pixel_spacing_mm, sl.origin_mm, sl.col_dir, sl.row_dir,
                  sl.slice_thickness_mm, source="blank")
    seen = [DetectedSlice.of(s, detect_blobs(s.pixels, s.pixel_spacing_mm, model.diameter_mm)) for s in (blank, sl)]
    assert [len(d.blobs) for d in seen] == [0, 9]
    return model, seen, sim.truth.T_scanner_from_fiducial


def test_a_blank_slice_is_skipped_and_the_other_locks(series):
    model, seen, T_true = series
    runs = lock_slices(seen, model, SolveOptions(), skip_failed=True)
    assert [r.index for r in runs] == [0, 1]
    blank, good = runs
    assert blank.fit is None and blank.skipped.source == "blank"
    assert blank.skipped.reason == "found 0 candidate tube cross-sections; need at least 6"
    assert good.skipped is None and good.fit.n_matched == 9
    centre = np.array([0.0, 0.0, 25.0, 1.0])
    assert np.linalg.norm((invert(good.fit.T_F_from_scanner) - T_true) @ centre) < 0.1


def test_without_skipping_a_slice_that_does_not_lock_refuses_the_series(series):
    model, seen, _ = series
    with pytest.raises(NoLock) as info:
        lock_slices(seen, model, SolveOptions(), skip_failed=False)
    assert info.value.reason == "blank: found 0 candidate tube cross-sections; need at least 6"
