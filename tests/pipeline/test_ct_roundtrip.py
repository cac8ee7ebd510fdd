"""CT slices of an N-localizer (a Leksell-G-like box) registered back to their known pose.

Round trips: geometry -> simulated CT slice in Hounsfield units (air, plates, contrast rods with partial volume,
Gaussian noise, padding outside the reconstruction circle; a skull and metal streaks where said) -> register with
an orientation prior (the box is symmetric under a half turn about x) -> the target error at the frame centre.
A single slice normal to the rods does not fix the turn about the left-right axis to first order: refused.
"""


import numpy as np
import pytest

from chic_register.errors import ImprecisePose, NoLock
from chic_register.imaging.ct import CTScene
from chic_register.imaging.simulate import add_rician_noise, simulate_ct_slice, simulate_slice
from chic_register.model.pose import rigid, rot_y, rot_z
from chic_register.options import SolveOptions
from chic_register.pipeline.register import register
from tests.helpers import NLOC_CENTRE, leksell_g_ct, tre_mm

PRIOR = SolveOptions(prior=np.eye(4))  # F's axes ~ the scanner's LPS axes


@pytest.fixture(scope="module")
def nloc():
    return leksell_g_ct()


def _check(reg, T_true, tol_mm=0.3):
    """The pose is ok and within ``tol_mm`` at the frame centre; prints the TRE and the predicted TRE."""
    tre = tre_mm(reg.T_scanner_from_fiducial, T_true, NLOC_CENTRE)
    print(f"TRE {tre:.4f} mm, predicted {reg.uncertainty.predicted_tre_mm:.4f} mm")
    assert reg.status == "ok"
    assert tre < tol_mm
    return tre


# (depth, tilt, azimuth, twist): azimuth 90 tilts about x, 0 about y (the plates stay in view up to ~32 deg)
TILTED = [(60, 20, 90, 0), (40, 30, 90, 0), (80, 15, 90, 0), (60, 20, 0, 0), (60, 30, 0, 0)]


@pytest.mark.parametrize("pose", TILTED)
def test_tilted_ct_slice_registers(nloc, pose):
    sim = simulate_ct_slice(nloc, *pose, rng=np.random.default_rng(1))
    assert sim.slice.modality == "CT" and sim.slice.pixels.min() == -2048.0
    _check(register([sim.slice], nloc, options=PRIOR), sim.truth.T_scanner_from_fiducial)


def test_axial_ct_slice_is_refused_as_imprecise(nloc):
    """Normal to the rods, a turn about x moves no crossing to first order: the solver refuses, never guesses."""
    sim = simulate_ct_slice(nloc, 60, 0, 0, 0, rng=np.random.default_rng(1))
    with pytest.raises(ImprecisePose):
        register([sim.slice], nloc, options=PRIOR)
    assert issubclass(ImprecisePose, NoLock)


def test_parallel_axial_ct_slices_register_jointly(nloc):
    """Axial slices at 30..90 mm of one frame pose (turned 3 deg about x, shifted): registered together."""
    T = rigid(rot_z(90) @ rot_y(3.0) @ rot_z(-90), (2.0, -4.0, -60.0))
    sims = [simulate_ct_slice(nloc, d, 0, 0, 0, T_scanner_from_fiducial=T, rng=np.random.default_rng(d))
            for d in (30, 50, 70, 90)]
    reg = register([s.slice for s in sims], nloc, options=PRIOR)
    _check(reg, sims[0].truth.T_scanner_from_fiducial)


def test_ct_slice_with_skull_and_metal_streaks_registers(nloc):
    sim = simulate_ct_slice(nloc, 60, 25, 0, 0, scene=CTScene(skull=True, metal=True), rng=np.random.default_rng(1))
    _check(register([sim.slice], nloc, options=PRIOR), sim.truth.T_scanner_from_fiducial)


def test_ct_slice_with_a_rod_missing_registers(nloc):
    """Five of six rods (one rod's fill lost), with ``min_tubes=5``: the default (six) refuses a six-rod box with a
    rod missing; five fix its pose too, in a slice tilted about F's y. (Tilted about x, a rod missing leaves the
    mirrored-tilt twin to the pixels, which cannot then choose: refused as ambiguous.)"""
    sim = simulate_ct_slice(nloc, 60, 20, 0, 0, missing_tubes=("left_b",), rng=np.random.default_rng(1))
    reg = register([sim.slice], nloc, options=PRIOR, min_tubes=5)
    _check(reg, sim.truth.T_scanner_from_fiducial)
    assert reg.slices[0].n_tubes == 5


@pytest.mark.parametrize("pose", [(60, 20, 90, 0), (60, 25, 0, 0)])
def test_mr_counterpart_registers(nloc, pose):
    """The same box in MR: a magnitude slice with Rician noise (SNR 20), 2 mm slices of 0.6 mm pixels. The 512 x 512
    slice is almost all Rayleigh background: the detection level is held above its noise, not Otsu's split of it."""
    rng = np.random.default_rng(2)
    sim = simulate_slice(nloc, *pose, shape=(512, 512), pixel_spacing_mm=(0.6, 0.6), slice_thickness_mm=2.0, rng=rng)
    sl = sim.slice
    sl = type(sl)(add_rician_noise(sl.pixels, 20.0, rng), sl.pixel_spacing_mm, sl.origin_mm, sl.col_dir, sl.row_dir,
                  sl.slice_thickness_mm, sl.source)
    _check(register([sl], nloc, options=PRIOR), sim.truth.T_scanner_from_fiducial)


