"""A volume registered from every slice the frame is in: real scans, partial slices, the scatter the data show."""

import dataclasses
import math

import numpy as np
import pytest

from chic_register.cli.inputs import load_prior
from chic_register.detect.blobs import Blobs
from chic_register.errors import NoLock
from chic_register.fit.scatter import Scatter
from chic_register.imaging.simulate import simulate_volume
from chic_register.io.volumes import read_volume
from chic_register.model.pose import rigid, rot_y, rot_z
from chic_register.pipeline.every_slice import MIN_SLICE_TUBES, enclosing_blobs
from chic_register.pipeline.volume import register_volume
from tests.conftest import REAL
from tests.helpers import ZF_CENTRE, pose_difference, tre_mm

#: ZFrameRegistration's pose of the masked scan (tests/data/real/README.md), slices 6-11.
MASKED_B_REFERENCE = np.array([[-0.999919, 0.012362, 0.003162, 11.135927],
                               [-0.012422, -0.999728, -0.019757, -14.787442],
                               [0.002917, -0.019795, 0.999800, -136.789753],
                               [0.0, 0.0, 0.0, 1.0]])


def test_scatter_is_the_model_error_that_puts_the_median_residual_at_its_chi_square_median():
    m = 0.3
    r2 = np.full(11, 2.0 * math.log(2.0) * (0.01 ** 2 + m ** 2))  # every residual at the median of its chi-square
    sc = Scatter.of(r2, np.full(11, 0.01))
    assert sc.model_error_mm == pytest.approx(m, rel=1e-6)
    np.testing.assert_allclose(sc.sigma_mm, math.hypot(0.01, m), rtol=1e-6)
    # residuals the noise alone explains leave no model error
    assert Scatter.of(np.full(5, 1e-4), np.full(5, 0.05)).model_error_mm == 0.0


def test_a_split_blob_knows_its_whole():
    mask = np.ones((4, 6), bool)
    half = np.zeros((4, 6), bool)
    half[:, :3] = True
    b = Blobs(centres_rc=np.array([[11.5, 12.5], [11.5, 11.0], [40.0, 40.0]]), area_px=np.array([24.0, 12.0, 20.0]),
              mean_intensity=np.ones(3), axis_ratio=np.ones(3), contrast=np.full(3, 10.0), background=0.0,
              noise_sigma=1.0, threshold=0.5, footprints=((10, 10, mask), (10, 10, half), (38, 38, np.ones((5, 5), bool))))
    np.testing.assert_array_equal(enclosing_blobs(b), [-1, 0, -1])


def test_the_real_masked_scan_registers_from_every_slice_of_the_frame(zframe_geometry):
    """All seven slices that show the frame (5-11) are used, the image's 0.6 % scale along x is fitted, and the pose
    lands near the reference algorithm's (whose own spread over slice choices is 0.1 mm, 0.1-0.15 deg)."""
    reg = register_volume(read_volume(REAL / "zframe-masked-b.nrrd"), zframe_geometry, prior=load_prior("RAS"))
    used = sorted(int(s.source.split("[k=")[1].rstrip("]")) for s in reg.slices)
    assert used == list(range(5, 12))
    assert all(s.reason.startswith(("no blob where", "found 0")) for s in reg.skipped)
    assert reg.scale.fitted and reg.scale.axes == ("x", "y", "z")
    x = reg.scale.scale[0]
    assert 0.003 < x < 0.01 and x > 3 * reg.scale.scale_sd[0]
    assert tre_mm(reg.T_scanner_from_fiducial, MASKED_B_REFERENCE, ZF_CENTRE) < 0.2
    assert pose_difference(reg.T_scanner_from_fiducial, MASKED_B_REFERENCE)[1] < 0.3
    # the covariance is the scatter's (0.25 mm per coordinate, the model error), not the pixel noise's (0.015 mm)
    noise = reg.uncertainty.to_dict()["noise"]
    assert noise["measurement"].startswith("centroid + model error") and 0.5 < noise["residual_chi2_per_dof"] < 2


