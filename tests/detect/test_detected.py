"""A slice as the stages after detection see it (chic_register.detect.detected.DetectedSlice), by hand."""

from __future__ import annotations

import math

import numpy as np
import pytest

from chic_register.detect.blobs import Blobs
from chic_register.detect.detected import DetectedSlice
from chic_register.model.slices import Slice


def hand_blobs(centres_rc, width_mm=math.nan) -> Blobs:
    n = len(centres_rc)
    return Blobs(np.array(centres_rc, float), np.full(n, 30), np.ones(n), np.ones(n), np.full(n, 20.0), 0.0, 0.05,
                 0.5, width_mm=width_mm)


def test_blob_centres_are_in_image_mm_x_along_the_columns():
    """Rows 0.5 mm apart, columns 0.8 mm: the blob at (row 10, col 20) is at x = 16 mm, y = 5 mm."""
    sl = Slice(np.zeros((40, 30)), (0.5, 0.8), slice_thickness_mm=2.0, source="hand")
    d = DetectedSlice.of(sl, hand_blobs([[10.0, 20.0], [3.5, 7.25]]))
    np.testing.assert_allclose(d.xy_mm, [[16.0, 5.0], [5.8, 1.75]])
    assert d.source == "hand" and d.slice is sl


@pytest.mark.parametrize("width_mm, thickness_mm, unit_mm", [
    (math.nan, 2.0, 0.8),  # the larger pixel side
    (7.5, 2.0, 1.0),  # a 7.5 mm wide blob: a 7.5th of it
    (math.nan, 6.0, 1.0),  # a 6 mm slice: a 6th of it
])
def test_the_trust_unit_is_the_pixel_or_what_blur_and_thickness_resolve(width_mm, thickness_mm, unit_mm):
    sl = Slice(np.zeros((40, 30)), (0.5, 0.8), slice_thickness_mm=thickness_mm)
    assert DetectedSlice.of(sl, hand_blobs([[10.0, 20.0]], width_mm)).resolution_mm == pytest.approx(unit_mm)


def test_the_image_frame_is_the_slices_unless_given():
    sl = Slice(np.zeros((40, 30)), (0.5, 0.8), origin_mm=(10.0, -20.0, 5.0))
    b = hand_blobs([[10.0, 20.0]])
    np.testing.assert_array_equal(DetectedSlice.of(sl, b).T_scanner_from_image, sl.T_scanner_from_image())
    S = np.eye(4)
    S[:3, 3] = (1.0, 2.0, 3.0)
    assert DetectedSlice.of(sl, b, S).T_scanner_from_image is S
