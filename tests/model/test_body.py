"""The fiducial's body: its outline, bore and the gaps to them."""


import numpy as np
import pytest

from chic_register.model.body import Body


def test_square_body_gaps_by_hand():
    b = Body.square(60.0, 67.0, 53.0)
    assert b.outer_diameter == pytest.approx(67.0 * 2**0.5) and b.inner_diameter == 53.0
    xy = np.array([[30.0, 30.0], [30.0, 0.0], [28.0, -29.0]])
    # to the outside: 33.5 - max(|x|, |y|); to the bore (26.5): Euclidean distance to the square
    assert np.allclose(b.outside_gap_mm(xy), [3.5, 3.5, 4.5])
    assert np.allclose(b.bore_gap_mm(xy), [np.hypot(3.5, 3.5), 3.5, np.hypot(1.5, 2.5)])
    assert b.outline_area_mm2 == 67.0**2 and b.bore_area_mm2 == 53.0**2
