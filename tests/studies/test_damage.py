"""The false-lock hunts' cases (chic_register.studies.damage): each case its index and seed alone, the truth moving
with damage that moves the image, the judging against it, a short seeded hunt, and the print hunt's other-design and
water-bath cases.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from chic_register.model.pose import rigid, rot_z
from chic_register.model.slices import Slice
from chic_register.studies.damage import (
    MUTATIONS,
    T_old_from_new,
    build_case,
    index_map,
    make_case,
    noisy_case,
    other_design_geometries,
    pose_error,
    print_scaled,
    run_case,
    run_print_case,
    solve_and_judge,
    true_centres_rc,
    unlisted_slice,
)
from tests.helpers import hunt_geometries


def test_short_seeded_hunt_has_no_false_lock_and_no_crash():
    """~10 s: 40 random damaged slices of both designs (benchmarks/hunt.py, seed 12)."""
    geoms = hunt_geometries()
    results = [run_case(make_case(i, 12, geoms), geoms) for i in range(40)]
    bad = [r for r in results if r["outcome"] in ("false_lock", "crash", "setup_error")]
    assert not bad, bad
    assert sum(r["outcome"] == "ok" for r in results) >= 1  # not vacuous: some slices lock, checked against the truth


def test_a_print_too_large_is_scaled_about_the_fiducial_centre_not_the_image_corner():
    """Hand-worked: the fiducial's axis along z through (30, 40) mm, its centre 10 mm off the slice's plane z = 0;
    the pixel at that centre's foot (row 80, col 60 at 0.5 mm) stays at (30, 40, 0), and pixel (0, 0) moves 0.4 %
    further from it."""
    geom = hunt_geometries()["neuro"]
    T = rigid(np.eye(3), [30.0, 40.0, 10.0 - 0.5 * geom.body.length])
    sl = Slice(np.zeros((128, 128)), (0.5, 0.5), slice_thickness_mm=2.0)
    big = print_scaled(sl, T, geom, 0.004)
    assert big.pixel_spacing_mm == pytest.approx((0.502, 0.502))
    at = big.origin_mm + 60 * big.pixel_spacing_mm[1] * big.col_dir + 80 * big.pixel_spacing_mm[0] * big.row_dir
    assert at == pytest.approx([30.0, 40.0, 0.0])
    assert np.linalg.norm(big.origin_mm - at) == pytest.approx(1.004 * 50.0)


@pytest.mark.parametrize("kind, cases", [("other_design", 12), ("water_bath", 12)])
def test_print_hunt_short(kind, cases):
    """The print hunt's cases (seed 5, as benchmarks/hunt_print.py runs them): slices solved with the other design's
    geometry file never lock, and fiducials in a water bath lock without a false lock (the full runs are in
    docs/benchmarks.md)."""
    geoms = hunt_geometries()
    wrong = other_design_geometries(geoms) if kind == "other_design" else None
    out = [run_print_case(i, 5, kind, 0.0, geoms, wrong)["outcome"] for i in range(cases)]
    assert "crash" not in out and "false_lock" not in out, out
    if kind == "other_design":
        assert set(out) == {"no_lock"}
    else:
        assert "ok" in out


def test_a_case_is_its_index_and_seed_alone():
    """Case 17 of seed 3 is the same whatever was drawn before it; the blob width has its own stream, so drawing it
    changes nothing else."""
    geoms = hunt_geometries()
    first = make_case(17, 3, geoms)
    [make_case(i, 3, geoms) for i in range(5)]
    assert make_case(17, 3, geoms) == first
    assert make_case(18, 3, geoms) != first and make_case(17, 4, geoms) != first
    assert first.index == 17 and first.geometry in geoms and first.mutation in MUTATIONS and first.blob_width == 1.0
    wide = make_case(17, 3, geoms, (1.0, 2.5))
    assert 1.0 < wide.blob_width < 2.5 and dataclasses.replace(wide, blob_width=1.0) == first
    assert noisy_case(17, 3, geoms) == dataclasses.replace(first, mutation="noisy")


def test_a_flip_maps_new_pixels_to_old_ones_by_hand():
    """np.fliplr on 4 x 6 pixels of 0.5 x 0.8 mm: new (r, c) is old (r, 5 - c), so new x' is old 4.0 - x' mm, y
    unchanged, and the plane is seen from its other side (z flips)."""
    A, t = index_map(np.fliplr, (4, 6))
    np.testing.assert_array_equal(A, [[1, 0], [0, -1]])
    np.testing.assert_array_equal(t, [0, 5])
    T = T_old_from_new(A, t, (0.5, 0.8), (0.5, 0.8))
    np.testing.assert_allclose(T, [[-1, 0, 0, 4.0], [0, 1, 0, 0], [0, 0, -1, 0], [0, 0, 0, 1]])


@pytest.mark.parametrize("op", [lambda a: np.rot90(a, 1), lambda a: np.rot90(a, 2), lambda a: np.rot90(a, 3),
                                np.fliplr, np.flipud, lambda a: np.rot90(np.fliplr(a))])
def test_every_rotation_or_flip_puts_each_pixel_where_its_transform_says(op):
    """The hunt's six re-indexings of a square-pixel image: every new pixel's centre, taken to the old image's frame
    by T_old_from_new, lands on the old pixel holding the same value."""
    s = 0.5
    old = np.arange(5 * 7, dtype=float).reshape(5, 7)
    new = op(old)
    T = T_old_from_new(*index_map(op, old.shape), (s, s), (s, s))
    for r in range(new.shape[0]):
        for c in range(new.shape[1]):
            x, y = (T @ [c * s, r * s, 0.0, 1.0])[:2]
            assert old[round(y / s), round(x / s)] == new[r, c]


def _values_at_crossings(img, geom, T, spacing):
    rc = np.round(true_centres_rc(geom, T, spacing)).astype(int)
    inside = (rc >= 0).all(axis=1) & (rc[:, 0] < img.shape[0]) & (rc[:, 1] < img.shape[1])
    return img[rc[inside, 0], rc[inside, 1]]


def test_the_truth_of_a_rotated_or_flipped_slice_follows_the_image():
    """Seed 0 case 80 (a needle-guide slice in the envelope, rotated or flipped): all nine crossings of the truth it
    returns lie on fluid (about 1), the crossings of the slice's truth before the flip on background (about 0.04)."""
    geoms = hunt_geometries()
    case = make_case(80, 0, geoms)
    assert case.mutation == "rotated_flipped"
    geom = geoms[case.geometry]
    sl, T_true, in_envelope = build_case(case, geom)
    img = np.asarray(sl.pixels)
    on = _values_at_crossings(img, geom, T_true, sl.pixel_spacing_mm)
    assert in_envelope and len(on) == 9 and on.min() > 0.9
    _, T_before, _ = build_case(dataclasses.replace(case, mutation="noisy"), geom)
    assert np.median(_values_at_crossings(img, geom, T_before, sl.pixel_spacing_mm)) < 0.1


