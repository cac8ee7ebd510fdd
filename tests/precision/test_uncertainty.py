"""Every pose's covariance (chic_register.precision.uncertainty): calibrated against Monte Carlo (CHIC and a
Z-frame, through ``register``), the target point, ``--max-tre`` and ``--trust`` refusals, the normal quantile.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from chic_register.cli.main import main
from chic_register.precision.uncertainty import normal_quantile
from chic_register.studies.calibration import run_calibration, z001_geometry

# tilted poses: the verification refuses single slices near tilt 0 of neuro as too imprecise to trust
POSES = [(35.0, 25.0, 300.0, 20.0), (22.0, 15.0, 30.0, 10.0), (30.0, 30.0, 100.0, 40.0), (15.0, 20.0, 200.0, 5.0)]


def check(cal):
    """Mahalanobis mean 6 +- 10 % (chi-square, 6 DOF) and predicted TRE SD within 20 % of the measured, over the
    poses reported ok (the verification may refuse a few draws as too imprecise to trust)."""
    assert cal.n_no_lock <= 10 and cal.mahalanobis2.size + cal.n_no_lock == 200
    assert cal.mahalanobis_mean == pytest.approx(6.0, rel=0.10), cal.mahalanobis_mean
    assert cal.tre_ratio == pytest.approx(1.0, abs=0.20), cal.tre_ratio


@pytest.mark.slow
def test_covariance_calibrated_for_chic(neuro_geometry):
    """200 Rician SNR 20 slices of neuro over four poses, registered by ``register`` (the default mode)."""
    check(run_calibration(neuro_geometry, POSES, 50, seed=21))


@pytest.mark.slow
def test_covariance_calibrated_for_a_zframe():
    """The same for Slicer's z001 Z-frame (seven line tubes, no helix), registered by ``register`` with an
    orientation prior (the Z-frame maps onto itself under a half turn)."""
    poses = [(30.0, 0.0, 0.0, 0.0), (25.0, 10.0, 30.0, 10.0), (35.0, 20.0, 100.0, 40.0), (20.0, 15.0, 200.0, 5.0)]
    check(run_calibration(z001_geometry(), poses, 50, seed=12, prior=True))


def test_solve_json_covariance_target_and_max_tre(tmp_path, neuro_geometry_file, capsys):
    img = tmp_path / "s.dcm"
    assert main(["simulate", "--geometry", str(neuro_geometry_file), "--out", str(img), "--depth", "22", "--tilt",
                 "15", "--azimuth", "30", "--noise", "rician", "--snr", "20", "--seed", "3"]) == 0
    capsys.readouterr()
    base = ["solve", str(img), "--geometry", str(neuro_geometry_file), "--json"]
    assert main(base) == 0
    doc = json.loads(capsys.readouterr().out)
    for key in ("status", "T_scanner_from_fiducial", "slices", "timing_ms"):  # CONTRACT keys stay
        assert key in doc
    cov = doc["covariance"]
    assert cov["parameters"] == ["rx_deg", "ry_deg", "rz_deg", "tx_mm", "ty_mm", "tz_mm"]
    C = np.array(cov["matrix"])
    assert C.shape == (6, 6) and np.allclose(C, C.T) and np.all(np.linalg.eigvalsh(C) > 0)
    assert doc["noise"]["image_sigma"][0] == pytest.approx(0.05, rel=0.1)  # the simulator's 1 / SNR
    assert doc["noise"]["background_model"] == ["rayleigh"]
    assert doc["target_F_mm"] == [0.0, 0.0, 25.0]  # no tool in the geometry: the body's centre
    tre = doc["predicted_tre_mm"]
    assert 0.005 < tre < 0.2
    # a far target: rotation errors grow the TRE
    assert main(base + ["--target", "0", "0", "200"]) == 0
    far = json.loads(capsys.readouterr().out)
    assert far["target_F_mm"] == [0.0, 0.0, 200.0] and far["predicted_tre_mm"] > 2 * tre
    # --max-tre: below the prediction refuses (exit 3, reason imprecise), above it passes
    assert main(base + ["--max-tre", f"{tre / 2:.6f}"]) == 3
    refused = json.loads(capsys.readouterr().out)
    assert refused["status"] == "no_lock" and refused["reason"].startswith("imprecise")
    assert refused["code"] == "imprecise" and "T_scanner_from_fiducial" not in refused
    assert main(base + ["--max-tre", f"{tre * 2:.6f}"]) == 0
    capsys.readouterr()
    # the text summary prints the predicted TRE
    assert main(["solve", str(img), "--geometry", str(neuro_geometry_file)]) == 0
    assert f"predicted TRE {tre:.3f} mm" in capsys.readouterr().out
    for bad in (["--max-tre", "0"], ["--max-tre", "nan"], ["--target", "0", "inf", "1"]):
        assert main(base + bad) == 2, bad
        assert capsys.readouterr().err.count("\n") == 1


def test_default_target_is_the_tool_tip(needle_geometry, neuro_geometry):
    from chic_register.precision.uncertainty import target_point

    assert target_point(needle_geometry) == pytest.approx((0.0, 0.0, -50.0))  # the needle tip of the spec
    assert target_point(neuro_geometry) == (0.0, 0.0, 25.0)  # no tool: the body's centre on its axis
    assert target_point(neuro_geometry, (1, 2, 3)) == (1.0, 2.0, 3.0)


def test_trust_limits_from_the_command_line(tmp_path, neuro_geometry_file, capsys):
    """A normal single slice locks at the default limits (1 mm / 0.75 deg at 3 sigma) on the true pose, within what
    its own covariance predicts; --trust tighter than its tilt precision (~0.2 deg at 1 sigma) refuses it and says
    how to proceed."""
    img = tmp_path / "s.dcm"
    assert main(["simulate", "--geometry", str(neuro_geometry_file), "--out", str(img), "--depth", "25", "--tilt",
                 "0", "--azimuth", "30", "--twist", "10", "--noise", "rician", "--snr", "20", "--seed", "1"]) == 0
    truth = json.loads((tmp_path / "s.dcm.truth.json").read_text())["T_scanner_from_fiducial"]
    capsys.readouterr()
    base = ["solve", str(img), "--geometry", str(neuro_geometry_file), "--json"]
    assert main(base + ["--trust", "0.3", "0.3"]) == 3
    refused = json.loads(capsys.readouterr().out)
    assert "not precise enough" in refused["reason"] and "--trust MM DEG" in refused["reason"]
    assert main(base) == 0
    doc = json.loads(capsys.readouterr().out)
    T, T0 = np.array(doc["T_scanner_from_fiducial"]), np.array(truth)
    centre = np.array([0.0, 0.0, 25.0, 1.0])
    assert np.linalg.norm((T - T0) @ centre) < 3 * doc["predicted_tre_mm"] + 0.05
    for bad in (["--trust", "0", "1"], ["--trust", "1", "nan"]):
        assert main(base + bad) == 2, bad
        assert capsys.readouterr().err.count("\n") == 1


def test_normal_quantile_matches_the_standard_library():
    from statistics import NormalDist

    for p in (1e-6, 0.01, 0.2, 0.5, 0.8, 0.95, 0.99, 0.999, 1 - 1e-6):
        assert normal_quantile(p) == pytest.approx(NormalDist().inv_cdf(p), abs=1e-9)
    assert normal_quantile(0.975) == pytest.approx(1.959964, abs=1e-6)  # the textbook two-sided 95 %
    for bad in (0.0, 1.0, -0.1, float("nan")):
        with pytest.raises(ValueError):
            normal_quantile(bad)


def test_the_rician_variance_table_is_its_quadrature_and_meets_the_known_limits():
    from chic_register.precision.uncertainty import (
        RICIAN_SIGNAL,
        RICIAN_VARIANCE,
        rician_variance_by_quadrature,
        rician_variance_factor,
    )

    np.testing.assert_allclose(RICIAN_VARIANCE, rician_variance_by_quadrature(RICIAN_SIGNAL), rtol=1e-13, atol=0)
    assert RICIAN_VARIANCE[0] == pytest.approx(2 - np.pi / 2, abs=1e-5)  # Rayleigh at no signal (the quadrature: 7e-6 low)
    assert rician_variance_factor(50.0) == 1.0 and abs(RICIAN_VARIANCE[-1] - 1) < 1e-2  # Gaussian at high signal
