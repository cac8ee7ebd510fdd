"""Fast start: what a one-shot solve from the command line imports (no scipy.optimize, SimpleITK, matplotlib, nor
the bound's renderer or the blurred fit for a sharp slice).
"""

from __future__ import annotations

from chic_register.imaging.simulate import simulate_slice, write_simulated
from tests.helpers import modules_after

SLOW_IMPORTS = ("scipy.optimize", "SimpleITK", "matplotlib")


def test_one_shot_dicom_solve_imports_only_what_a_slice_needs(tmp_path, neuro_geometry, neuro_geometry_file):
    sim = simulate_slice(neuro_geometry, 22.0, 20.0, 30.0, 15.0, noise="rician", snr=20, rng=3)
    dcm = tmp_path / "slice.dcm"
    write_simulated(sim, dcm)
    code = ("import sys\nfrom chic_register.cli.main import main\n"
            f"rc = main(['solve', {str(dcm)!r}, '--geometry', {str(neuro_geometry_file)!r}, '--json'])\n"
            "assert rc == 0, rc")
    mods = modules_after(code)
    assert "chic_register.pipeline.register" in mods and "pydicom" in mods  # it did solve, from the DICOM
    assert not [m for m in mods if m.split(".")[0] in ("SimpleITK", "matplotlib", "pyigtl")
                or m.startswith(("scipy.optimize", "scipy.ndimage", "scipy.special"))
                or m == "numpy.ma" or m.startswith("numpy.ma.")  # np.median / np.unique import it: ~40 ms
                or m in ("statistics", "fractions", "chic_register.io.volumes", "chic_register.pipeline.volume")]  # NormalDist: ~4 ms (uncertainty.normal_quantile instead)
    # a sharp slice needs neither the bound's renderer (pose_params holds the covariance's convention) nor the
    # blurred pixel fit (wide_blobs decides it is not needed)
    assert "chic_register.precision.crlb" not in mods and "chic_register.fit.blurred" not in mods


def test_one_shot_volume_solve_of_a_real_scan_with_anatomy_does_not_load_scipy(zframe_geometry_file):
    """The clinical scan's thighs run together into components the detector tries to split (a watershed, scipy's
    algorithm in :mod:`chic_register.detect.watershed`): scipy.ndimage's import alone would cost a third of a
    second, as much as the rest of the volume's one-shot start-up."""
    from tests.conftest import REAL

    code = ("import sys\nfrom chic_register.cli.main import main\n"
            f"rc = main(['solve', {str(REAL / 'zframe-clinical-3t.nrrd')!r}, '--geometry', "
            f"{str(zframe_geometry_file)!r}, '--prior', 'RAS', '--json'])\n"
            "assert rc == 0, rc")
    mods = modules_after(code)
    assert "chic_register.detect.watershed" in mods and "chic_register.pipeline.volume" in mods
    assert not [m for m in mods if m == "scipy" or m.startswith("scipy.")]
