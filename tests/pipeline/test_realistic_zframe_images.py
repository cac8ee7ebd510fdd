"""What real scanner images of a Z-frame do that the plain simulator does not, each a seeded round trip.

Found by ``benchmarks/stress_zframe_volume.py``: rods of unequal fluid signal,
blobs of any width between the verification's blur grid values, pixels that
are not square, DICOM series with gaps between slices, and a self-symmetric
frame solved without a prior (the message must say what to give).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from chic_register.cli.main import main
from chic_register.errors import NoLock
from chic_register.imaging.simulate import add_rician_noise, simulate_slice, simulate_volume
from chic_register.io.volumes import Volume, read_volume, write_volume
from chic_register.model.geometry import load_geometry, write_geometry
from chic_register.model.pose import rigid
from chic_register.model.slices import Slice
from chic_register.pipeline.register import register
from tests.conftest import ZFRAME

CENTRE = np.array([0.0, 0.0, 30.0, 1.0])


@pytest.fixture(scope="module")
def zf(tmp_path_factory):
    from chic_design.families import family_of
    from chic_design.spec import load_spec


    spec = load_spec(ZFRAME)
    path = write_geometry(family_of(spec).geometry(spec), tmp_path_factory.mktemp("zf") / "g.yaml")
    return load_geometry(path)


def _tre(T, T_true) -> float:
    return float(np.linalg.norm((T @ CENTRE)[:3] - (T_true @ CENTRE)[:3]))


def _rot_deg(T, T_true) -> float:
    return float(np.degrees(Rotation.from_matrix(T[:3, :3].T @ T_true[:3, :3]).magnitude()))


def _slice(geom, angles, *, gains=None, blob_width=2.0, spacing=(0.5, 0.5), thickness=2.0, snr=20.0, seed=0):
    """A Z-frame slice whose rods each have their own fluid level (``gains``, one per tube), Rician noise."""
    gains = np.ones(len(geom.tubes)) if gains is None else np.asarray(gains, float)
    common = dict(shape=(200, 200), pixel_spacing_mm=spacing, slice_thickness_mm=thickness, blob_width=blob_width,
                  supersample=2, thickness_samples=3)
    image, sim = None, None
    for k, t in enumerate(geom.tubes):
        sim = simulate_slice(geom, *angles, missing_tubes=[u.id for u in geom.tubes if u.id != t.id], **common)
        img = gains[k] * sim.slice.pixels
        image = img if image is None else np.maximum(image, img)
    pixels = 800.0 * add_rician_noise(image, snr, np.random.default_rng(seed))
    s = sim.slice
    return Slice(pixels, s.pixel_spacing_mm, s.origin_mm, s.col_dir, s.row_dir, s.slice_thickness_mm), \
        sim.truth.T_scanner_from_fiducial


def _prior(T_true, deg=20.0):
    T = T_true.copy()
    T[:3, :3] = Rotation.from_rotvec(np.radians(deg) * np.array([0.6, 0.0, 0.8])).as_matrix() @ T_true[:3, :3]
    return T


@pytest.mark.parametrize("angles, gains", [
    ((30.0, 22.0, 20.0, 10.0), [0.6, 1.4, 0.6, 1.4, 0.6, 1.4, 0.6]),
    ((40.0, 15.0, 250.0, 30.0), [0.87, 0.65, 1.16, 1.37, 0.74, 1.12, 1.33]),
])
def test_rods_of_unequal_fluid_signal_register(zf, angles, gains):
    """Tilted slices whose rods range 0.6-1.4x in signal, neighbours close: each rod is judged at its own level
    (before: a bright diagonal's section 'did not have the shape' the pose predicts)."""
    sl, T_true = _slice(zf, angles, gains=gains, blob_width=1.85, spacing=(0.77, 0.77), thickness=2.3, snr=14, seed=3)
    reg = register([sl], zf, prior=_prior(T_true))
    assert _tre(reg.T_scanner_from_fiducial, T_true) < 0.3 and _rot_deg(reg.T_scanner_from_fiducial, T_true) < 0.5


@pytest.mark.parametrize("blob_width, spacing", [(2.2, (0.8, 0.8)), (2.0, (1.1, 0.6))])
def test_blobs_between_the_blur_grid_and_non_square_pixels_register(zf, blob_width, spacing):
    """Blobs 2.2x the rods (between the verification's blur grid values) and pixels 1.1 x 0.6 mm (a blur round
    in mm is not round in pixels): the fitted point spread is refined and anisotropic in pixels."""
    sl, T_true = _slice(zf, (31.0, 5.0, 40.0, 30.0), blob_width=blob_width, spacing=spacing, thickness=2.7,
                        snr=18, seed=8)
    reg = register([sl], zf, prior=_prior(T_true))
    assert _tre(reg.T_scanner_from_fiducial, T_true) < 0.3 and _rot_deg(reg.T_scanner_from_fiducial, T_true) < 0.5


def test_dicom_series_with_gaps_keeps_its_slice_thickness(tmp_path):
    vol = Volume(np.zeros((3, 4, 5), np.float32), (0.8, 0.8, 4.5), np.zeros(3), np.eye(3), "v", slice_thickness_mm=2.7)
    back = read_volume(write_volume(vol, tmp_path / "series"))
    assert back.spacing_mm[2] == pytest.approx(4.5) and back.thickness_mm == pytest.approx(2.7)
    assert back.native_slice(1).slice_thickness_mm == pytest.approx(2.7)
    nrrd = read_volume(write_volume(vol, tmp_path / "v.nrrd"))  # NRRD/NIfTI do not say: the spacing serves
    assert nrrd.thickness_mm == pytest.approx(4.5)


def test_no_prior_on_the_symmetric_frame_says_what_to_give_at_once(zf, tmp_path, capsys):
    T = rigid(Rotation.from_euler("xyz", [8, -6, 12], degrees=True).as_matrix(), (1.0, -2.0, -30.0))
    sim = simulate_volume(zf, T, shape_vox=(150, 150, 12), spacing_mm=(0.8, 0.8, 4.0), snr=20, rng=1, blob_width=1.5)
    geo = write_geometry(zf, tmp_path / "g.yaml")
    vol = write_volume(sim.volume, tmp_path / "v.nrrd")
    assert main(["solve", str(vol), "--geometry", str(geo), "--json"]) == 3
    reason = json.loads(capsys.readouterr().out)["reason"]
    assert reason.startswith("ambiguous fit") and "half turn about the y axis" in reason
    assert "--prior RAS" in reason and "--prior identity" in reason and "T_scanner_from_fiducial" in reason
    assert ".tfm" in reason
    with pytest.raises(NoLock, match="--prior"):
        register([sim.volume.native_slice(5)], zf)
    # the frame's axes lie near the scanner's (within 15 deg): '--prior identity' is all it takes
    assert main(["solve", str(vol), "--geometry", str(geo), "--prior", "identity", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert _tre(np.array(out["T_scanner_from_fiducial"]), T) < 0.3
    # a frame upside down (its half turn about x) is not near identity: refused, never its twin
    T_flip = T @ rigid(Rotation.from_euler("x", 180, degrees=True).as_matrix(), (0, 0, 60.0))
    sim2 = simulate_volume(zf, T_flip, shape_vox=(150, 150, 12), spacing_mm=(0.8, 0.8, 4.0), snr=20, rng=1,
                           blob_width=1.5)
    vol2 = write_volume(sim2.volume, tmp_path / "v2.nrrd")
    assert main(["solve", str(vol2), "--geometry", str(geo), "--prior", "identity", "--json"]) == 3
    capsys.readouterr()


def test_a_series_given_file_by_file_points_to_its_folder(zf, tmp_path, capsys):
    """`solve series/*.dcm` makes every file a slice that must lock: an empty end slice refuses them all, and the
    message says to give the folder (a volume: slices without the frame are skipped)."""
    rng = np.random.default_rng(0)
    vol = Volume(rng.rayleigh(20.0, (4, 32, 32)).astype(np.float32), (1.0, 1.0, 3.0), np.zeros(3), np.eye(3), "v")
    folder = write_volume(vol, tmp_path / "series")
    geo = write_geometry(zf, tmp_path / "g.yaml")
    files = sorted(str(p) for p in folder.iterdir())
    assert main(["solve", *files, "--geometry", str(geo), "--prior", "identity", "--json"]) == 3
    reason = json.loads(capsys.readouterr().out)["reason"]
    assert f"give the series' folder as one volume: chic-register solve {folder}" in reason
    assert main(["solve", str(folder), "--geometry", str(geo), "--prior", "identity", "--json"]) == 3
    assert "folder" not in json.loads(capsys.readouterr().out)["reason"]
