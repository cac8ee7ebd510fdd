"""The trust checks (chic_register.verify.trust)."""

from chic_register.model.tube_model import prepare_geometry
from chic_register.verify.trust import depth_tube_name


def test_depth_tubes_are_named_by_their_shape(z001, neuro_geometry):
    assert depth_tube_name(prepare_geometry(z001)[0]) == "diagonal"
    assert depth_tube_name(prepare_geometry(neuro_geometry)[0]) == "helical"
