"""The first guess from a volume's voxels (chic_register.guess.volume_search)."""

from chic_register.guess.volume_search import volume_first_guesses
from chic_register.model.pose import invert
from chic_register.model.tube_model import prepare_geometry
from tests.helpers import tre_mm, wide_blob_volume


def test_the_voxels_give_a_first_guess_near_the_pose(neuro_geometry):
    """The centreline search finds the pose of a 2.5x neuro volume (no slice has more than 5 blobs) within 1 mm."""
    vol, T, centre = wide_blob_volume(neuro_geometry, "neuro", 15.0, 100, 2.5, 2)
    model, _ = prepare_geometry(neuro_geometry)
    guesses = volume_first_guesses(vol.voxels, vol.affine_lps, model)
    assert guesses and tre_mm(invert(guesses[0][1]), T, centre) < 1.0
