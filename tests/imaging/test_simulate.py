"""The slice simulator: rendering against analytic crossings and areas, noise statistics, truth."""

import math

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree

from chic_register.imaging.render import render_slice
from chic_register.imaging.simulate import (
    add_rician_noise,
    add_uniform_noise,
    crossings_px,
    simulate_slice,
    simulate_volume,
)
from chic_register.model.geometry import FiducialGeometry
from chic_register.model.pose import apply, invert, slice_frame
from chic_register.model.tubes import LineTube
from tests.helpers import OBLIQUE, T_TRUE

SHAPE = (256, 256)
CENTER = ((SHAPE[0] - 1) / 2, (SHAPE[1] - 1) / 2)


def blob_centroids(img):
    """Intensity-weighted centroid (row, col) of each connected blob of a noise-free image."""
    lab, n = ndimage.label(img > 0)
    return lab, np.array(ndimage.center_of_mass(img, lab, range(1, n + 1))).reshape(-1, 2)


def centroid_errors_px(geom, T, thickness=0.0):
    """Distance (px) from each tube's analytic crossing to the centroid of its rendered blob (tube alone)."""
    errors = {}
    for tid, px in crossings_px(geom, T, (0.5, 0.5), CENTER).items():
        assert len(px) == 1, tid
        one = FiducialGeometry("one", geom.body, (geom.tube(tid),))
        img = render_slice(one, T, SHAPE, (0.5, 0.5), thickness)
        lab, cents = blob_centroids(img)
        assert len(cents) == 1, tid
        errors[tid] = float(np.hypot(*(cents[0] - px[0])))
    return errors


@pytest.mark.parametrize("depth, twist, thickness", [(5, 0, 0.0), (25, 17, 0.0), (40, 63, 0.0), (25, 30, 2.0)])
def test_centroids_match_analytic_crossings_at_tilt_0(neuro_geometry, depth, twist, thickness):
    T = slice_frame(depth, 0.0, 0.0, twist)
    errors = centroid_errors_px(neuro_geometry, T, thickness)
    assert max(errors.values()) < 0.02, errors


def test_centroids_match_analytic_crossings_tilted(neuro_geometry, needle_geometry):
    for geom, pose in ((neuro_geometry, (20, 30, 40, 10)), (needle_geometry, (15, 20, 200, 75))):
        T = slice_frame(*pose)
        errors = centroid_errors_px(geom, T)
        assert max(errors.values()) < 0.02, errors


def test_axis_crossing_moves_with_center_px(neuro_geometry):
    """Moving center_px moves the whole picture by the same number of pixels."""
    T = slice_frame(25, 0, 0, 0)
    a = render_slice(neuro_geometry, T, (128, 128), (0.5, 0.5), 0.0, center_px=(60, 70))
    b = render_slice(neuro_geometry, T, (128, 128), (0.5, 0.5), 0.0, center_px=(63, 65))
    assert np.allclose(a[:-3, 5:], b[3:, :-5], atol=1e-12)


@pytest.mark.parametrize("tilt, azimuth", [(0, 0), (30, 40), (60, 200)])
@pytest.mark.parametrize("tube_id", ["D0", "H1"])
def test_partial_volume_area_is_the_ellipse_area(neuro_geometry, tilt, azimuth, tube_id):
    """Sum of fluid fraction x pixel area = pi r^2 / cos(angle between tube and normal)."""
    tube = neuro_geometry.tube(tube_id)
    one = FiducialGeometry("one", neuro_geometry.body, (tube,))
    T = slice_frame(25, tilt, azimuth, 10)
    img = render_slice(one, T, SHAPE, (0.5, 0.5), 0.0)
    crossing = tube.intersect_plane(T[:3, 3], T[:3, 2])
    u = (crossing[0, 2] - tube.z_range[0]) / (tube.z_range[1] - tube.z_range[0])
    cos_angle = abs(float(tube.tangents(u)[0] @ T[:3, 2]))
    expected = math.pi * (tube.diameter / 2) ** 2 / cos_angle
    assert img.sum() * 0.25 == pytest.approx(expected, rel=3e-3)
    assert img.max() == pytest.approx(1.0) and img.min() >= 0.0


