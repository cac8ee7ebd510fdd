"""The k-space image model of the body mesh (chic_register.studies.kspace): fluid area, blob centres, noise, a solve.

Occupancy comes from the neuro design's CAD body, built once per test run
through the library and tessellated as its ``body.stl`` is (about 5 s), so
the tests check the model against the geometry, not against the solver's
section model.
"""

import math

import numpy as np
import pytest

from chic_design.cad.export import STL_ANGULAR_TOLERANCE_RAD, STL_TOLERANCE_MM
from chic_design.families import family_of
from chic_register.io.stl import write_stl
from chic_register.model.pose import apply, invert, slice_frame
from chic_register.pipeline.register import register
from chic_register.studies.calibration import pose_error
from chic_register.studies.kspace import (
    fluid_occupancy,
    kspace_image,
    kspace_window,
    read_body_mesh,
    slice_placement,
    slice_profile,
    with_noise,
)


@pytest.fixture(scope="module")
def neuro_mesh(neuro_spec, neuro_geometry):
    """The neuro body's triangles in F: vertices (V, 3) mm, faces (F, 3)."""
    body = family_of(neuro_spec).parts(neuro_spec, neuro_geometry).body
    verts, faces = body.tessellate(STL_TOLERANCE_MM, STL_ANGULAR_TOLERANCE_RAD)
    return np.array([[v.X, v.Y, v.Z] for v in verts]), np.asarray(faces, dtype=np.int64)


POSE = (25.0, 20.0, 40.0, 10.0)  # depth, tilt, azimuth, twist: every tube crosses the slice well inside the body


@pytest.fixture(scope="module")
def clean_image(neuro_mesh, neuro_geometry):
    """The noise-free complex image at POSE, its placement and the true pose."""
    sl, T = slice_placement(*POSE)
    return kspace_image(*neuro_mesh, neuro_geometry.body, T, sl), sl, T


def test_slice_profile_is_a_slab_of_the_thickness():
    z, w = slice_profile(2.0)
    assert z.shape == w.shape == (24,) and math.isclose(w.sum(), 1.0)
    assert z.min() > -2.0 and z.max() < 2.0 and np.allclose(w, w[::-1])
    half = np.interp(1.0, z, w / w.max())  # at the nominal edge the profile is near half its peak
    assert 0.35 < half < 0.65
    assert np.all(w[np.abs(z) > 1.6] < 0.1 * w.max())


def test_kspace_windows_keep_the_centre():
    for kind in ("none", "hamming", "tukey"):
        w = kspace_window(256, kind)
        assert w[128] == 1.0 and np.all(w <= 1.0) and np.all(w >= 0.0)
    assert kspace_window(256, "hamming")[0] < 0.1
    with pytest.raises(ValueError):
        kspace_window(256, "kaiser")


def test_axial_fluid_area_is_the_tubes_cross_sections(neuro_mesh, neuro_geometry):
    """At mid length every channel is cut once: fluid area = sum of pi r^2 / cos(angle of the tube to the axis)."""
    h = 0.05
    x = np.arange(-16.0, 16.0, h) + h / 3  # off the mesh's symmetry lines
    T_F_from_S = slice_frame(25.0, 0.0)
    occ = fluid_occupancy(*neuro_mesh, neuro_geometry.body, T_F_from_S, x, x, 0.0)
    expected = 0.0
    for t in neuro_geometry.tubes:
        cos_axis = abs(float(t.tangents(np.array([0.5]))[0, 2]))
        expected += math.pi * (t.diameter / 2) ** 2 / cos_axis
    assert occ.sum() * h * h == pytest.approx(expected, rel=0.01)


def test_blob_centroids_sit_on_the_centreline_crossings(clean_image, neuro_geometry):
    image, sl, T = clean_image
    mag = np.abs(image)
    T_F_from_image = invert(T) @ sl.T_scanner_from_image()
    T_image_from_F = invert(T_F_from_image)
    rows, cols = np.mgrid[0:mag.shape[0], 0:mag.shape[1]]
    found = 0
    for pts in neuro_geometry.intersect_plane(T_F_from_image[:3, 3], T_F_from_image[:3, 2]).values():
        for p in pts:
            if not 3.0 < p[2] < neuro_geometry.body.length - 3.0:
                continue
            x, y, _ = apply(T_image_from_F, p)
            r0, c0 = y / sl.pixel_spacing_mm[0], x / sl.pixel_spacing_mm[1]
            win = (rows - r0) ** 2 + (cols - c0) ** 2 < 4.0 ** 2  # 2 mm: clear of the nearest other blob
            w = mag * win
            rc = np.array([(w * rows).sum(), (w * cols).sum()]) / w.sum()
            assert np.hypot(*(rc - (r0, c0))) * sl.pixel_spacing_mm[0] < 0.02  # mm
            found += 1
    assert found == len(neuro_geometry.tubes)


