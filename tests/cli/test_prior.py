"""--prior: a file, or the scanner directions the frame's axes point along (RAS, LPS, identity)."""

import json

import numpy as np
import pytest

from chic_register.cli.inputs import load_prior, orientation_rotation
from chic_register.cli.main import main
from chic_register.errors import ChicRegisterError
from tests.conftest import REAL


@pytest.mark.parametrize("code, columns", [
    ("RAS", [(-1, 0, 0), (0, -1, 0), (0, 0, 1)]),
    ("lps", [(1, 0, 0), (0, 1, 0), (0, 0, 1)]),
    ("LAI", [(1, 0, 0), (0, -1, 0), (0, 0, -1)]),
    ("SRA", [(0, 0, 1), (-1, 0, 0), (0, -1, 0)]),
])
def test_an_orientation_code_names_each_frame_axis_in_the_scanner(code, columns):
    np.testing.assert_array_equal(orientation_rotation(code), np.array(columns, float).T)
    T = load_prior(code)
    assert T.shape == (4, 4) and np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3))


def test_identity_is_lps():
    np.testing.assert_array_equal(load_prior("identity"), np.eye(4))


@pytest.mark.parametrize("code", ["RLS", "XYZ", "RA", "RASL"])
def test_what_is_not_an_orientation_code_is_read_as_a_file(code, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert orientation_rotation(code) is None
    with pytest.raises(ChicRegisterError, match=code):
        load_prior(code)


def test_a_left_handed_code_is_refused_with_what_to_give():
    with pytest.raises(ChicRegisterError, match="left-handed"):
        orientation_rotation("RPS")


def test_a_file_named_like_a_code_is_read_as_the_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    T = np.eye(4)
    T[:3, 3] = (1, 2, 3)
    (tmp_path / "RAS").write_text(json.dumps({"T_scanner_from_fiducial": T.tolist()}))
    np.testing.assert_array_equal(load_prior("RAS"), T)


def test_solve_takes_the_code(zframe_geometry_file, capsys):
    """The real masked Z-frame scan, mounted with its x, y, z along the scanner's R, A, S: a prior of RAS searches
    near that orientation, LPS (half a turn away about z) finds nothing there."""
    geo, scan = zframe_geometry_file, REAL / "zframe-masked-b.nrrd"
    rc_ras = main(["solve", str(scan), "--geometry", str(geo), "--prior", "RAS", "--slices", "6-11", "--json"])
    out_ras = json.loads(capsys.readouterr().out)
    rc_lps = main(["solve", str(scan), "--geometry", str(geo), "--prior", "LPS", "--slices", "6-11", "--json"])
    out_lps = json.loads(capsys.readouterr().out)
    assert rc_lps == 3 and out_lps["status"] == "no_lock"
    # near RAS the slices' blobs match the frame (whatever the verdict), near LPS no pose fits them at all
    assert out_ras.get("reason") != out_lps["reason"]
    if rc_ras == 0:  # its x axis along the scanner's R: the pose's first column points to -x (LPS)
        assert np.array(out_ras["T_scanner_from_fiducial"])[0][0] < -0.99
