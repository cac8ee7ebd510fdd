"""The image's scale fitted with the pose of several slices: recovered where the data show it, reported always."""

import dataclasses
import json
import math

import numpy as np
import pytest

from chic_register.cli.main import main
from chic_register.errors import NoLock
from chic_register.imaging.simulate import simulate_slice
from chic_register.model.geometry import write_geometry
from chic_register.model.pose import invert, rigid, slice_frame
from chic_register.pipeline.register import register
from chic_register.pipeline.scaling import calibrated_scale_sd

T_SF = rigid(slice_frame(0, 20, 30, 40)[:3, :3], (5.0, -3.0, 60.0))
POSES = [(12, 12, 0, 0), (20, 12, 0, 0), (28, 12, 0, 0), (36, 12, 0, 0)]


def _series(geom, declared_scale=(0.0, 0.0), snr=40.0):
    """Four parallel slices of the neuro fiducial at ``T_SF`` whose pixel spacing is declared ``1 + declared_scale``
    (x: columns, y: rows) times the true 0.5 mm: the image shows the fiducial that much smaller than it is."""
    shape, spacing = (256, 256), (0.5, 0.5)
    out = []
    for i, p in enumerate(POSES):
        T_image_from_S = rigid(np.eye(3), ((shape[1] - 1) / 2 * spacing[1], (shape[0] - 1) / 2 * spacing[0], 0))
        S = T_SF @ slice_frame(*p) @ invert(T_image_from_S)
        sim = simulate_slice(geom, *p, noise="rician", snr=snr, rng=i, T_scanner_from_image=S)
        sl = sim.slice
        sx, sy = declared_scale
        out.append(dataclasses.replace(sl, pixel_spacing_mm=(sl.pixel_spacing_mm[0] * (1 + sy),
                                                             sl.pixel_spacing_mm[1] * (1 + sx))))
    return out


def _errors(reg, geom, slices=None, declared_scale=(0.0, 0.0)):
    """``(mm, deg)``: the frame centre's distance from where the image shows it (the truth's centre in the
    declared image coordinates of ``slices[0]``), and the rotation's distance from the truth's."""
    centre = T_SF @ np.array([0.0, 0.0, 0.5 * geom.body.length, 1.0])
    if slices is not None:
        S = slices[0].T_scanner_from_image()
        sx, sy = declared_scale
        c = invert(S) @ centre  # in the image's true mm; the declared spacing stretches it about pixel (0, 0)
        centre = S @ np.array([c[0] * (1 + sx), c[1] * (1 + sy), c[2], 1.0])
    got = reg.T_scanner_from_fiducial @ np.array([0.0, 0.0, 0.5 * geom.body.length, 1.0])
    dR = reg.T_scanner_from_fiducial[:3, :3].T @ T_SF[:3, :3]
    return float(np.linalg.norm((got - centre)[:3])), float(np.degrees(np.arccos(np.clip((np.trace(dR) - 1) / 2,
                                                                                        -1, 1))))


def test_a_scale_the_slices_show_is_fitted_with_the_pose(neuro_geometry):
    """Declared 0.8 % too coarse along the columns (the image shows the fiducial 0.8 % larger along x): the spacing's
    correction, -0.8 %, is recovered within three of its standard deviations, the pose fitted with it is closer to the truth than the rigid
    one, and its covariance holds the scale's uncertainty."""
    slices = _series(neuro_geometry, (0.008, 0.0))
    reg = register(slices, neuro_geometry)
    assert reg.scale is not None and reg.scale.fitted and reg.scale.axes[:2] == ("x", "y")
    sx, sy = reg.scale.scale[:2]
    sdx, sdy = reg.scale.scale_sd[:2]
    assert abs(sx + 0.008) < 3 * sdx + 1e-4 and abs(sy) < 3 * sdy + 1e-4 and sdx < 0.004
    assert "image scale" in reg.uncertainty.measurement
    rigid_reg = register(slices, neuro_geometry, fit_scale=False, trust_tre_mm=5, trust_rot_deg=5)
    mm, deg = _errors(reg, neuro_geometry, slices, (0.008, 0.0))
    rigid_mm, rigid_deg = _errors(rigid_reg, neuro_geometry, slices, (0.008, 0.0))
    assert mm < 0.1 and deg < 0.1 and deg < 0.8 * rigid_deg


