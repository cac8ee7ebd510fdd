"""The blob width ratio (chic_register.detect.wide_blobs) reads the blur of a slice."""

import numpy as np
import pytest

from chic_register.detect.blobs import detect_blobs
from chic_register.detect.detected import DetectedSlice
from chic_register.detect.wide_blobs import WIDE_RATIO, blob_width_ratio
from chic_register.model.tube_model import prepare_geometry
from chic_register.pipeline.register import register
from tests.helpers import blurred_slice


@pytest.mark.parametrize("width, lo, hi", [(1.0, 0.9, 1.08), (2.0, 1.45, 1.8)])
def test_blob_width_ratio_reads_the_blur(neuro_geometry, width, lo, hi):
    sl, _, _ = blurred_slice(neuro_geometry, (25, 15, 40, 10), width, 20.0, 3)
    model, _ = prepare_geometry(neuro_geometry)
    reg = register([sl], neuro_geometry, verify=False, blurred_fit=False)
    b = detect_blobs(sl.pixels, sl.pixel_spacing_mm, model.diameter_mm)
    a = np.array([reg.slices[0].assignment.get(t, -1) for t in model.ids])
    ratio = blob_width_ratio(model, [DetectedSlice.of(sl, b)], [a])
    assert lo < ratio < hi
    assert (ratio >= WIDE_RATIO) == (width > 1)
