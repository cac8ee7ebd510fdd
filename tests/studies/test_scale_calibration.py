"""Calibrating a geometry file to a printed fiducial from a series of it, then single slices with it."""

import numpy as np
import pytest

from chic_register.cli.main import main
from chic_register.errors import NoLock
from chic_register.imaging.simulate import simulate_slice
from chic_register.io.dicom import write_dicom
from chic_register.model.geometry import load_geometry, scaled_geometry, write_geometry
from chic_register.model.pose import invert, rigid, slice_frame
from chic_register.pipeline.register import register
from chic_register.studies.damage import pose_error
from chic_register.studies.scale_calibration import calibrated_geometry, calibration_factor

PRINT = 1.006  # the print came out 0.6 % larger than its geometry file
T_SF = rigid(slice_frame(0, 20, 30, 40)[:3, :3], (5.0, -3.0, 60.0))
POSES = [(12, 12, 0, 0), (20, 12, 0, 0), (28, 12, 0, 0), (36, 12, 0, 0)]


def _slices(geom, poses, seed=0):
    shape, spacing = (256, 256), (0.5, 0.5)
    T_image_from_S = rigid(np.eye(3), ((shape[1] - 1) / 2 * spacing[1], (shape[0] - 1) / 2 * spacing[0], 0))
    return [simulate_slice(geom, *p, noise="rician", snr=40, rng=seed + i,
                           T_scanner_from_image=T_SF @ slice_frame(*p) @ invert(T_image_from_S)) for i, p in
            enumerate(poses)]


def test_scaled_geometry_scales_every_length_and_keeps_the_helix_turn(neuro_geometry):
    g = scaled_geometry(neuro_geometry, 1.01, {"why": "test"})
    assert g.body.length == pytest.approx(50.5) and g.source["calibration"] == {"why": "test"}
    h0, h1 = neuro_geometry.tube("H0"), g.tube("H0")
    assert h1.radius == pytest.approx(1.01 * h0.radius) and h1.diameter == pytest.approx(1.01 * h0.diameter)
    turn = lambda h: h.pitch_deg_per_mm * (h.z1 - h.z0)  # noqa: E731
    assert turn(h1) == pytest.approx(turn(h0))
    with pytest.raises(ValueError, match="0.5, 2"):
        scaled_geometry(neuro_geometry, 3.0, {})


def test_a_series_measures_the_print_and_calibrated_single_slices_need_no_scale(neuro_geometry):
    printed = scaled_geometry(neuro_geometry, PRINT, {})
    reg = register([s.slice for s in _slices(printed, POSES)], neuro_geometry)
    factor, sd = calibration_factor(reg)
    assert abs(factor - PRINT) < 3 * sd + 2e-4 and sd < 0.002
    calibrated = calibrated_geometry(neuro_geometry, reg, ["series"])
    assert calibrated.source["calibration"]["factor"] == pytest.approx(factor, abs=1e-6)
    # a single tilted slice of the print: with the calibrated file its pose is closer to the truth
    sim = _slices(printed, [(25, 35, 60, 10)], seed=9)[0]
    truth = sim.truth.T_scanner_from_fiducial
    nominal = register([sim.slice], neuro_geometry, trust_tre_mm=5, trust_rot_deg=5)
    better = register([sim.slice], calibrated)
    L = neuro_geometry.body.length
    assert pose_error(better.T_scanner_from_fiducial, truth, L)[0] < pose_error(nominal.T_scanner_from_fiducial,
                                                                                  truth, L)[0]


def test_one_slice_cannot_calibrate(neuro_geometry):
    reg = register([_slices(neuro_geometry, POSES[:1])[0].slice], neuro_geometry)
    with pytest.raises(NoLock, match="several slices"):
        calibration_factor(reg)


def test_calibrate_writes_a_geometry_file_that_records_its_calibration(tmp_path, neuro_geometry, capsys):
    printed = scaled_geometry(neuro_geometry, PRINT, {})
    files = [write_dicom(s.slice, tmp_path / f"s{i}.dcm") for i, s in enumerate(_slices(printed, POSES))]
    geo = write_geometry(neuro_geometry, tmp_path / "g.yaml")
    out = tmp_path / "calibrated.yaml"
    assert main(["calibrate", *map(str, files), "--geometry", str(geo), "--out", str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    g = load_geometry(out)  # its hash holds: the calibration is part of the content
    assert g.source["calibration"]["factor"] == pytest.approx(PRINT, abs=0.003)
    assert g.source["calibration"]["slices_used"] == 4
    assert main(["calibrate", str(files[0]), "--geometry", str(geo), "--out", str(tmp_path / "x.yaml")]) == 3
    assert not (tmp_path / "x.yaml").exists()
