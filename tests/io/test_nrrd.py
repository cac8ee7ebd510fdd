"""NRRD volumes read through pynrrd: the same volume as SimpleITK reads, and SimpleITK for every other header."""

from __future__ import annotations

import json
import subprocess
import sys

import nrrd
import numpy as np
import pytest
import SimpleITK as sitk

from chic_register.errors import ImageReadError
from chic_register.io.nrrd import read_nrrd
from chic_register.io.volumes import Volume, read_volume, volume_from_sitk, write_volume
from tests.conftest import REAL
from tests.helpers import OBLIQUE


def _as_simpleitk_reads(path) -> Volume:
    return volume_from_sitk(sitk.ReadImage(str(path)), source=str(path))


def _assert_same(a: Volume, b: Volume) -> None:
    assert a.voxels.dtype == b.voxels.dtype and a.voxels.shape == b.voxels.shape
    np.testing.assert_array_equal(a.voxels, b.voxels)
    np.testing.assert_allclose(a.spacing_mm, b.spacing_mm, rtol=1e-12)
    np.testing.assert_allclose(a.origin_mm, b.origin_mm, atol=1e-9)
    np.testing.assert_allclose(a.direction, b.direction, atol=1e-9)


@pytest.mark.parametrize("name", ["zframe-masked-b.nrrd", "zframe-clinical-3t.nrrd"])
def test_a_real_scans_nrrd_reads_as_simpleitk_reads_it(name):
    assert read_nrrd(REAL / name) is not None
    _assert_same(read_volume(REAL / name), _as_simpleitk_reads(REAL / name))


@pytest.mark.parametrize("dtype", [np.int16, np.uint8, np.float32, np.float64])
@pytest.mark.parametrize("direction", [np.eye(3), OBLIQUE, np.diag([-1.0, 1.0, -1.0])])
def test_a_written_volume_reads_as_simpleitk_reads_it(tmp_path, dtype, direction):
    rng = np.random.default_rng(3)
    v = Volume((rng.random((5, 6, 7)) * 200).astype(dtype), (0.6, 0.8, 2.5), (-30.0, 12.5, 88.0), direction, "v")
    path = write_volume(v, tmp_path / "v.nrrd")
    assert read_nrrd(path) is not None
    _assert_same(read_volume(path), _as_simpleitk_reads(path))


def test_a_big_endian_raw_nrrd_in_ras_reads_as_simpleitk_reads_it(tmp_path):
    data = np.arange(4 * 5 * 3, dtype=">i2").reshape(4, 5, 3)  # pynrrd: index [i, j, k]
    dirs = np.array([[0.0, 0.9, 0.0], [-0.4, 0.0, 0.0], [0.0, 0.0, 2.0]])
    nrrd.write(str(tmp_path / "b.nrrd"), data, {"space": "right-anterior-superior", "space directions": dirs,
                                                 "space origin": np.array([1.0, 2.0, 3.0]), "encoding": "raw",
                                                 "endian": "big"})
    fast = read_volume(tmp_path / "b.nrrd")
    assert fast.voxels.dtype.isnative
    _assert_same(fast, _as_simpleitk_reads(tmp_path / "b.nrrd"))


def test_a_detached_header_reads_as_simpleitk_reads_it(tmp_path):
    data = np.arange(3 * 4 * 5, dtype=np.float32).reshape(3, 4, 5)  # pynrrd: index [i, j, k]
    nrrd.write(str(tmp_path / "d.nhdr"), data, {"space": "left-posterior-superior", "space directions": np.diag(
        [0.7, 0.7, 2.4]), "space origin": np.array([-90.0, -90.0, 10.0]), "encoding": "gzip"}, detached_header=True)
    assert read_nrrd(tmp_path / "d.nhdr") is not None
    _assert_same(read_volume(tmp_path / "d.nhdr"), _as_simpleitk_reads(tmp_path / "d.nhdr"))


def test_other_headers_are_left_to_simpleitk(tmp_path):
    data = np.zeros((4, 5, 3), np.float32)
    skew = np.array([[1.0, 0.0, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, 2.0]])  # not orthogonal
    nrrd.write(str(tmp_path / "skew.nrrd"), data, {"space": "left-posterior-superior", "space directions": skew})
    nrrd.write(str(tmp_path / "plain.nrrd"), data)  # no space at all
    nrrd.write(str(tmp_path / "4d.nrrd"), np.zeros((4, 5, 3, 2), np.float32),
               {"space": "left-posterior-superior", "kinds": ["domain", "domain", "domain", "list"]})
    for name in ("skew.nrrd", "plain.nrrd", "4d.nrrd"):
        assert read_nrrd(tmp_path / name) is None
    (tmp_path / "bad.nrrd").write_text("NRRD0004\ntype: float\ndimension: 3\nsizes: 2 2\n\n")
    assert read_nrrd(tmp_path / "bad.nrrd") is None
    with pytest.raises(ImageReadError, match="bad.nrrd: cannot read volume"):
        read_volume(tmp_path / "bad.nrrd")


def test_a_volume_solve_of_an_nrrd_file_does_not_load_simpleitk(tmp_path):
    """SimpleITK's import costs a quarter of a second of a one-shot solve; reading a plain NRRD file needs none of it."""
    code = ("import json, sys\nfrom chic_register.io.volumes import read_volume\n"
            f"v = read_volume({str(REAL / 'zframe-masked-b.nrrd')!r})\n"
            "print(json.dumps({'shape': list(v.shape), 'sitk': 'SimpleITK' in sys.modules}))")
    out = json.loads(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                                    timeout=120).stdout)
    assert out == {"shape": [20, 256, 256], "sitk": False}
