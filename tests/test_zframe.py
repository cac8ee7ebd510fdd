"""The solver's side of the Z-frame: the square body model, its symmetry test, blob widths and simulated slices."""

import json

import numpy as np
import pytest
from scipy import ndimage

from chic_design.families import family_of
from chic_design.spec import load_spec
from chic_register.cli.main import main as register_main
from chic_register.imaging.blob_width import BlobWidth, render_tubes_widened
from chic_register.imaging.simulate import simulate_slice
from chic_register.model.body import Body
from chic_register.model.geometry import write_geometry
from chic_register.model.pose import slice_frame

from .conftest import ZFRAME


@pytest.fixture(scope="module")
def zgeom():
    spec = load_spec(ZFRAME)
    return family_of(spec).geometry(spec, source={"spec": "designs/zframe.yaml"})


def test_square_body_gaps_by_hand():
    b = Body.square(60.0, 67.0, 53.0)
    assert b.outer_diameter == pytest.approx(67.0 * 2**0.5) and b.inner_diameter == 53.0
    xy = np.array([[30.0, 30.0], [30.0, 0.0], [28.0, -29.0]])
    # to the outside: 33.5 - max(|x|, |y|); to the bore (26.5): Euclidean distance to the square
    assert np.allclose(b.outside_gap_mm(xy), [3.5, 3.5, 4.5])
    assert np.allclose(b.bore_gap_mm(xy), [np.hypot(3.5, 3.5), 3.5, np.hypot(1.5, 2.5)])
    assert b.outline_area_mm2 == 67.0**2 and b.bore_area_mm2 == 53.0**2









def test_the_solvers_coarse_symmetry_test_bounds_the_full_one_from_below(zgeom, neuro_geometry, needle_geometry):
    """prior_needed first compares 9 of the 65 points per tube (a subset of the same pairs): each coarse mismatch
    is a lower bound, so a frame it clears has no symmetry, and the frames it does not clear get the full test."""
    from chic_register.model.symmetry import (
        EXACT_SHARE,
        candidate_rotations,
        mismatches,
        prior_needed,
    )

    for g in (zgeom, neuro_geometry, needle_geometry):
        Rs = np.stack([R for _, R in candidate_rotations(g.body.length)])
        full, coarse = mismatches(g, Rs), mismatches(g, Rs, 9)
        assert all(c <= f + 1e-12 for (c, _), (f, _) in zip(coarse, full))
        assert min(f for f, _ in full) > 0.5 or g is zgeom  # the CHIC designs are far from any symmetry
    assert prior_needed(zgeom, EXACT_SHARE * 1.0) is not None
    assert prior_needed(neuro_geometry, 0.1) is None and prior_needed(needle_geometry, 0.1) is None
    assert prior_needed(needle_geometry, 0.7) is not None  # its half turn leaves the tubes 0.63 mm apart


def test_prior_needed_memo_gives_what_the_test_itself_gives(zgeom, neuro_geometry, needle_geometry):
    """prior_needed is memoised per geometry and tolerance: every answer equals the unmemoised test's, on repeat
    calls too, and a different tolerance is not served another's answer."""
    from chic_register.model.symmetry import prior_needed, prior_needed_unmemoised

    for g in (zgeom, neuro_geometry, needle_geometry):
        for tol in (0.05, 0.1, 0.7):
            want = prior_needed_unmemoised(g, tol)
            assert prior_needed(g, tol) == want and prior_needed(g, tol) == want
    assert prior_needed(needle_geometry, 0.1) is None and prior_needed(needle_geometry, 0.7) is not None











# ----------------------------------------------------------------------------- blob width


