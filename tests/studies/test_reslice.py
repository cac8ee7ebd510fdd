"""Reslicing a volume (chic_register.studies.reslice): exact on a linear field, as direct rendering, and the study's
table.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree

from chic_register.imaging.render import render_slice
from chic_register.imaging.simulate import simulate_volume
from chic_register.io.volumes import Volume
from chic_register.model.pose import apply, invert, rigid, rot_y, rot_z, slice_frame
from chic_register.studies.reslice import default_depths, reslice, reslice_study
from tests.helpers import OBLIQUE, T_TRUE


def _centroids(img):
    lab, n = ndimage.label(img > 0.4 * img.max())
    return np.array(ndimage.center_of_mass(img, lab, range(1, n + 1)))


@pytest.mark.parametrize("thickness", [0.0, 3.0])
def test_reslice_of_a_linear_field_is_exact(thickness):
    """Trilinear sampling reproduces a linear function of LPS position exactly; a slab averages to its centre."""
    grid = Volume(np.zeros((40, 50, 60)), (0.8, 0.7, 1.1), (-20.0, -15.0, -22.0), OBLIQUE)
    ijk = np.stack(np.meshgrid(np.arange(60), np.arange(50), np.arange(40), indexing="ij"), -1).reshape(-1, 3)
    g = np.array([0.3, -1.2, 2.0])
    field = (grid.index_to_lps(ijk) @ g + 5.0).reshape(60, 50, 40).transpose(2, 1, 0)
    vol = Volume(field, grid.spacing_mm, grid.origin_mm, grid.direction)
    S = rigid(rot_z(33.0) @ rot_y(40.0) @ rot_z(-10.0), grid.index_to_lps([[29.5, 24.5, 19.5]])[0] + 0.37)
    sl = reslice(vol, S, (24, 20), (0.6, 0.9), slice_thickness_mm=thickness)
    rows, cols = np.meshgrid(np.arange(24), np.arange(20), indexing="ij")
    expected = sl.pixel_to_scanner(rows.ravel(), cols.ravel()) @ g + 5.0
    np.testing.assert_allclose(sl.pixels.ravel(), expected, atol=1e-3)  # float32 sampling
    np.testing.assert_allclose(sl.pixel_to_scanner([11.5], [9.5])[0], S[:3, 3], atol=1e-12)  # centre = S origin
    np.testing.assert_allclose(sl.normal, S[:3, 2], atol=1e-12)


@pytest.fixture(scope="module")
def clean_volume(neuro_geometry):
    return simulate_volume(neuro_geometry, T_TRUE, (96, 96, 64), (0.5, 0.5, 1.0), direction=OBLIQUE, noise="none")


@pytest.mark.parametrize("angles", [(20.0, 15.0, 0.0, 0.0), (30.0, 15.0, 60.0, 20.0), (25.0, 0.0, 0.0, 45.0)])
def test_reslice_matches_direct_rendering(neuro_geometry, clean_volume, angles):
    """Tube centroids of a reformatted slice agree with the renderer's at the same pose (noise-free volume)."""
    T_F_from_S = slice_frame(*angles)
    sl = reslice(clean_volume.volume, T_TRUE @ T_F_from_S, (96, 96), (0.5, 0.5))
    ref = render_slice(neuro_geometry, T_F_from_S, (96, 96), (0.5, 0.5), 0.0)
    a, b = _centroids(sl.pixels), _centroids(ref)
    assert len(a) == len(b) == 9
    dist, _ = cKDTree(b).query(a)
    assert dist.max() < 0.25  # pixels
    # the slice's geometry: its centre pixel is the S origin, on the fiducial axis at the depth
    centre = sl.pixel_to_scanner([47.5], [47.5])[0]
    np.testing.assert_allclose(apply(invert(T_TRUE), centre), [0, 0, angles[0]], atol=1e-9)


def test_reslice_study_table(neuro_geometry, sim_volume):
    depths = default_depths(neuro_geometry, 15.0, step_mm=6.0)
    study = reslice_study(sim_volume.volume, neuro_geometry, T_TRUE, depths_mm=depths, tilt_deg=15.0,
                          shape=(128, 128), pixel_spacing_mm=(0.5, 0.5))
    assert len(study.results) == len(depths) >= 4
    assert len(study.locked) >= len(depths) - 1
    s = study.summary()
    assert s["x_mm"]["rms"] < 0.2 and s["y_mm"]["rms"] < 0.2 and s["z_mm"]["rms"] < 0.3
    assert s["tilt_deg"]["rms"] < 0.5 and s["twist_deg"]["rms"] < 0.5
    table = study.table().splitlines()
    assert table[0].split() == ["X", "Y", "Z", "Tilt", "Twist"]
    assert table[1].startswith("RMS Error") and table[2].startswith("Standard Deviation")
    # a reference 2 mm off along the fiducial axis cuts every slice 2 mm deeper: a +2 mm z error
    shifted = reslice_study(sim_volume.volume, neuro_geometry, T_TRUE @ rigid(np.eye(3), (0, 0, 2.0)),
                            depths_mm=depths[1:3], tilt_deg=15.0, shape=(128, 128))
    assert shifted.locked and all(abs(r.errors["z_mm"] - 2.0) < 0.3 for r in shifted.locked)