@pytest.mark.parametrize("height_mm", [0.0, 0.9])
def test_a_tube_lying_in_the_plane_is_a_band(neuro_geometry, height_mm):
    """A Z-frame-like horizontal line tube 0.9 mm off an axial slice: a band 2 sqrt(r^2 - h^2) wide, L long."""
    bar = LineTube("Z0", "other", (-15.0, 5.0, 20.0 + height_mm), (15.0, 5.0, 20.0 + height_mm), 3.0)
    img = render_slice(FiducialGeometry("z", neuro_geometry.body, (bar,)), slice_frame(20.0, 0, 0, 0), SHAPE,
                       (0.5, 0.5), 0.0)
    assert img.sum() * 0.25 == pytest.approx(30.0 * 2 * math.sqrt(1.5**2 - height_mm**2), rel=2e-3)
    rows = np.nonzero(img.sum(axis=1))[0]
    assert (rows.min() + rows.max()) / 2 == pytest.approx(CENTER[0] + 10.0)


def test_tilted_cut_through_the_end_face_matches_brute_force(neuro_geometry):
    """A 70-degree plane meets D0's line 1 mm below its end and clips it: compare with dense point sampling."""
    d0 = FiducialGeometry("d0", neuro_geometry.body, (neuro_geometry.tube("D0"),))
    tilt = math.radians(70)
    T = slice_frame(12.5 * math.tan(tilt) - 1.0, 70.0, 0.0, 0.0)
    end_S = apply(invert(T), [12.5, 0.0, 0.0])  # D0's bottom end, put at the image centre
    shape, cc = (64, 64), 31.5 - end_S[0] / 0.5
    img = render_slice(d0, T, shape, (0.5, 0.5), 0.0, center_px=(31.5 - end_S[1] / 0.5, cc))
    rc = 31.5 - end_S[1] / 0.5
    n = 16  # n x n exact inside tests per pixel
    sub = (np.arange(n) + 0.5) / n - 0.5
    ii, jj, si, sj = np.meshgrid(np.arange(64), np.arange(64), sub, sub, indexing="ij")
    pts = apply(T, np.stack([(jj + sj - cc).ravel() * 0.5, (ii + si - rc).ravel() * 0.5, 0 * ii.ravel()], axis=1))
    inside = (np.hypot(pts[:, 0] - 12.5, pts[:, 1]) <= 1.5) & (pts[:, 2] >= 0) & (pts[:, 2] <= 50)
    brute = inside.reshape(64, 64, n * n).mean(axis=2)
    assert brute.sum() > 2.0 and brute[0].sum() == brute[-1].sum() == brute[:, 0].sum() == brute[:, -1].sum() == 0
    assert np.abs(img - brute).max() < 0.08
    assert img.sum() == pytest.approx(brute.sum(), rel=0.01)


