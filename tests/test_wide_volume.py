"""Volumes of CHIC designs whose blobs are twice as wide as the channels: no slice alone gives a pose, the volume does.

Round trips: geometry -> simulated volume (Rician SNR 20, blob width 2x nominal, axial and tilted near the design's
computed limit: neuro 26.5 deg, needle-guide 24.5 deg at mid depth) -> ``register_volume`` -> compared with the known
pose at the frame centre. The pose comes from the voxels (chic_register.guess.volume_search), is fitted through the blurred
model to spread slices and verified on them (chic_register.pipeline.volume._register_wide).
"""

import numpy as np
import pytest

from chic_register.errors import NoLock
from chic_register.guess.volume_search import volume_first_guesses
from chic_register.imaging.simulate import simulate_volume
from chic_register.model.pose import apply, invert, rigid, rot_y, rot_z
from chic_register.model.tube_model import prepare_geometry
from chic_register.pipeline.volume import register_volume

PROTOCOL = {"neuro": ((0.5, 0.5, 2.0), (128, 128, 40)), "needle": ((0.3, 0.3, 1.0), (128, 128, 40))}


def _volume(geom, name, tilt, az, width, seed):
    spacing, shape = PROTOCOL[name]
    L = geom.body.length
    T = rigid(rot_z(az) @ rot_y(tilt), (1.0, -2.0, -L / 2))
    sv = simulate_volume(geom, T, shape, spacing, noise="rician", snr=20, rng=seed, supersample=2,
                         thickness_samples=2, blob_width=width)
    return sv.volume, T, np.array([0.0, 0.0, L / 2])


def _tre_mm(T, T_true, point):
    return float(np.linalg.norm(apply(T, point) - apply(T_true, point)))


@pytest.mark.slow
@pytest.mark.parametrize("name, tilt, az, seed", [
    ("neuro", 0.0, 30, 1),
    ("neuro", 25.0, 200, 3),
    ("needle", 0.0, 30, 1),
    ("needle", 23.0, 200, 3),
])
def test_wide_blob_volume_registers(neuro_geometry, needle_geometry, name, tilt, az, seed):
    geom = neuro_geometry if name == "neuro" else needle_geometry
    vol, T, centre = _volume(geom, name, tilt, az, 2.0, seed)
    reg = register_volume(vol, geom)
    assert _tre_mm(reg.T_scanner_from_fiducial, T, centre) < 0.3
    assert len(reg.slices) >= 2 and len(reg.slices) + len(reg.skipped) == vol.shape[0]
    assert any("wide blobs were fitted" in s.reason for s in reg.skipped)


@pytest.mark.slow
def test_wide_blob_volume_is_right_or_refused(needle_geometry):
    """Tilted needle guide at 2x: its flipped pose also fits the voxels; never a wrong pose reported ok."""
    vol, T, centre = _volume(needle_geometry, "needle", 15.0, 100, 2.0, 2)
    try:
        reg = register_volume(vol, needle_geometry)
    except NoLock as exc:
        assert "ambiguous" in exc.reason or "wide blobs" in exc.reason
        return
    assert _tre_mm(reg.T_scanner_from_fiducial, T, centre) < 0.3


def test_the_voxels_give_a_first_guess_near_the_pose(neuro_geometry):
    """The centreline search finds the pose of a 2.5x neuro volume (no slice has more than 5 blobs) within 1 mm."""
    vol, T, centre = _volume(neuro_geometry, "neuro", 15.0, 100, 2.5, 2)
    model, _ = prepare_geometry(neuro_geometry)
    guesses = volume_first_guesses(vol.voxels, vol.affine_lps, model)
    assert guesses and _tre_mm(invert(guesses[0][1]), T, centre) < 1.0
