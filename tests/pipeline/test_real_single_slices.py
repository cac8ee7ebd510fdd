"""Single slices of a real scan: an ``ok`` lies within its own uncertainty of the volume's pose."""

import numpy as np
import pytest

from chic_register.cli.inputs import load_prior
from chic_register.errors import NoLock
from chic_register.io.volumes import read_volume
from chic_register.pipeline.volume import register_volume
from chic_register.studies.scale_calibration import calibrated_geometry
from chic_register.verify.pixels import SliceCheck, section_model_error_mm
from tests.conftest import REAL
from tests.helpers import ZF_CENTRE, pose_difference, tre_mm


def test_the_sections_model_error_is_their_scatter_beyond_their_noise():
    m = 0.2
    se = np.full(9, 0.01)
    d = np.sqrt(2.0 * np.log(2.0) * (se ** 2 + m ** 2))  # every offset at the median of its chi-square (2 dof)
    checks = [SliceCheck((), (), (1.0, 1.0), "ok", offsets_mm=tuple(zip(d[i:i + 3], se[i:i + 3]))) for i in (0, 3, 6)]
    assert section_model_error_mm(checks) == pytest.approx(m, rel=1e-6)
    quiet = [SliceCheck((), (), (1.0, 1.0), "ok", offsets_mm=((0.005, 0.01),) * 5)]
    assert section_model_error_mm(quiet) == 0.0  # offsets the noise explains
    assert section_model_error_mm([SliceCheck((), (), (1.0, 1.0), "ok", offsets_mm=((1.0, 0.01),) * 2)]) == 0.0


@pytest.mark.slow
@pytest.mark.parametrize("scan, ks, calibrated", [("zframe-masked-b.nrrd", range(5, 12), False),
                                                  ("zframe-masked-b.nrrd", range(5, 12), True),
                                                  ("zframe-clinical-3t.nrrd", range(3, 8), False)])
def test_a_real_slice_alone_is_refused_or_within_three_sigma_of_the_volumes_pose(zframe_geometry, scan, ks,
                                                                                calibrated):
    """The real scans' slices one at a time, each fitted through the blurred model (its blobs are wide). Their
    sections lie 0.1-0.7 mm from where any rigid pose of the geometry puts them (their offsets are 10-25 times
    their pixel noise), and the masked scan's pixels are 0.6 % longer along x than its spacing says; alone, a
    slice was pulled 0.8-1.7 deg from the volume's pose, even with the geometry calibrated on the same scan. The
    sections' model error and the stretch the pixels show are part of the pose's uncertainty: each slice is
    refused as not precise enough, or ``ok`` within 3 sigma of the volume's pose."""
    vol = read_volume(REAL / scan)
    geom = zframe_geometry
    if calibrated:
        whole = register_volume(vol, geom, prior=load_prior("RAS"))
        geom = calibrated_geometry(geom, whole, [scan])
    whole = register_volume(vol, geom, prior=load_prior("RAS")).T_scanner_from_fiducial
    reasons = []
    for k in ks:
        try:
            reg = register_volume(vol, geom, indices=[k], prior=load_prior("RAS"))
        except NoLock as exc:
            reasons.append(exc.reason)
            continue
        rot_sd = float(np.sqrt(np.diag(reg.uncertainty.covariance)[:3]).max())
        T = reg.T_scanner_from_fiducial
        assert pose_difference(T, whole)[1] < 3 * rot_sd, k
        assert tre_mm(T, whole, ZF_CENTRE) < 3 * reg.uncertainty.predicted_tre_mm, k
    assert sum("not precise enough" in r for r in reasons) >= 2, reasons
    if calibrated:  # the stretch is gone; the sections' model error is what refuses some of them, and the reason says so
        assert any("its sections lie" in r for r in reasons), reasons