def test_steep_helix_section_matches_exact_distance_sampling(neuro_geometry):
    """At tilt 60 a helix section is curved (its centroid leaves the crossing by ~0.1 px): the
    rendering must follow the exact distance to the helix, not only the tangent line."""

    tube = neuro_geometry.tube("H1")
    T = slice_frame(20.0, 60.0, 40.0, 0.0)
    C = (47.5, 47.5)
    img = render_slice(FiducialGeometry("h", neuro_geometry.body, (tube,)), T, (96, 96), (0.5, 0.5), 0.0, center_px=C)
    z_c = tube.intersect_plane(T[:3, 3], T[:3, 2])[0, 2]
    zs = np.linspace(z_c - 12, z_c + 12, 24001)
    tree = cKDTree(tube.point_at_z(zs))
    n = 8
    sub = (np.arange(n) + 0.5) / n - 0.5
    rows, cols = np.nonzero(ndimage.binary_dilation(img > 0, iterations=3))
    ii, si, sj = rows[:, None, None] + sub[:, None], sub[:, None], sub[None, :]
    ys = np.broadcast_to(ii + 0 * sj, (len(rows), n, n))
    xs = np.broadcast_to(cols[:, None, None] + sj + 0 * si, (len(rows), n, n))
    pts = apply(T, np.stack([(xs - C[1]).ravel() * 0.5, (ys - C[0]).ravel() * 0.5, 0 * xs.ravel()], axis=1))
    inside = tree.query(pts, distance_upper_bound=2.0)[0] <= 1.5
    brute = np.zeros_like(img)
    brute[rows, cols] = inside.reshape(len(rows), n * n).mean(axis=1)
    c_img, c_brute = ndimage.center_of_mass(img), ndimage.center_of_mass(brute)
    crossing = crossings_px(FiducialGeometry("h", neuro_geometry.body, (tube,)), T, (0.5, 0.5), C)["H1"][0]
    assert np.hypot(*np.subtract(c_brute, crossing)) > 0.05  # the curvature shows
    assert np.hypot(*np.subtract(c_img, c_brute)) < 0.01
    assert img.sum() == pytest.approx(brute.sum(), rel=2e-3)
    assert np.abs(img - brute).max() < 0.06


def test_slice_thickness_partial_volume_at_the_end_face(neuro_geometry):
    """A 2 mm slab centred on the bottom face holds fluid in its upper half only."""
    d0 = FiducialGeometry("d0", neuro_geometry.body, (neuro_geometry.tube("D0"),))
    T = slice_frame(0.0, 0, 0, 0)
    row, col = crossings_px(d0, T, (0.5, 0.5), CENTER)["D0"][0]
    thick = render_slice(d0, T, SHAPE, (0.5, 0.5), 2.0, thickness_samples=4)
    assert thick[int(round(row)), int(round(col))] == pytest.approx(0.5)
    inside = render_slice(d0, slice_frame(25.0, 0, 0, 0), SHAPE, (0.5, 0.5), 2.0)
    assert inside[int(round(row)), int(round(col))] == pytest.approx(1.0)
    outside = render_slice(d0, slice_frame(-1.5, 0, 0, 0), SHAPE, (0.5, 0.5), 2.0)
    assert outside.max() == 0.0


def test_uniform_noise_statistics():
    rng = np.random.default_rng(1)
    ones = add_uniform_noise(np.ones((256, 256)), 0.3, rng)
    assert ones.mean() == pytest.approx(1.0, abs=0.005)
    assert ones.std() == pytest.approx(0.3 / math.sqrt(3), rel=0.02)
    zeros = add_uniform_noise(np.zeros((256, 256)), 0.3, rng)
    assert zeros.min() == 0.0 and zeros.max() <= 0.3
    assert np.mean(zeros == 0.0) == pytest.approx(0.5, abs=0.01)  # clipped half
    assert zeros.mean() == pytest.approx(0.3 / 4, rel=0.02)


def test_rician_noise_statistics():
    rng = np.random.default_rng(2)
    snr = 10.0
    s = 1.0 / snr
    background = add_rician_noise(np.zeros((256, 256)), snr, rng)
    assert background.mean() == pytest.approx(s * math.sqrt(math.pi / 2), rel=0.01)  # Rayleigh
    assert background.std() == pytest.approx(s * math.sqrt((4 - math.pi) / 2), rel=0.02)
    fluid = add_rician_noise(np.ones((256, 256)), snr, rng)
    assert fluid.mean() == pytest.approx(1 + s**2 / 2, rel=0.003)
    assert fluid.std() == pytest.approx(s, rel=0.03)
    with pytest.raises(ValueError):
        add_rician_noise(np.zeros(3), 0.0, rng)