def test_the_truth_of_a_resampled_rotation_follows_the_image():
    """The unlisted damage rotate_resample (seed 7 case 2, a needle-guide slice turned by a non-right angle): the
    truth turned with it finds fluid at every crossing; the unturned truth mostly background."""
    geoms = hunt_geometries()
    sl, T_true, case, in_envelope = unlisted_slice(2, 7, "rotate_resample", geoms)
    geom = geoms[case.geometry]
    img = np.asarray(sl.pixels)
    on = _values_at_crossings(img, geom, T_true, sl.pixel_spacing_mm)
    assert in_envelope and len(on) == 9 and on.min() > 0.6
    _, T_before, _ = build_case(noisy_case(2, 7, geoms), geom)
    assert np.median(_values_at_crossings(img, geom, T_before, sl.pixel_spacing_mm)) < 0.45


def test_pose_error_by_hand():
    """A pose turned 30 deg about the axis and moved (3, 4, 0) mm: the frame centre, on the axis, moves 5 mm."""
    tre, rot = pose_error(rigid(rot_z(30.0), (3.0, 4.0, 0.0)), np.eye(4), 50.0)
    assert tre == pytest.approx(5.0) and rot == pytest.approx(30.0)


def test_a_lock_is_judged_against_the_truth():
    """Seed 0 case 80 locks 0.02 mm from its truth (ok); judged against that truth moved 1 mm it is a false lock."""
    geoms = hunt_geometries()
    case = make_case(80, 0, geoms)
    geom = geoms[case.geometry]
    sl, T_true, _ = build_case(case, geom)
    right = solve_and_judge(sl, geom, T_true, ndigits=4)
    assert right["outcome"] == "ok" and right["tre_mm"] < 0.05
    wrong = solve_and_judge(sl, geom, rigid(np.eye(3), (0.0, 0.0, 1.0)) @ T_true)
    assert wrong["outcome"] == "false_lock" and 0.95 < wrong["tre_mm"] < 1.05


def test_other_design_geometries_swap_the_designs():
    assert other_design_geometries({"b": 2, "a": 1}) == {"a": 2, "b": 1}
    assert other_design_geometries({"a": 1, "b": 2, "c": 3}) == {"a": 2, "b": 3, "c": 1}