@pytest.mark.parametrize("factor", [1.5, 2.0, 2.5])
def test_blob_width_factor_gives_that_full_width_at_half_maximum(factor):
    spec = load_spec(ZFRAME)
    tube = family_of(spec).geometry(spec).tube("A0")
    bw = BlobWidth.for_tube(tube.diameter, factor)
    # an axial rod in a thin axial slice, 0.05 mm pixels: measure the profile through its centre
    T = slice_frame(30.0, 0.0, 0.0, 0.0)
    T[:3, 3] = (30.0, -30.0, 30.0)  # the slice frame's origin on the rod
    img = render_tubes_widened([tube], T, (301, 301), (0.05, 0.05), 0.0, supersample=2, blob_width=factor)
    row = img[150]
    assert row.max() == pytest.approx(1.0, abs=0.01)  # peak kept at the fluid signal
    above = np.flatnonzero(row >= 0.5 * row.max())
    fwhm = (above[-1] - above[0] + 1) * 0.05
    assert fwhm == pytest.approx(factor * tube.diameter, abs=0.1)
    assert bw.sigma_mm > 0 and bw.gain > 1


def test_narrow_blobs_and_centroids_at_any_width(zgeom):
    areas = {}
    for factor in (0.7, 1.0, 2.0):
        sim = simulate_slice(zgeom, 25.0, 12.0, 30.0, 10.0, shape=(220, 220), slice_thickness_mm=1.0,
                             blob_width=factor, supersample=3)
        img = sim.slice.pixels
        labels, n = ndimage.label(img > 0.05)
        assert n == 7, factor
        cents = ndimage.center_of_mass(img, labels, range(1, n + 1))
        for tid, (r, c) in sim.truth.centres_px.items():
            d = min(np.hypot(r - a, c - b) for a, b in cents)
            assert d < 0.05, (factor, tid, d)  # symmetric widening: centroids stay put (pixels)
        areas[factor] = img.sum()
        assert sim.truth.settings["blob_width"] == factor
    assert areas[0.7] / areas[1.0] == pytest.approx(0.49, rel=0.05)  # a 0.7x narrower lumen
    assert areas[2.0] > 3 * areas[1.0]
    with pytest.raises(ValueError, match="blob width factor must be 0.2..5, got 9"):
        BlobWidth.for_tube(3.0, 9.0)


def test_simulate_cli_on_a_zframe_geometry_slices_and_volume(zgeom, tmp_path, capsys):
    geo = write_geometry(zgeom, tmp_path / "geometry.yaml")
    for tilt, bw in ((0.0, 1.0), (15.0, 2.0)):
        out = tmp_path / f"s{tilt:g}.npy"
        assert register_main(["simulate", "--geometry", str(geo), "--depth", "30", "--tilt", str(tilt),
                              "--azimuth", "40", "--size", "200", "--blob-width", str(bw), "--noise", "rician",
                              "--seed", "3", "--out", str(out)]) == 0
        truth = json.loads((tmp_path / f"s{tilt:g}.npy.truth.json").read_text())
        assert sorted(truth["centres_px"]) == sorted(zgeom.ids) and truth["settings"]["blob_width"] == bw
        assert np.load(out).shape == (200, 200)
    vol = tmp_path / "v.nii.gz"
    assert register_main(["simulate", "--geometry", str(geo), "--depth", "30", "--tilt", "8", "--out", str(vol),
                          "--volume-shape", "150", "150", "9", "--voxel-size", "0.5", "0.5", "2",
                          "--blob-width", "1.5", "--noise", "none"]) == 0
    from chic_register.io.volumes import read_volume

    mid = np.asarray(read_volume(vol).voxels)[4]  # the middle k-plane: depth 30, tilt 8
    truth = json.loads((tmp_path / "v.nii.gz.truth.json").read_text())
    assert truth["settings"]["blob_width"] == 1.5
    assert ndimage.label(mid > 0.05 * mid.max())[1] == 7
    assert register_main(["simulate", "--geometry", str(geo), "--depth", "30", "--out", str(tmp_path / "x.npy"),
                          "--blob-width", "0"]) == 2
    assert "--blob-width must be 0.2..5" in capsys.readouterr().err