def test_truth_maps_fiducial_crossings_onto_their_pixels(neuro_geometry):
    """pixel_to_scanner(centre of a tube) = T_scanner_from_fiducial @ (crossing in F), off-centre and oblique."""
    ori = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])  # a sagittal image
    rot = np.array([[1.0, 0, 0], [0, math.cos(0.3), -math.sin(0.3)], [0, math.sin(0.3), math.cos(0.3)]])
    ori = ori @ rot.T
    sim = simulate_slice(
        neuro_geometry, 30.0, 25.0, 110.0, -40.0, center_offset_mm=(7.0, -4.5),
        image_position=(12.0, -80.0, 33.0), image_orientation=ori.ravel(), slice_thickness_mm=0.0,
    )
    t = sim.truth
    assert t.center_px == pytest.approx((127.5 - 9.0, 127.5 + 14.0))
    for tid, (row, col) in t.centres_px.items():
        tube = neuro_geometry.tube(tid)
        crossing_F = tube.intersect_plane(t.T_F_from_S[:3, 3], t.T_F_from_S[:3, 2])[0]
        assert np.allclose(sim.slice.pixel_to_scanner(row, col)[0], apply(t.T_scanner_from_fiducial, crossing_F), atol=1e-9)
    # the fiducial axis crosses the image at the axis-crossing pixel
    axis_point = apply(t.T_scanner_from_fiducial, [0.0, 0.0, t.angles.depth_mm])
    assert np.allclose(sim.slice.pixel_to_scanner(*t.center_px)[0], axis_point, atol=1e-9)
    assert np.allclose(sim.slice.pixel_to_scanner(0, 0)[0], (12.0, -80.0, 33.0))
    assert (t.angles.depth_mm, t.angles.tilt_deg, t.angles.azimuth_deg, t.angles.twist_deg) == pytest.approx((30, 25, 110, -40))
    # the rendered blob sits on the truth
    lab, cents = blob_centroids(sim.slice.pixels)
    r, c = t.centres_px["D1"]
    assert np.hypot(*(cents[lab[round(r), round(c)] - 1] - (r, c))) < 0.05


def test_default_placement_is_axial_centred_at_scanner_origin(neuro_geometry):
    sim = simulate_slice(neuro_geometry, 20.0, 0.0, slice_thickness_mm=0.0)
    assert np.allclose(sim.slice.pixel_to_scanner(127.5, 127.5)[0], 0.0)
    assert np.allclose(sim.slice.col_dir, (1, 0, 0)) and np.allclose(sim.slice.row_dir, (0, 1, 0))
    # at zero pose the fiducial frame is the scanner frame shifted by -depth along z
    assert np.allclose(sim.truth.T_scanner_from_fiducial, np.array(
        [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -20.0], [0, 0, 0, 1]]), atol=1e-12)
    T = np.eye(4)
    T[:3, 3] = (5, 6, 7)
    moved = simulate_slice(neuro_geometry, 20.0, 0.0, slice_thickness_mm=0.0, T_scanner_from_image=T)
    assert np.allclose(moved.slice.origin_mm, (5, 6, 7))
    assert np.allclose(invert(moved.truth.T_scanner_from_fiducial) @ moved.slice.T_scanner_from_image(),
                       invert(sim.truth.T_scanner_from_fiducial) @ sim.slice.T_scanner_from_image())


