"""ITK transform files: SimpleITK reads back the registration, in the documented direction."""

from __future__ import annotations

import numpy as np
import pytest
import SimpleITK as sitk

from chic_register.errors import ChicRegisterError
from chic_register.io.transforms import read_tfm, sitk_to_matrix, write_tfm
from chic_register.model.pose import apply, invert, rigid, rot_y, rot_z


def _pose():
    return rigid(rot_z(-20.0) @ rot_y(35.0) @ rot_z(70.0), (-3.0, 55.5, 120.0))


@pytest.mark.parametrize("suffix", [".tfm", ".txt", ".h5"])
def test_round_trip_through_simpleitk(tmp_path, suffix):
    T = _pose()
    path = write_tfm(T, tmp_path / f"reg{suffix}")
    tx = sitk.ReadTransform(str(path))
    # The file holds T_fiducial_from_scanner (ITK resampling convention: fixed = scanner, moving = F).
    np.testing.assert_allclose(sitk_to_matrix(tx), invert(T), atol=1e-9)
    np.testing.assert_allclose(sitk_to_matrix(tx.GetInverse()), T, atol=1e-9)
    np.testing.assert_allclose(read_tfm(path), T, atol=1e-9)


def test_file_maps_scanner_points_to_fiducial_points(tmp_path):
    T = _pose()
    tx = sitk.ReadTransform(str(write_tfm(T, tmp_path / "reg.tfm")))
    p_F = np.array([12.5, 0.0, 25.0])  # on the centreline of D0 at mid-depth
    p_scanner = apply(T, p_F)
    np.testing.assert_allclose(tx.TransformPoint(tuple(p_scanner)), p_F, atol=1e-9)


def test_text_file_is_an_affine_transform(tmp_path):
    text = write_tfm(_pose(), tmp_path / "reg.tfm").read_text()
    assert text.startswith("#Insight Transform File V1.0")
    assert "AffineTransform_double_3_3" in text


def test_rejects_bad_suffix_and_non_rigid(tmp_path):
    with pytest.raises(ChicRegisterError, match=r"reg\.json: transform file must end in"):
        write_tfm(_pose(), tmp_path / "reg.json")
    with pytest.raises(ValueError):
        write_tfm(np.diag([2.0, 1.0, 1.0, 1.0]), tmp_path / "reg.tfm")
    assert list(tmp_path.iterdir()) == []


def test_read_rejects_non_transform(tmp_path):
    bad = tmp_path / "bad.tfm"
    bad.write_text("hello\n")
    with pytest.raises(ChicRegisterError, match="bad.tfm: not an ITK transform file"):
        read_tfm(bad)


def test_tfm_of_a_registration_reads_back_equal(tmp_path, neuro_geometry):
    from chic_register.imaging.simulate import simulate_slice
    from chic_register.pipeline.register import register

    sim = simulate_slice(neuro_geometry, 22.0, 12.0, 40.0, -15.0, noise="rician", snr=25.0, rng=5,
                         image_position=(-70.0, -50.0, 30.0))
    reg = register([sim.slice], neuro_geometry)
    tx = sitk.ReadTransform(str(write_tfm(reg.T_scanner_from_fiducial, tmp_path / "reg.tfm")))
    np.testing.assert_allclose(sitk_to_matrix(tx.GetInverse()), reg.T_scanner_from_fiducial, atol=1e-9)
    # and it is the fiducial's pose: the file maps the scanner position of the F origin back to 0
    np.testing.assert_allclose(tx.TransformPoint(tuple(reg.T_scanner_from_fiducial[:3, 3])), [0, 0, 0], atol=1e-9)


def test_cli_solve_writes_tfm_equal_to_its_json(tmp_path, neuro_geometry, neuro_geometry_file, capsys):
    import json

    from chic_register.cli.main import main
    from chic_register.imaging.simulate import simulate_slice, write_simulated

    sim = simulate_slice(neuro_geometry, 30.0, 8.0, -20.0, 60.0, noise="rician", snr=25.0, rng=2,
                         image_position=(-64.0, -64.0, 12.0))
    img, _ = write_simulated(sim, tmp_path / "s.dcm")
    tfm = tmp_path / "out" / "reg.tfm"
    tfm.parent.mkdir()  # outputs never create folders
    rc = main(["solve", str(img), "--geometry", str(neuro_geometry_file), "--json", "--tfm", str(tfm)])
    assert rc == 0
    T_json = np.array(json.loads(capsys.readouterr().out)["T_scanner_from_fiducial"])
    tx = sitk.ReadTransform(str(tfm))
    np.testing.assert_allclose(sitk_to_matrix(tx.GetInverse()), T_json, atol=1e-9)
    assert main(["solve", str(img), "--geometry", str(neuro_geometry_file), "--tfm", str(tmp_path / "r.mat")]) == 2
    assert "--tfm" in capsys.readouterr().err and not (tmp_path / "r.mat").exists()