def test_no_scale_leaves_the_pose_rigid_and_reports_it(neuro_geometry):
    reg = register(_series(neuro_geometry), neuro_geometry)
    assert reg.scale is not None and not reg.scale.fitted
    assert np.all(np.abs(reg.scale.scale[:2]) < 3 * reg.scale.scale_sd[:2] + 1e-4)
    mm, deg = _errors(reg, neuro_geometry)
    assert mm < 0.1 and deg < 0.1


def test_a_scale_beyond_the_tolerance_is_refused_naming_it(neuro_geometry):
    slices = _series(neuro_geometry, (0.008, 0.0))
    with pytest.raises(NoLock, match=r"scale|stretched|scaled") as info:
        register(slices, neuro_geometry, max_scale_error=0.004)
    assert "spacing" in info.value.reason


def test_solve_reports_the_scale_in_json_and_text(tmp_path, neuro_geometry, capsys):
    from chic_register.io.dicom import write_dicom

    files = [write_dicom(sl, tmp_path / f"s{i}.dcm") for i, sl in enumerate(_series(neuro_geometry, (0.008, 0.0)))]
    geo = write_geometry(neuro_geometry, tmp_path / "g.yaml")
    assert main(["solve", *map(str, files), "--geometry", str(geo), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["scale"]["axes"][:2] == ["x", "y"] and doc["scale"]["fitted"] is True
    assert doc["scale"]["scale"][0] == pytest.approx(-0.008, abs=0.004)
    assert main(["solve", *map(str, files), "--geometry", str(geo)]) == 0
    assert "image scale: x -0." in capsys.readouterr().out
    assert main(["solve", *map(str, files), "--geometry", str(geo), "--max-scale-error", "0"]) == 2


def _delta_F_params(T0, T1):
    """(6,): ``T1 = T0 @ exp(delta)`` to first order, in F's parameters (deg about F's axes, mm along them)."""
    D = invert(T0) @ T1
    A = 0.5 * (D[:3, :3] - D[:3, :3].T)
    return np.array([np.degrees(A[2, 1]), np.degrees(A[0, 2]), np.degrees(A[1, 0]), *D[:3, 3]])


def test_one_slices_sensitivity_to_an_unmeasured_scale_is_the_pose_it_moves(neuro_geometry):
    """Hand-worked by finite differences: a noise-free slice's pixel spacing declared 0.3 % larger along x, then along
    y, moves the rigid pose by ``dx``, ``dy``; the registration's a-priori scale covariance for an SD of 0.3 % per axis
    is ``dx dx^T + dy dy^T`` in its rotation block (a spacing scales about pixel (0, 0), the prior about the
    fiducial's centre: their translations differ by that shift), and its reported SD per 1 % is that block's worst
    direction, scaled."""
    sim = simulate_slice(neuro_geometry, 22.0, 18.0, 40.0, 15.0, noise="none")
    wide = {"trust_rot_deg": 90.0, "trust_tre_mm": 100.0}  # 0.3 % moves this pose beyond the default limits
    base = register([sim.slice], neuro_geometry, scale_sd=0.003, **wide)
    moves = []
    for axis in (1, 0):  # the columns' spacing (x), then the rows' (y)
        spacing = list(sim.slice.pixel_spacing_mm)
        spacing[axis] *= 1.003
        reg = register([dataclasses.replace(sim.slice, pixel_spacing_mm=tuple(spacing))], neuro_geometry, scale_sd=0,
                       **wide)
        moves.append(_delta_F_params(base.T_scanner_from_fiducial, reg.T_scanner_from_fiducial))
    expected = sum(np.outer(d, d) for d in moves)
    got = base.scale.pose_covariance
    assert base.scale.prior_sd == pytest.approx(0.003) and not base.scale.fitted
    assert np.allclose(got[:3, :3], expected[:3, :3], atol=0.05 * np.abs(expected[:3, :3]).max())
    rot_per_pct = base.scale.pose_sd_per_pct[0]
    assert rot_per_pct * 0.3 == pytest.approx(np.sqrt(np.linalg.eigvalsh(expected[:3, :3]).max()), rel=0.1)
    rigid_only = register([sim.slice], neuro_geometry, scale_sd=0, **wide)
    # the a-priori scale widens the covariance by exactly its share, and the pose is the rigid one
    assert np.allclose(base.uncertainty.covariance - rigid_only.uncertainty.covariance, got, atol=1e-9)
    assert np.allclose(base.T_scanner_from_fiducial, rigid_only.T_scanner_from_fiducial)


def test_an_unmeasured_scale_beyond_the_trust_limits_is_refused_and_a_calibrated_file_brings_its_own(
        tmp_path, neuro_geometry, capsys):
    """A near-normal slice whose pose an unmeasured 0.2 % scale moves by more than the trust limits allow: ``solve``
    says so in the text and the JSON and still locks by default; ``--scale-sd 0.2`` refuses it naming the scale;
    a geometry file calibrated to 0.01 % (``chic-register calibrate``'s record) carries that SD into the registration."""
    sim = simulate_slice(neuro_geometry, 25.0, 15.0, 30.0, 10.0, noise="rician", snr=20.0, slice_thickness_mm=2.0, rng=3)
    from chic_register.io.dicom import write_dicom

    path = write_dicom(sim.slice, tmp_path / "s.dcm")
    geometry = write_geometry(neuro_geometry, tmp_path / "geometry.yaml")
    assert main(["solve", str(path), "--geometry", str(geometry), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    per_pct = out["scale"]["pose_sd_per_pct"]
    assert 3 * 0.2 * per_pct["rot_deg"] > 0.75 and "prior_sd" not in out["scale"]
    assert main(["solve", str(path), "--geometry", str(geometry)]) == 0
    assert "an unmeasured scale of 0.1 %" in capsys.readouterr().out
    assert main(["solve", str(path), "--geometry", str(geometry), "--scale-sd", "0.2"]) != 0
    err = capsys.readouterr().err
    assert "the pixel noise and the image's unmeasured scale (--scale-sd)" in err and "chic-register calibrate" in err
    assert main(["solve", str(path), "--geometry", str(geometry), "--scale-sd", "9"]) == 2
    assert "--scale-sd takes a per cent in [0, 5], got 9" in capsys.readouterr().err
    calibrated = dataclasses.replace(neuro_geometry, source={**(neuro_geometry.source or {}),
                                                             "calibration": {"factor": 1.0, "factor_sd": 0.0001}})
    reg = register([sim.slice], calibrated)
    assert reg.scale.prior_sd == pytest.approx(0.0001) and "a-priori scale" in reg.uncertainty.measurement
    # a calibration scan whose columns read 0.6 % and rows 0.2 % (their mean, 0.4 %, recorded as the factor) leaves
    # 0.2 % per axis unmeasured
    record = {"factor": 1 / 1.004, "factor_sd": 0.0001, "image_scale": {"axes": ["x", "y", "z"],
                                                                       "scale": [0.006, 0.002, 0.01]}}
    assert calibrated_scale_sd(dataclasses.replace(neuro_geometry, source={"calibration": record})) == \
        pytest.approx(math.hypot(0.0001, 0.002), rel=1e-6)
    assert calibrated_scale_sd(neuro_geometry) == 0.0