def test_a_series_of_slices_shares_a_chosen_fiducial_pose(neuro_geometry):
    """Parallel slices 2 mm apart, like the paper's real series, all at one fiducial pose in the scanner."""
    c, s = math.cos(0.4), math.sin(0.4)
    T_sf = np.array([[c, 0, s, 10.0], [0, 1, 0, -20.0], [-s, 0, c, 55.0], [0, 0, 0, 1]])
    sims = [simulate_slice(neuro_geometry, d, 15.0, 30.0, 5.0, slice_thickness_mm=0.0, T_scanner_from_fiducial=T_sf)
            for d in (20.0, 22.0, 24.0)]
    normals = [sim.slice.normal for sim in sims]
    assert np.allclose(normals[0], normals[1]) and np.allclose(normals[0], normals[2])
    gaps = [float((b.slice.origin_mm - a.slice.origin_mm) @ normals[0]) for a, b in zip(sims, sims[1:])]
    assert gaps == pytest.approx([2.0 * math.cos(math.radians(15))] * 2)
    for sim in sims:
        t = sim.truth
        assert np.allclose(t.T_scanner_from_fiducial, T_sf, atol=1e-12)
        for tid, (row, col) in t.centres_px.items():
            crossing = neuro_geometry.tube(tid).intersect_plane(t.T_F_from_S[:3, 3], t.T_F_from_S[:3, 2])[0]
            assert np.allclose(sim.slice.pixel_to_scanner(row, col)[0], apply(T_sf, crossing), atol=1e-9)
    with pytest.raises(ValueError, match="rigid"):
        simulate_slice(neuro_geometry, 20.0, 0.0, T_scanner_from_fiducial=np.diag([2.0, 1, 1, 1]))


def test_missing_tube_bore_tool_and_distractors(neuro_geometry):
    kw = dict(slice_thickness_mm=1.0)
    clean = simulate_slice(neuro_geometry, 25.0, 20.0, 50.0, 5.0, **kw)
    sim = simulate_slice(neuro_geometry, 25.0, 20.0, 50.0, 5.0, missing_tubes=("H2",), bore_signal=0.7,
                         distractors=6, rng=np.random.default_rng(3), **kw)
    t = sim.truth
    assert "H2" not in t.centres_px and t.missing_tubes == ("H2",)
    r, c = clean.truth.centres_px["H2"]
    assert clean.slice.pixels[round(r), round(c)] > 0.9 and sim.slice.pixels[round(r), round(c)] == 0.0
    assert sim.slice.pixels[round(t.center_px[0]), round(t.center_px[1])] == pytest.approx(0.7)
    # distractors: new bright pixels, all outside the fiducial body
    extra = (sim.slice.pixels > 0) & (clean.slice.pixels == 0)
    tool = np.hypot(*(np.indices(SHAPE) - np.array(t.center_px)[:, None, None])) * 0.5 < 10.0
    extra &= ~tool
    assert ndimage.label(extra)[1] >= 3
    rows, cols = np.nonzero(extra)
    pts_S = np.stack([(cols - t.center_px[1]) * 0.5, (rows - t.center_px[0]) * 0.5, 0 * rows], axis=1)
    pts_F = apply(t.T_F_from_S, pts_S)
    outside = (np.hypot(pts_F[:, 0], pts_F[:, 1]) > neuro_geometry.body.outer_diameter / 2) | (pts_F[:, 2] < 0) | (
        pts_F[:, 2] > neuro_geometry.body.length)
    assert outside.all()
    with pytest.raises(ValueError, match="Q7"):
        simulate_slice(neuro_geometry, 25.0, 0.0, missing_tubes=("Q7",))


def test_noise_is_seeded(neuro_geometry):
    a = simulate_slice(neuro_geometry, 25.0, 10.0, noise="rician", snr=15, rng=7)
    b = simulate_slice(neuro_geometry, 25.0, 10.0, noise="rician", snr=15, rng=7)
    c = simulate_slice(neuro_geometry, 25.0, 10.0, noise="rician", snr=15, rng=8)
    assert np.array_equal(a.slice.pixels, b.slice.pixels) and not np.array_equal(a.slice.pixels, c.slice.pixels)
    u = simulate_slice(neuro_geometry, 25.0, 10.0, noise="uniform", noise_level=0.2, rng=7)
    clean = simulate_slice(neuro_geometry, 25.0, 10.0)
    diff = u.slice.pixels - clean.slice.pixels
    assert np.abs(diff).max() <= 0.2 and diff.std() > 0.05
    with pytest.raises(ValueError, match="noise"):
        simulate_slice(neuro_geometry, 25.0, 10.0, noise="gaussian")