def test_the_clinical_scan_is_registered_from_every_slice_that_shows_its_rods(zframe_geometry):
    """The unmasked clinical scan (thighs far brighter than the rods, textured and fading rod sections): read at a
    level bounded by the noise, not between tissue and background, the rods of slices 3-13 are found (10-13 show
    only the four parallel rods as the slab fades) and fit one pose to about 0.2 mm, with the slice direction
    3 % short (the gradients' non-linearity 90-150 mm below the isocentre); the end slices 0-2, whose sections
    are crescents 0.8-2 mm off it, are named as disagreeing, and the faint rods of slice 14 as too faint to locate."""
    vol = read_volume(REAL / "zframe-clinical-3t.nrrd")
    reg = register_volume(vol, zframe_geometry, prior=load_prior("RAS"))
    used = sorted(int(s.source.split("[k=")[1].rstrip("]")) for s in reg.slices)
    assert set(range(3, 14)) <= set(used)
    assert all(s.n_tubes >= MIN_SLICE_TUBES for s in reg.slices)
    assert all(s.n_tubes >= 4 for s in reg.slices if int(s.source.split("[k=")[1].rstrip("]")) >= 10)
    disagree = [int(s.source.split("[k=")[1].rstrip("]")) for s in reg.skipped if s.reason.startswith("disagrees")]
    assert set(disagree) <= {0, 1, 2}
    # slice 14's rods are plain to the eye but below any detection level: its reason says so
    faint = [s.reason for s in reg.skipped if s.source.endswith("[k=14]")]
    assert faint and "too faint to locate" in faint[0]
    assert max(rotation_sd_deg(reg)) < 0.25
    z = reg.scale.scale[2]
    assert reg.scale.fitted and -0.05 < z < -0.01 and abs(z) > 2 * reg.scale.scale_sd[2]


def test_the_clinical_scan_registers_the_same_with_its_intensities_scaled_and_offset(zframe_geometry):
    """Intensities x 10 + 500 (a reconstruction's rescale, a DC offset: no exact zeros, a background far from 0) change
    each blob centre's noise estimate, and least squares over every slice then drags the start towards the three
    crescent slices; the pose the other slices agree on (a Cauchy-weighted fit) leaves
    them out as before, and the registration is the plain scan's."""
    vol = read_volume(REAL / "zframe-clinical-3t.nrrd")
    plain = register_volume(vol, zframe_geometry, prior=load_prior("RAS"))
    shifted = dataclasses.replace(vol, voxels=vol.voxels.astype(np.float32) * 10 + 500)
    reg = register_volume(shifted, zframe_geometry, prior=load_prior("RAS"))
    assert sorted(s.source for s in reg.slices) == sorted(s.source for s in plain.slices)
    assert tre_mm(reg.T_scanner_from_fiducial, plain.T_scanner_from_fiducial, ZF_CENTRE) < 0.02
    assert pose_difference(reg.T_scanner_from_fiducial, plain.T_scanner_from_fiducial)[1] < 0.02
    assert abs(reg.scale.scale[2] - plain.scale.scale[2]) < 0.005


def _noisier(voxels: np.ndarray) -> np.ndarray:
    """The magnitude of the scan plus complex Gaussian noise of 5 % of its bright level (SNR down by about 1.7)."""
    rng = np.random.default_rng(0)
    x = voxels.astype(float)
    s = 0.05 * np.percentile(x, 99.5)
    return np.hypot(x + rng.normal(0.0, s, x.shape), rng.normal(0.0, s, x.shape))


