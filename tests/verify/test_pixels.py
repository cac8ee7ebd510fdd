"""The pose against the pixels (chic_register.verify.pixels.verify_fit) on one simulated slice.

A tilted neuro slice (depth 25 mm, tilt 30 deg, Rician SNR 40) is detected and locked by the stages below; the
verification must accept that fit, every tube present, and refuse the same fit moved in the image plane.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from chic_register.detect.blobs import detect_blobs
from chic_register.detect.detected import DetectedSlice
from chic_register.errors import NoLock
from chic_register.fit.lock import lock_slice
from chic_register.imaging.simulate import simulate_slice
from chic_register.model.pose import rigid
from chic_register.model.tube_model import prepare_geometry
from chic_register.options import SolveOptions
from chic_register.verify.pixels import verify_fit


@pytest.fixture(scope="module")
def locked(neuro_geometry):
    """(model, the slice as detected, its fits best first)."""
    model, _ = prepare_geometry(neuro_geometry)
    sim = simulate_slice(neuro_geometry, 25, 30, 40, 10, slice_thickness_mm=2.0, noise="rician", snr=40, rng=5)
    sl = sim.slice
    seen = DetectedSlice.of(sl, detect_blobs(sl.pixels, sl.pixel_spacing_mm, model.diameter_mm))
    fits, _ = lock_slice(model, seen.xy_mm, seen.T_scanner_from_image, SolveOptions(), seen.resolution_mm)
    return model, seen, fits


def test_the_locked_pose_verifies_with_every_tube_present(neuro_geometry, locked):
    model, seen, fits = locked
    (check,) = verify_fit(neuro_geometry, model, fits[0], [fits[1:]], [seen], SolveOptions())
    assert check.present == neuro_geometry.ids and check.missing == () and check.envelope == "ok"
    assert check.spacing_scale == pytest.approx((1.0, 1.0), abs=0.01)  # the declared spacing is the image's


@pytest.mark.parametrize("shift_mm, reason", [
    (0.5, r"tube D0's section lies 1\.\d px from where the pose"),
    (1.0, r"tube D0's section does not have the shape and place the pose"),
])
def test_the_pose_moved_in_the_image_plane_is_refused(neuro_geometry, locked, shift_mm, reason):
    """The same fit moved 0.5 mm (a pixel) or 1 mm along the scanner's x: the first section is found that far from
    its prediction, or does not match it at all."""
    model, seen, fits = locked
    T = rigid(np.eye(3), (shift_mm, 0.0, 0.0)) @ fits[0].T_F_from_scanner
    moved = dataclasses.replace(fits[0], T_F_from_scanner=T)
    with pytest.raises(NoLock, match=reason):
        verify_fit(neuro_geometry, model, moved, [[]], [seen], SolveOptions())