@pytest.mark.parametrize("seed", range(4))
def test_render_windows_draws_each_tube_as_render_tubes_does(neuro_geometry, seed):
    """The verification's batched renderer: each tube alone in its own window, as render_tubes draws it (to rounding),
    for tilted slabs of 1-3 sub-planes, windows clipped by the sections, steep planes that cross a helix twice."""
    from chic_register.imaging.render import render_tubes, render_windows
    from chic_register.model.tube_model import plane_crossings, prepare_geometry

    rng = np.random.default_rng(seed)
    model = prepare_geometry(neuro_geometry)[0]
    drawn = 0
    for _ in range(6):
        T = slice_frame(rng.uniform(5, 45), rng.uniform(0, 80), rng.uniform(-180, 180), rng.uniform(-180, 180))
        spacing, thick, ts = (rng.uniform(0.3, 0.8), rng.uniform(0.3, 0.8)), rng.choice([0.0, 2.0]), int(rng.integers(1, 4))
        q = plane_crossings(model, T, margin_mm=5.0)[0]
        wins = [(tube, int(q[k, 1] / spacing[0]) - int(rng.integers(0, 25)), int(q[k, 0] / spacing[1]) - int(rng.integers(0, 25)),
                 int(rng.integers(2, 50)), int(rng.integers(2, 50)))
                for k, tube in enumerate(neuro_geometry.tubes) if np.isfinite(q[k]).all()]
        for (tube, r0, c0, h, w), img in zip(wins, render_windows(wins, T, spacing, thick, ts)):
            ref = render_tubes([tube], T, (h, w), spacing, thick, center_px=(-float(r0), -float(c0)), supersample=1,
                               thickness_samples=ts)
            np.testing.assert_allclose(img, ref, rtol=0, atol=1e-12)
            drawn += ref.max() > 0
    assert drawn > 10
    # a plane along the axis meets a steep helix at several points: one large window holds more than one section
    from chic_register.model.tubes import HelixTube

    helix = HelixTube("H", "helix", 12.5, 10.0, 12.0, 0.0, 50.0, 3.0)
    T = slice_frame(25.0, 90.0, helix.theta0_deg + 25.0 * helix.pitch_deg_per_mm, 0.0)
    T[:3, 3] += 12.2 * T[:3, 2]  # grazing the helix: two sections a few pixels apart, and one beyond each end
    assert len(helix.section_params(T[:3, 3], T[:3, 2], 4 * helix.diameter + 1.0)) == 4
    wins = [(helix, -60, -60, 120, 120), (helix, -10, -40, 20, 80)]
    for (tube, r0, c0, h, w), img in zip(wins, render_windows(wins, T, (0.5, 0.5), 2.0, 3)):
        ref = render_tubes([tube], T, (h, w), (0.5, 0.5), 2.0, center_px=(-float(r0), -float(c0)), supersample=1,
                           thickness_samples=3)
        np.testing.assert_allclose(img, ref, rtol=0, atol=1e-12)


def _centroids(img):
    lab, n = ndimage.label(img > 0.4 * img.max())
    return np.array(ndimage.center_of_mass(img, lab, range(1, n + 1)))


def test_simulated_volume_truth_places_the_tubes(neuro_geometry):
    """A noise-free volume has fluid on the D0 centreline and none on the axis."""
    sv = simulate_volume(neuro_geometry, T_TRUE, (64, 64, 30), (1.0, 1.0, 2.0), direction=OBLIQUE, noise="none")
    v = sv.volume
    A_inv = np.linalg.inv(v.affine_lps)
    d0 = neuro_geometry.tube("D0")
    for z in (15.0, 25.0, 35.0):
        on_tube = (A_inv @ np.append(apply(T_TRUE, d0.point_at_z(z)[0]), 1))[:3]
        on_axis = (A_inv @ np.append(apply(T_TRUE, [0, 0, z]), 1))[:3]
        i, j, k = np.rint(on_tube).astype(int)
        assert v.voxels[k, j, i] > 0.5 * sv.settings["signal"]
        i, j, k = np.rint(on_axis).astype(int)
        assert v.voxels[k, j, i] == 0.0
