"""Volume files: each format's orientation (NIfTI RAS, NRRD space), round trips, DICOM series, read errors, and
native slices' geometry.
"""

from __future__ import annotations

import nibabel as nib
import nrrd
import numpy as np
import pytest

from chic_register.errors import ChicRegisterError, ImageReadError
from chic_register.io.volumes import Volume, read_volume, write_volume
from tests.helpers import OBLIQUE

LPS_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def _random_volume(direction=OBLIQUE, dtype=np.float32):
    rng = np.random.default_rng(7)
    vox = (rng.random((6, 7, 9)) * 500).astype(dtype)  # (nk, nj, ni): all sizes differ
    return Volume(vox, (0.5, 0.7, 1.3), (10.0, -20.0, 35.0), direction, "random")


def test_nifti_affine_is_ras_of_our_lps(tmp_path):
    v = _random_volume()
    path = write_volume(v, tmp_path / "v.nii.gz")
    img = nib.load(path)
    np.testing.assert_allclose(img.affine, LPS_RAS @ v.affine_lps, atol=1e-4)
    data = np.asarray(img.dataobj)  # nibabel indexes [i, j, k]
    np.testing.assert_array_equal(data, v.voxels.transpose(2, 1, 0))


def test_nifti_written_by_nibabel_reads_in_lps(tmp_path):
    """A RAS affine written by nibabel comes back as its LPS mirror, voxel (i, j, k) -> same point."""
    A_ras = np.array([[0.0, -0.8, 0.0, 40.0], [0.6, 0.0, 0.0, -12.0], [0.0, 0.0, 1.5, 7.0], [0, 0, 0, 1]])
    data = np.arange(4 * 5 * 6, dtype=np.float32).reshape(4, 5, 6)
    nib.save(nib.Nifti1Image(data, A_ras), tmp_path / "r.nii")
    v = read_volume(tmp_path / "r.nii")
    np.testing.assert_allclose(v.affine_lps, LPS_RAS @ A_ras, atol=1e-5)
    np.testing.assert_array_equal(v.voxels, data.transpose(2, 1, 0))
    p_ras = A_ras @ [1, 2, 3, 1]
    np.testing.assert_allclose(v.index_to_lps([[1, 2, 3]])[0], (LPS_RAS @ p_ras)[:3], atol=1e-5)


@pytest.mark.parametrize("space", ["right-anterior-superior", "left-posterior-superior"])
def test_nrrd_space_field_is_honoured(tmp_path, space):
    dirs = np.array([[0.0, 0.9, 0.0], [-0.4, 0.0, 0.0], [0.0, 0.0, 2.0]])  # rows: axes i, j, k
    origin = np.array([5.0, 6.0, -7.0])
    data = np.arange(3 * 4 * 5, dtype=np.int16).reshape(3, 4, 5)  # pynrrd: index [i, j, k]
    nrrd.write(str(tmp_path / "s.nrrd"), data, {"space": space, "space directions": dirs, "space origin": origin})
    v = read_volume(tmp_path / "s.nrrd")
    A = np.eye(4)
    A[:3, :3], A[:3, 3] = dirs.T, origin
    if space.startswith("right"):
        A = LPS_RAS @ A
    np.testing.assert_allclose(v.affine_lps, A, atol=1e-9)
    np.testing.assert_array_equal(v.voxels, data.transpose(2, 1, 0))


def test_nrrd_written_is_lps(tmp_path):
    v = _random_volume()
    write_volume(v, tmp_path / "v.nrrd")
    data, hdr = nrrd.read(str(tmp_path / "v.nrrd"))
    assert hdr["space"] == "left-posterior-superior"
    np.testing.assert_allclose(np.asarray(hdr["space directions"]).T, v.affine_lps[:3, :3], atol=1e-9)
    np.testing.assert_allclose(hdr["space origin"], v.origin_mm, atol=1e-9)
    np.testing.assert_array_equal(data, v.voxels.transpose(2, 1, 0))