@pytest.mark.parametrize("change, rot_deg, tre", [
    ("quantised to 8 bits", 0.05, 0.02),
    ("noisier", 0.2, 0.1),
])
def test_the_clinical_scan_registers_the_same_quantised_or_noisier(zframe_geometry, change, rot_deg, tre):
    """Quantised to 8 bits, or with its noise raised: fewer slices lock alone (one, for the noisier scan), and the
    joint fit counts the slices in which it matches the whole pattern as locking at its pose; the registration is
    the plain scan's, from slices 3-13."""
    vol = read_volume(REAL / "zframe-clinical-3t.nrrd")
    plain = register_volume(vol, zframe_geometry, prior=load_prior("RAS"))
    x = vol.voxels.astype(float)
    voxels = np.round(255 * np.clip(x / x.max(), 0, 1)).astype(np.uint8) if change.startswith("quantised") \
        else _noisier(vol.voxels)
    reg = register_volume(dataclasses.replace(vol, voxels=voxels), zframe_geometry, prior=load_prior("RAS"))
    used = sorted(int(s.source.split("[k=")[1].rstrip("]")) for s in reg.slices)
    assert set(range(4, 13)) <= set(used) <= set(range(3, 15))
    assert tre_mm(reg.T_scanner_from_fiducial, plain.T_scanner_from_fiducial, ZF_CENTRE) < tre
    assert pose_difference(reg.T_scanner_from_fiducial, plain.T_scanner_from_fiducial)[1] < rot_deg


def test_every_second_slice_of_the_clinical_scan_is_one_pose_or_refused(zframe_geometry):
    """Every second slice (4 mm apart): a crescent end slice among only five splits the joint fits of the slices
    that locked alone into two poses 0.8 deg apart; read again with their faint sections, both reach the pose of
    slices 4-12, the plain scan's. Its slice direction's scale, -7 +- 1.2 % from five slices, is fitted (beyond the
    5 % limit by its noise only), and the pose's 3 sigma of 0.76 deg is refused by the default trust limit and
    accepted by a looser one; never a one-slice pose."""
    vol = read_volume(REAL / "zframe-clinical-3t.nrrd")
    plain = register_volume(vol, zframe_geometry, prior=load_prior("RAS"))
    si, sj, sk = vol.spacing_mm
    thinned = dataclasses.replace(vol, voxels=vol.voxels[::2].copy(), spacing_mm=(si, sj, 2 * sk),
                                  slice_thickness_mm=vol.thickness_mm)
    with pytest.raises(NoLock, match="not precise enough"):
        register_volume(thinned, zframe_geometry, prior=load_prior("RAS"))
    reg = register_volume(thinned, zframe_geometry, prior=load_prior("RAS"), trust_rot_deg=1.0)
    used = sorted(int(s.source.split("[k=")[1].rstrip("]")) for s in reg.slices)
    assert used == [2, 3, 4, 5, 6]
    assert reg.scale.fitted and reg.scale.scale[2] < -0.05
    assert tre_mm(reg.T_scanner_from_fiducial, plain.T_scanner_from_fiducial, ZF_CENTRE) < 0.1
    assert pose_difference(reg.T_scanner_from_fiducial, plain.T_scanner_from_fiducial)[1] < 0.1


@pytest.mark.parametrize("stretch, ok", [(1.03, True), (1.06, False), (1.12, False)])
def test_a_slice_spacing_off_by_a_few_per_cent_is_fitted_and_a_wrong_one_refused(z001, cut_volume, stretch, ok):
    """The volume's slice spacing declared 3 % too large (what the gradients' non-linearity does across the slices
    far from the isocentre) is fitted, the pose within 0.3 mm of where the image shows the frame; 6 % and 12 % (the
    end slices' diagonals 4 mm off any rigid pose) are refused naming the slice spacing. In-plane, 3 % stays beyond
    the 2 % a calibration explains."""
    T = cut_volume.T_scanner_from_fiducial
    vol = cut_volume.volume
    sx, sy, sz = vol.spacing_mm
    declared = dataclasses.replace(vol, spacing_mm=(sx, sy, sz * stretch))
    prior = rigid(T[:3, :3], (0, 0, 0))
    if not ok:
        with pytest.raises(NoLock, match="along z .* check the slice spacing"):
            register_volume(declared, z001, prior=prior)
        return
    reg = register_volume(declared, z001, prior=prior)
    assert reg.scale.fitted and reg.scale.scale[2] == pytest.approx(1 / stretch - 1, abs=3 * reg.scale.scale_sd[2])
    # the frame's centre as the declared volume shows it: its slice index stays, its depth along k stretches
    A, A_declared = vol.affine_lps, declared.affine_lps
    centre = A_declared @ np.linalg.inv(A) @ T @ np.append(ZF_CENTRE, 1.0)
    got = reg.T_scanner_from_fiducial @ np.append(ZF_CENTRE, 1.0)
    assert np.linalg.norm((got - centre)[:3]) < 0.3
    with pytest.raises(NoLock, match="along x .* check the pixel spacing"):
        register_volume(dataclasses.replace(vol, spacing_mm=(sx * 1.03, sy, sz)), z001, prior=prior)


