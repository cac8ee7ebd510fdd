"""Sections wider along one image axis: a point spread (an MR phase-encoding blur) or a wrong pixel spacing?

The blob-aspect test refuses sections whose column and row widths differ from the prediction (a wrong
spacing). A frame whose rods span the image measures both axes' scales from the rod positions themselves:
there a blur along one axis is not refused, and a wrong spacing still is.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import ndimage as ndi

from chic_register.errors import NoLock
from chic_register.imaging.simulate import add_rician_noise, simulate_slice
from chic_register.options import SolveOptions
from chic_register.pipeline.register import register
from chic_register.verify import pixels
from tests.helpers import three_plate_frame, tre_mm

POSE = (60.0, 20.0, 90.0, 0.0)  # tilted about F's x: one slice fixes the three-plate frame's pose


def _slice(blur_cols_px: float, col_spacing_factor: float = 1.0, seed: int = 0):
    frame = three_plate_frame()
    rng = np.random.default_rng(seed)
    sim = simulate_slice(frame, *POSE, shape=(384, 384), pixel_spacing_mm=(0.7, 0.7), slice_thickness_mm=2.0,
                         rng=rng)
    img = sim.slice.pixels
    if blur_cols_px > 0:
        img = ndi.gaussian_filter1d(img, blur_cols_px, axis=1)
        img = img / img.max()
    img = add_rician_noise(img, 25.0, rng)
    rs, cs = sim.slice.pixel_spacing_mm
    sl = dataclasses.replace(sim.slice, pixels=img, pixel_spacing_mm=(rs, cs * col_spacing_factor))
    return frame, sl, sim.truth.T_scanner_from_fiducial


def test_a_blur_along_the_columns_is_the_point_spread_when_the_rods_pin_the_scale(monkeypatch):
    frame, sl, T_true = _slice(blur_cols_px=1.6)
    reg = register([sl], frame)
    assert tre_mm(reg.T_scanner_from_fiducial, T_true, (0, 0, 60)) < 0.3
    # the aspect test alone reads the same slice as a wrong spacing
    monkeypatch.setattr(pixels, "positions_rule_out_stretch", lambda *a, **k: False)
    with pytest.raises(NoLock, match="wider along the columns"):
        register([sl], frame)


@pytest.mark.parametrize("factor", [1.06, 0.94])
def test_a_wrong_column_spacing_is_still_refused(factor):
    frame, sl, _ = _slice(blur_cols_px=0.0, col_spacing_factor=factor)
    with pytest.raises(NoLock):
        register([sl], frame, options=SolveOptions())