@pytest.mark.parametrize("name", ["v.nii", "v.nii.gz", "v.nrrd", "v.mha", "series"])
def test_round_trip(tmp_path, name):
    v = _random_volume()
    w = read_volume(write_volume(v, tmp_path / name))
    np.testing.assert_allclose(w.affine_lps, v.affine_lps, atol=1e-5)
    tol = 500 / 32000 if name == "series" else 0  # DICOM: int16 with a rescale slope
    np.testing.assert_allclose(w.voxels, v.voxels, atol=tol)


def test_dicom_series_is_mr_with_its_geometry(tmp_path):
    pydicom = pytest.importorskip("pydicom")
    v = _random_volume(dtype=np.int16)
    folder = write_volume(v, tmp_path / "series")
    files = sorted(folder.glob("*.dcm"))
    assert len(files) == v.shape[0]
    ds = pydicom.dcmread(files[2])
    assert ds.Modality == "MR" and ds.SOPClassUID == "1.2.840.10008.5.1.4.1.1.4"
    np.testing.assert_allclose([float(x) for x in ds.ImagePositionPatient], v.index_to_lps([[0, 0, 2]])[0], atol=1e-6)
    np.testing.assert_allclose([float(x) for x in ds.ImageOrientationPatient], OBLIQUE[:, :2].T.ravel(), atol=1e-9)
    np.testing.assert_allclose([float(x) for x in ds.PixelSpacing], [0.7, 0.5])
    real = ds.pixel_array * float(ds.RescaleSlope) + float(ds.RescaleIntercept)
    np.testing.assert_array_equal(real, v.voxels[2])  # integers kept exactly


def test_rewriting_a_series_replaces_it(tmp_path):
    v = _random_volume()
    write_volume(v, tmp_path / "series")
    small = Volume(v.voxels[:3], v.spacing_mm, v.origin_mm, v.direction)
    write_volume(small, tmp_path / "series")
    assert len(list((tmp_path / "series").glob("*.dcm"))) == 3
    assert [p.name for p in tmp_path.iterdir()] == ["series"]


def test_read_errors_name_the_path(tmp_path):
    with pytest.raises(ImageReadError, match="nope.nii: no such file"):
        read_volume(tmp_path / "nope.nii")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ImageReadError, match="empty: folder holds no DICOM series"):
        read_volume(tmp_path / "empty")
    (tmp_path / "bad.nrrd").write_text("not a nrrd\n")
    with pytest.raises(ImageReadError, match="bad.nrrd: cannot read volume"):
        read_volume(tmp_path / "bad.nrrd")
    with pytest.raises(ImageReadError, match="notes.txt: not a volume file"):
        (tmp_path / "notes.txt").write_text("x")
        read_volume(tmp_path / "notes.txt")
    with pytest.raises(ChicRegisterError, match="v.png: volume output must end in"):
        write_volume(_random_volume(), tmp_path / "v.png")


def test_two_series_in_one_folder_is_an_error(tmp_path):
    import shutil

    write_volume(_random_volume(), tmp_path / "a")
    write_volume(_random_volume(), tmp_path / "b")
    for f in (tmp_path / "b").iterdir():
        shutil.move(str(f), tmp_path / "a" / f"b_{f.name}")
    with pytest.raises(ImageReadError, match="holds 2 DICOM series"):
        read_volume(tmp_path / "a")


def test_native_slice_geometry_matches_the_affine():
    v = _random_volume()
    sl = v.native_slice(4)
    rows, cols = np.array([0, 3, 6]), np.array([0, 8, 2])
    np.testing.assert_allclose(sl.pixel_to_scanner(rows, cols), v.index_to_lps(np.stack([cols, rows, [4] * 3], 1)))
    np.testing.assert_array_equal(sl.pixels, v.voxels[4])
    with pytest.raises(ChicRegisterError, match="slice index 6 is outside 0..5"):
        v.native_slice(6)