def rotation_sd_deg(reg) -> np.ndarray:
    """(3,) the pose's rotation standard deviations (deg) about F's axes."""
    return np.sqrt(np.diag(reg.uncertainty.covariance)[:3])


@pytest.fixture(scope="module")
def cut_volume(z001):
    """A tilted Z-frame volume reaching past both ends of the frame."""
    T = rigid(rot_z(15) @ rot_y(6), (1.0, -2.0, -30.0))
    sv = simulate_volume(z001, T, (96, 96, 30), (1.0, 1.0, 2.5), noise="rician", snr=20, rng=3, supersample=2,
                         thickness_samples=2)
    return sv


def test_a_slice_with_rods_missing_still_counts_its_visible_rods(z001, cut_volume):
    T = cut_volume.T_scanner_from_fiducial
    vox = np.array(cut_volume.volume.voxels)
    prior = rigid(T[:3, :3], (0, 0, 0))
    whole = register_volume(cut_volume.volume, z001, prior=prior)
    k = sorted(int(s.source.split("[k=")[1].rstrip("]")) for s in whole.slices)[len(whole.slices) // 2]
    third = vox.shape[2] // 3
    vox[k, :, :third] = vox[0, :, :third]  # a third of the slice shows only noise (an empty slice's)
    reg = register_volume(dataclasses.replace(cut_volume.volume, voxels=vox), z001, prior=prior)
    cut = [s for s in reg.slices if s.source.endswith(f"[k={k}]")]
    assert cut and MIN_SLICE_TUBES <= cut[0].n_tubes < 7
    assert tre_mm(reg.T_scanner_from_fiducial, T, ZF_CENTRE) < 0.3


def test_a_symmetric_frames_starts_are_the_twins_the_prior_allows(z001, cut_volume):
    """z001 maps onto itself under a half turn: a slice locked alone finds either twin (at random where the image is
    stretched a little), and a volume whose slices all found the one the prior rules out was refused as mounted
    upside down; every start is taken as its twin nearest the prior."""
    from chic_register.model.pose import near_prior, rotation_deg
    from chic_register.model.tube_model import prepare_geometry
    from chic_register.options import SolveOptions
    from chic_register.pipeline.detection import check_pixel_range, detect_slices
    from chic_register.pipeline.every_slice import starting_poses, symmetry_twins

    T = cut_volume.T_scanner_from_fiducial
    opts = SolveOptions(prior=rigid(T[:3, :3], (0, 0, 0)))
    slices = [cut_volume.volume.native_slice(k) for k in range(cut_volume.volume.shape[0])]
    model, _ = prepare_geometry(z001)
    seen = detect_slices(slices, check_pixel_range(slices), model)
    twins = symmetry_twins(z001, model, opts)
    assert len(twins) == 1  # the half turn about y
    plain, _ = starting_poses(model, seen, opts)
    assert any(not near_prior(X, opts) for _, X, _ in plain)  # a lone lock knows no prior
    starts, _ = starting_poses(model, seen, opts, twins)
    assert starts and all(near_prior(X, opts) for _, X, _ in starts)
    assert min(rotation_deg(X[:3, :3].T, T[:3, :3]) for _, X, _ in starts) < 1.0
