"""Volumes of CHIC designs whose blobs are twice as wide as the channels: no slice alone gives a pose, the volume does.

Round trips: geometry -> simulated volume (Rician SNR 20, blob width 2x nominal, axial and tilted near the design's
computed limit: neuro 26.5 deg, needle-guide 24.5 deg at mid depth) -> ``register_volume`` -> compared with the known
pose at the frame centre. The pose comes from the voxels (chic_register.guess.volume_search), is fitted through the blurred
model to spread slices and verified on them (chic_register.pipeline.volume._register_wide).
"""

import math

import numpy as np
import pytest

from chic_register.errors import NoLock
from chic_register.imaging.simulate import simulate_volume
from chic_register.model.pose import invert, rigid, rot_y, rot_z
from chic_register.pipeline.volume import register_volume
from tests.helpers import tre_and_rotation, tre_mm, wide_blob_volume


@pytest.mark.slow
@pytest.mark.parametrize("name, tilt, az, seed", [
    ("neuro", 0.0, 30, 1),
    ("neuro", 25.0, 200, 3),
    ("needle", 0.0, 30, 1),
    ("needle", 23.0, 200, 3),
])
def test_wide_blob_volume_registers(neuro_geometry, needle_geometry, name, tilt, az, seed):
    geom = neuro_geometry if name == "neuro" else needle_geometry
    vol, T, centre = wide_blob_volume(geom, name, tilt, az, 2.0, seed)
    reg = register_volume(vol, geom)
    assert tre_mm(reg.T_scanner_from_fiducial, T, centre) < 0.3
    assert len(reg.slices) >= 2 and len(reg.slices) + len(reg.skipped) == vol.shape[0]
    assert any("wide blobs were fitted" in s.reason for s in reg.skipped)


@pytest.mark.slow
def test_wide_blob_volume_is_right_or_refused(needle_geometry):
    """Tilted needle guide at 2x: its flipped pose also fits the voxels; never a wrong pose reported ok."""
    vol, T, centre = wide_blob_volume(needle_geometry, "needle", 15.0, 100, 2.0, 2)
    try:
        reg = register_volume(vol, needle_geometry)
    except NoLock as exc:
        assert "ambiguous" in exc.reason or "wide blobs" in exc.reason
        return
    assert tre_mm(reg.T_scanner_from_fiducial, T, centre) < 0.3


@pytest.mark.slow
def test_wide_volume_pose_carries_the_pixel_fits_covariance(needle_geometry):
    """A 1.3x needle-guide volume: 18 slices' blob centres alone put the pose 0.29 mm off while predicting 0.04 mm
    (merged neighbours pull every slice the same way); the pose fitted to the pixels of spread slices through the
    blurred model is within 0.1 mm, and its reported covariance (from that fit) is consistent with the error."""
    from chic_register.pipeline.volume import register_volume
    from chic_register.precision.uncertainty import mahalanobis2

    L = needle_geometry.body.length
    T = rigid(rot_z(30) @ rot_y(0.0), (1.0, -2.0, -L / 2))
    vol = simulate_volume(needle_geometry, T, (128, 128, 40), (0.3, 0.3, 1.0), noise="rician", snr=20, rng=1,
                          supersample=2, thickness_samples=2, blob_width=1.3).volume
    reg = register_volume(vol, needle_geometry)
    tre, rot = tre_and_rotation(reg.T_scanner_from_fiducial, T, L)
    assert tre < 0.15 and rot < 0.3
    unc = reg.uncertainty
    assert unc.measurement.startswith("blurred fit (pixels)")  # (+ the sections' model error, where they show one)
    D = invert(T) @ reg.T_scanner_from_fiducial  # the error as a motion in F
    delta = np.array([math.degrees(v) for v in (D[2, 1], D[0, 2], D[1, 0])] + list(D[:3, 3]))
    assert mahalanobis2(delta, unc.covariance) < 22.5  # chi-square, 6 dof: p = 0.001


@pytest.mark.slow
def test_a_tight_field_of_view_never_crashes_the_blurred_fit(needle_geometry):
    """A 1.3x needle-guide volume in a 24 mm field of view (sections near the edges): some spread slice holds no
    section box, and the fit must cope with that: a pose within 0.3 mm, or a refusal, never an IndexError."""
    from chic_register.pipeline.volume import register_volume

    L = needle_geometry.body.length
    T = rigid(rot_z(30) @ rot_y(0.0), (1.0, -2.0, -L / 2))
    vol = simulate_volume(needle_geometry, T, (80, 80, 40), (0.3, 0.3, 1.0), noise="rician", snr=20, rng=1,
                          supersample=2, thickness_samples=2, blob_width=1.3).volume
    try:
        reg = register_volume(vol, needle_geometry)
    except NoLock:
        return
    assert tre_and_rotation(reg.T_scanner_from_fiducial, T, L)[0] < 0.3