@pytest.mark.slow
@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("tilt, azimuth", [(15, 90), (25, 90), (15, 0), (25, 0), (20, 45)])  # within check's 26 deg limit
def test_tilted_ct_grid(nloc, tilt, azimuth, seed):
    rng = np.random.default_rng(seed)
    depth = 60 + rng.uniform(-10, 10)
    sim = simulate_ct_slice(nloc, depth, tilt, azimuth, rng.uniform(-5, 5), scene=CTScene(skull=seed % 2 == 1),
                            rng=rng)
    _check(register([sim.slice], nloc, options=PRIOR), sim.truth.T_scanner_from_fiducial)


def test_dicom_ct_round_trip_keeps_hounsfield_units(nloc, tmp_path):
    """Written as DICOM CT (RescaleIntercept -1024, signed for the -2048 padding), read back as CT in whole HU."""
    import pydicom

    from chic_register.imaging.simulate import write_simulated
    from chic_register.io.dicom import read_dicom_file

    sim = simulate_ct_slice(nloc, 60, 25, 0, 0, scene=CTScene(metal=True), rng=np.random.default_rng(3))
    path, _ = write_simulated(sim, tmp_path / "ct.dcm")
    ds = pydicom.dcmread(path)
    assert (ds.Modality, float(ds.RescaleIntercept), float(ds.RescaleSlope), ds.PixelRepresentation) == ("CT", -1024.0, 1.0, 1)
    sl = read_dicom_file(path, True)[0]
    assert sl.modality == "CT" and np.abs(sl.pixels - sim.slice.pixels).max() <= 0.5 + 1e-9
    _check(register([sl], nloc, options=PRIOR), sim.truth.T_scanner_from_fiducial)


def test_a_ct_slices_noise_is_read_on_its_hounsfield_values(nloc):
    """The top-hat's own background reads about two thirds of the noise on the rods: the covariance takes the
    noise of the Hounsfield values (simulated: 20 HU), and its chi-square is then about one."""
    rng = np.random.default_rng(4)
    sim = simulate_ct_slice(nloc, 60, 20, 90, 0, scene=CTScene(noise_hu=20.0), rng=rng)
    reg = register([sim.slice], nloc, options=PRIOR)
    noise = reg.uncertainty.noise[0]
    assert noise.model == "gaussian" and 17.0 < noise.sigma < 23.0
    assert reg.uncertainty.residual_chi2_per_dof < 4


@pytest.mark.parametrize("modality", ["MR", "CT"])
@pytest.mark.parametrize("tilt, missing", [(0, ()), (0, ("left_a",)), (15, ()), (15, ("right_b",))])
def test_the_printable_brw_frame_registers_axial_and_tilted_with_a_rod_missing(modality, tilt, missing):
    """designs/brw-nlocalizer.yaml: three plates facing three ways, no whole-frame symmetry: one axial slice
    outside the band where check finds a flipped twin (z 36.5-44 mm) fixes its pose without a prior, with one of
    its nine rods missing too. (Inside the band the solver refuses it as ambiguous.)"""
    from chic_design.families import family_named
    from chic_design.spec import load_spec
    from tests.helpers import ROOT

    brw = family_named("nlocalizer").geometry(load_spec(ROOT / "designs" / "brw-nlocalizer.yaml"))
    rng = np.random.default_rng(5)
    if modality == "MR":
        sim = simulate_slice(brw, 25, tilt, 30, 5, noise="rician", snr=20, rng=rng, missing_tubes=missing)
    else:
        sim = simulate_ct_slice(brw, 25, tilt, 30, 5, rng=rng, missing_tubes=missing)
    reg = register([sim.slice], brw)
    T, T_true = reg.T_scanner_from_fiducial, sim.truth.T_scanner_from_fiducial
    for p in ((0, 0, 0.5 * brw.body.length), (50, 50, 0), (-50, -50, brw.body.length)):  # not only the centre
        q = np.array([*p, 1.0])
        assert np.linalg.norm((T @ q - T_true @ q)[:3]) < 0.3
    assert reg.slices[0].n_tubes == 9 - len(missing)


def test_the_brw_frame_is_refused_inside_its_twin_band():
    """At mid-height (z = 40 mm) a tilt-0 slice of the BRW frame fits a flipped twin (check's ambiguous_slices)."""
    from chic_design.families import family_named
    from chic_design.spec import load_spec
    from tests.helpers import ROOT

    brw = family_named("nlocalizer").geometry(load_spec(ROOT / "designs" / "brw-nlocalizer.yaml"))
    sim = simulate_slice(brw, 40, 0, 30, 5, noise="rician", snr=20, rng=np.random.default_rng(5))
    with pytest.raises(NoLock, match="ambiguous"):
        register([sim.slice], brw)


@pytest.mark.parametrize("modality", ["MR", "CT"])
def test_the_brw_frame_without_its_posterior_diagonal_is_refused_as_ambiguous(modality):
    """Without post_d the other eight rods are mirror-symmetric (x -> -x): the pose and the mirrored twin (28 mm
    away at the frame's ends) show the same slice but for where each puts the missing rod, so the solver refuses
    rather than report either."""
    from chic_design.families import family_named
    from chic_design.spec import load_spec
    from tests.helpers import ROOT

    brw = family_named("nlocalizer").geometry(load_spec(ROOT / "designs" / "brw-nlocalizer.yaml"))
    rng = np.random.default_rng(5)
    if modality == "MR":
        sim = simulate_slice(brw, 25, 15, 30, 5, noise="rician", snr=20, rng=rng, missing_tubes=("post_d",))
    else:
        sim = simulate_ct_slice(brw, 25, 15, 30, 5, rng=rng, missing_tubes=("post_d",))
    with pytest.raises(NoLock, match="ambiguous"):
        register([sim.slice], brw)
