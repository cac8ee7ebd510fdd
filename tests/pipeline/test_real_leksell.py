"""Real axial slices of a Leksell G localizer box (CT and MR, tests/data/real/leksell): registered through the
command line, or refused with the reason the physics gives.

One axial slice of two lateral N-plates fixes the turn about the left-right axis (F's x) only to second
order: the six dots fit a pose, with residuals at the level of the blob-centre noise, but the pose's
rotation about x is known to degrees, and the solver refuses it as imprecise, naming that axis. With the
trust limits opened the same fits are reported, and they must be fits: six rods, sub-pixel residuals,
and a slice plane inside the box.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from chic_design.families import family_named
from chic_design.spec import load_spec
from chic_register.cli.main import main
from chic_register.model.geometry import write_geometry
from tests.helpers import ROOT

REAL = ROOT / "tests" / "data" / "real" / "leksell"
SLICES = {  # file, the box its geometry describes, its pixel spacing (mm)
    "ct": ("test_ct_axial_slice.nii.gz", "leksell-g-ct", 0.625),
    "t1_15T": ("test_t1_15T_axial_slice.nii.gz", "leksell-g-mr", 1.143),
    "t2_15T": ("test_t2_15T_axial_slice.nii.gz", "leksell-g-mr", 1.094),
    "t2_30T": ("test_t2_30T_axial_slice.nii.gz", "leksell-g-mr", 1.094),
}


@pytest.fixture(scope="module")
def boxes(tmp_path_factory):
    out = tmp_path_factory.mktemp("leksell")
    fam = family_named("nlocalizer")
    return {name: write_geometry(fam.geometry(load_spec(ROOT / "designs" / f"{name}.yaml")), out / f"{name}.yaml")
            for name in ("leksell-g-ct", "leksell-g-mr")}


def _solve(capsys, image, geometry, *extra):
    rc = main(["solve", str(image), "--geometry", str(geometry), "--prior", "LPS", *extra])
    return rc, capsys.readouterr()


@pytest.mark.parametrize("which", sorted(SLICES))
def test_one_axial_slice_is_refused_as_imprecise_about_the_left_right_axis(capsys, boxes, which):
    name, box, _ = SLICES[which]
    rc, out = _solve(capsys, REAL / name, boxes[box])
    assert rc == 3
    assert "not precise enough to trust" in out.err and "about F's x axis" in out.err, out.err


@pytest.mark.parametrize("which", sorted(SLICES))
def test_with_open_trust_limits_the_six_rods_fit_within_the_blob_noise(capsys, boxes, which):
    name, box, px = SLICES[which]
    rc, out = _solve(capsys, REAL / name, boxes[box], "--trust", "20", "90", "--json")
    assert rc == 0, out.err
    doc = json.loads(out.out)
    s = doc["slices"][0]
    assert s["n_tubes"] == 6 and set(s["residuals_mm"]) == {f"{p}_{r}" for p in ("left", "right") for r in "adb"}
    assert s["residual_rms_mm"] < 0.5 * px  # within the solver's own limit: a few tenths of a pixel
    noise = doc["noise"]
    if which != "ct":  # MR: the residuals are those the pixel noise predicts (chi-square per degree of freedom ~1)
        assert noise["residual_chi2_per_dof"] < 3 and noise["inflation"] == 1.0
    else:  # CT: the rods' 2700 HU against 15 HU of noise put the noise's share far below the residuals' 0.2 mm,
        # which are the model's (section shape, plate): the covariance is widened by their chi-square
        assert noise["inflation"] == pytest.approx(noise["residual_chi2_per_dof"]) and noise["inflation"] > 1
    # the plane lies inside the box: Leksell Z of the slice's centre between the box's ends (40..160 mm)
    T = np.array(doc["frame_coordinates"]["T_frame_from_scanner"])
    centre_scanner = np.array(doc["T_scanner_from_fiducial"])[:3, :3] @ [0, 0, s["depth_mm"]] \
        + np.array(doc["T_scanner_from_fiducial"])[:3, 3]
    z = (T[:3, :3] @ centre_scanner + T[:3, 3])[2]
    assert 40 < z < 160


def test_the_3t_t1_slice_shows_five_rods_above_its_noise(capsys, boxes):
    """Its sixth rod (pixel (55, 191)) is three times dimmer than the brightest: the detector finds five."""
    rc, out = _solve(capsys, REAL / "test_t1_30T_axial_slice.nii.gz", boxes["leksell-g-mr"])
    assert rc == 3 and "found 5 candidate tube cross-sections" in out.err