def test_background_noise_has_the_requested_sigma(clean_image):
    image, sl, _ = clean_image
    noisy = with_noise(image, sl, 20.0, rng=3).pixels
    corner = np.concatenate([noisy[:40, :40].ravel(), noisy[-40:, -40:].ravel()])
    sigma = math.sqrt(np.mean(corner ** 2) / 2.0)  # Rayleigh: E[M^2] = 2 sigma^2
    assert sigma == pytest.approx(1.0 / 20.0, rel=0.05)
    fluid = np.abs(image) > 0.999  # the signal of fluid is 1 where the slab is all fluid
    assert fluid.sum() > 0 and np.abs(image).max() < 1.3


def test_a_kspace_slice_registers_near_the_truth(clean_image, neuro_geometry):
    image, sl, T = clean_image
    reg = register([with_noise(image, sl, 20.0, rng=1)], neuro_geometry)
    d = pose_error(T, reg.T_scanner_from_fiducial)
    assert np.linalg.norm(d[:3]) < 0.3  # deg
    assert np.linalg.norm(d[3:]) < 0.3  # mm


def test_a_hamming_filter_damps_the_ringing_and_keeps_the_pose(neuro_mesh, neuro_geometry, clean_image):
    """Gibbs undershoot (the real image below zero beside a blob) shrinks under the filter; the solve holds."""
    image, sl, T = clean_image
    filtered = kspace_image(*neuro_mesh, neuro_geometry.body, T, sl, kspace_filter="hamming")
    assert image.real.min() < -0.05 and filtered.real.min() > 0.3 * image.real.min()
    assert np.abs(filtered).max() < np.abs(image).max()
    reg = register([with_noise(filtered, sl, 20.0, rng=2)], neuro_geometry)
    d = pose_error(T, reg.T_scanner_from_fiducial)
    assert np.linalg.norm(d[:3]) < 0.5 and np.linalg.norm(d[3:]) < 0.5


def test_body_stl_reads_back_as_the_mesh(tmp_path, neuro_mesh):
    path = write_stl(tmp_path / "body.stl", *neuro_mesh)
    V, F = read_body_mesh(path)
    assert len(F) == len(neuro_mesh[1])
    assert np.allclose(V.min(axis=0), neuro_mesh[0].min(axis=0), atol=1e-4)
    assert np.allclose(V.max(axis=0), neuro_mesh[0].max(axis=0), atol=1e-4)


def test_a_filtered_slices_point_spread_is_measured_with_its_sections(neuro_mesh, neuro_geometry):
    """A Hamming k-space filter blurs every edge; a sharp section model weights the blurred edges wrongly and reads
    their sharpness as precision (noise-free, this slice is refused as imprecise, 1.4 deg at 3 sigma); with the
    point spread measured with the sections (``section_blur``, the default) it registers within 0.01 deg and mm."""
    from chic_register.errors import NoLock

    sl, T = slice_placement(35.0, 25.0, 300.0, 20.0)
    clean = with_noise(kspace_image(*neuro_mesh, neuro_geometry.body, T, sl, kspace_filter="hamming"), sl, None)
    d = pose_error(T, register([clean], neuro_geometry).T_scanner_from_fiducial)
    assert np.linalg.norm(d[:3]) < 0.01 and np.linalg.norm(d[3:]) < 0.01
    try:
        sharp = pose_error(T, register([clean], neuro_geometry, section_blur=False).T_scanner_from_fiducial)
    except NoLock:
        return
    assert np.linalg.norm(sharp[:3]) > 3 * np.linalg.norm(d[:3])


@pytest.mark.slow
@pytest.mark.parametrize("snr", [20.0, 50.0])
def test_the_covariance_is_calibrated_on_slices_the_solver_did_not_draw(neuro_mesh, neuro_geometry, snr):
    """Over three poses x 60 noise draws of k-space slices of the body mesh, the squared Mahalanobis length of the
    pose error under the reported covariance averages 6 (its dimension) within 10 %: the noise model, the measured
    point spread and the section model's own error floor (``MODEL_ERROR_PX``) together, at the SNR where the floor
    matters (50) and where it does not (20)."""
    from chic_register.errors import NoLock
    from chic_register.precision.uncertainty import mahalanobis2

    rng = np.random.default_rng(7)
    m2 = []
    for pose in ((35.0, 25.0, 300.0, 20.0), (30.0, 30.0, 100.0, 40.0), (25.0, 30.0, 60.0, 20.0)):
        sl, T = slice_placement(*pose)
        image = kspace_image(*neuro_mesh, neuro_geometry.body, T, sl)
        for _ in range(60):
            try:
                reg = register([with_noise(image, sl, snr, rng)], neuro_geometry)
            except NoLock:
                continue
            m2.append(mahalanobis2(pose_error(T, reg.T_scanner_from_fiducial), reg.uncertainty.covariance))
    assert len(m2) >= 150
    assert 5.4 <= float(np.mean(m2)) <= 6.6
