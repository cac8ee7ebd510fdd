"""chic-register simulate: the image and its truth file, the refusals of bad flags and files."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import ndimage

from chic_register.cli.main import main
from chic_register.cli.main import main as register_main
from chic_register.imaging.simulate import simulate_slice, truth_path
from chic_register.io.images import read_slices
from chic_register.model.geometry import load_geometry, write_geometry
from chic_register.model.pose import apply
from chic_register.studies.damage import pose_error


def _one_line_error(capsys, prefix: str) -> str:
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and "\n" not in err, err
    assert err.startswith(prefix), err
    return err


def _simulate_args(geometry_file, out, *extra):
    return ["simulate", "--geometry", str(geometry_file), "--depth", "22", "--tilt", "15", "--azimuth", "60",
            "--twist", "20", "--slice-thickness", "1", "--out", str(out), *extra]


@pytest.mark.parametrize("suffix", [".dcm", ".npy", ".png", ".tif"])
def test_cli_simulate_writes_image_and_truth(neuro_geometry_file, tmp_path, capsys, suffix):
    out = tmp_path / f"slice{suffix}"
    extra = ["--noise", "rician", "--snr", "30", "--seed", "4", "--distractors", "2", "--missing", "O1"]
    if suffix == ".dcm":
        extra += ["--image-position", "-40", "-50", "10", "--image-orientation", "1", "0", "0", "0", "0", "-1"]
    assert main(_simulate_args(neuro_geometry_file, out, *extra)) == 0
    assert "wrote" in capsys.readouterr().out
    truth = json.loads(truth_path(out).read_text())
    assert truth["depth_mm"] == pytest.approx(22) and truth["tilt_deg"] == pytest.approx(15)
    assert "O1" not in truth["centres_px"] and len(truth["centres_px"]) == 8
    sl = read_slices([out], pixel_spacing=(0.5, 0.5))[0]
    assert sl.shape == (256, 256)
    T = np.array(truth["T_scanner_from_fiducial"])
    T_F_from_S = np.array(truth["T_F_from_S"])
    geom = load_geometry(neuro_geometry_file)
    for tid, (row, col) in truth["centres_px"].items():
        crossing = geom.tube(tid).intersect_plane(T_F_from_S[:3, 3], T_F_from_S[:3, 2])[0]
        assert np.allclose(sl.pixel_to_scanner(row, col)[0], apply(T, crossing), atol=1e-4)
        assert sl.pixels[round(row), round(col)] > 0.4 * sl.pixels.max()
    if suffix == ".dcm":
        assert np.allclose(sl.origin_mm, (-40, -50, 10)) and np.allclose(sl.row_dir, (0, 0, -1))
        assert sl.slice_thickness_mm == pytest.approx(1.0)
    else:
        assert truth["file"]["frame"] == "image"


@pytest.mark.parametrize("extra, fragment", [
    (["--missing", "Q9"], "Q9"),
    (["--size", "2"], "--size"),
    (["--pixel-size", "0"], "--pixel-size"),
    (["--snr", "-1"], "--snr"),
    (["--noise-level", "-0.1"], "--noise-level"),
    (["--slice-thickness", "-1"], "--slice-thickness"),
    (["--distractors", "-2"], "--distractors"),
    (["--image-position", "0", "0", "0"], "DICOM output only"),
    (["--scanner-scale", "12", "0"], "--scanner-scale takes two per cent values within +-10"),
    (["--nonlinearity", "-1"], "--nonlinearity must be 0..20 mm"),
    (["--shading", "nan"], "--shading must be 0..1"),
    (["--tissue", "-3"], "--tissue must be 0..100"),
    (["--modality", "ct", "--shading", "0.3"], "apply to MR"),
])
def test_cli_simulate_bad_options_exit_2(neuro_geometry_file, tmp_path, capsys, extra, fragment):
    out = tmp_path / ("x.npy" if "--image-position" in extra else "x.dcm")
    assert main(_simulate_args(neuro_geometry_file, out, *extra)) == 2
    err = capsys.readouterr().err.strip()
    assert fragment in err and len(err.splitlines()) == 1
    assert not out.exists()


def test_cli_simulate_bad_files_exit_2(neuro_geometry_file, tmp_path, capsys):
    assert main(_simulate_args(tmp_path / "none.yaml", tmp_path / "a.dcm")) == 2
    assert "no such geometry file" in capsys.readouterr().err
    tampered = tmp_path / "tampered.yaml"
    tampered.write_text(neuro_geometry_file.read_text().replace("12.5", "12.6", 1))
    assert main(_simulate_args(tampered, tmp_path / "a.dcm")) == 2
    assert "sha256" in capsys.readouterr().err
    assert main(_simulate_args(neuro_geometry_file, tmp_path / "a.jpg")) == 2
    assert "unsupported suffix" in capsys.readouterr().err
    assert main(_simulate_args(neuro_geometry_file, tmp_path)) == 2
    assert "directory" in capsys.readouterr().err


@pytest.mark.parametrize("extra, fragment", [
    (["--distractors", "1000000000"], "--distractors must be 0..1000"),
    (["--pixel-size", "1e-300"], "--pixel-size must be 0.01..50 mm"),
    (["--slice-thickness", "inf"], "--slice-thickness must be 0..100 mm"),
    (["--center-offset", "1e300", "0"], "--center-offset, --image-position and --image-orientation"),
    (["--volume-shape", "1024", "1024", "1024"], "is 1073741824 voxels; at most 67108864"),
    (["--volume-shape", "8", "8", "8", "--voxel-size", "1e-300"], "--voxel-size takes one or three sizes in 0.01..50"),
    (["--volume-shape", "8", "8", "8", "--tissue", "2"], "--tissue: not available in volume mode"),
])
def test_simulate_flags_that_would_allocate_or_loop_without_bound_are_refused(tmp_path, capsys, neuro_geometry_file,
                                                                            extra, fragment):
    argv = ["simulate", "--geometry", str(neuro_geometry_file), "--depth", "25", "--out", str(tmp_path / "s.npy")]
    if "--volume-shape" in extra:
        argv[-1] = str(tmp_path / "v.nii")
    assert main(argv + extra) == 2
    assert fragment in _one_line_error(capsys, "chic-register: error: ")
    assert not (tmp_path / "s.npy").exists() and not (tmp_path / "v.nii").exists()


def test_simulate_with_no_tube_in_view_is_an_error_and_writes_nothing(tmp_path, neuro_geometry_file, capsys):
    out = tmp_path / "s.npy"
    assert main(["simulate", "--geometry", str(neuro_geometry_file), "--depth", "80", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "no tube crosses the image" in err and "0..50" in err and len(err.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == [neuro_geometry_file]
    assert main(["simulate", "--geometry", str(neuro_geometry_file), "--depth", "80", "--out", str(out),
                 "--allow-empty"]) == 0  # a deliberately missed slice, with a warning
    assert out.is_file() and "warning: only 0 of 9 tubes in view" in capsys.readouterr().err


def test_simulate_warns_when_some_tubes_are_out_of_view(tmp_path, neuro_geometry_file, capsys):
    out = tmp_path / "s.npy"
    assert main(["simulate", "--geometry", str(neuro_geometry_file), "--depth", "25", "--size", "64",
                 "--center-offset", "12", "0", "--out", str(out)]) == 0
    assert "warning: only" in capsys.readouterr().err


def test_truth_file_holds_the_tool_tip_in_the_scanner_and_in_F(tmp_path, tool_geometry, capsys):
    """With a tool frame in the geometry, the truth says where the tip is: what solve's tool_tip_mm must match."""
    from chic_register.model.geometry import write_geometry
    from tests.conftest import TOOL_TIP_MM

    g = write_geometry(tool_geometry, tmp_path / "geometry.yaml")
    out = tmp_path / "s.dcm"
    assert main(["simulate", "--geometry", str(g), "--depth", "24", "--tilt", "12", "--azimuth", "40", "--twist",
                 "25", "--noise", "rician", "--snr", "30", "--seed", "7", "--image-position", "-60", "-75", "30",
                 "--out", str(out)]) == 0
    truth = json.loads(truth_path(out).read_text())
    T = np.array(truth["T_scanner_from_fiducial"])
    assert truth["tool_tip_F_mm"] == [0.0, 0.0, TOOL_TIP_MM]
    np.testing.assert_allclose(truth["T_fiducial_from_tool"], tool_geometry.tool.T_fiducial_from_tool)
    np.testing.assert_allclose(truth["tool_tip_mm"], apply(T, [0.0, 0.0, TOOL_TIP_MM]), atol=1e-9)
    np.testing.assert_allclose(truth["T_scanner_from_tool"], T @ tool_geometry.tool.T_fiducial_from_tool, atol=1e-12)
    capsys.readouterr()
    assert main(["solve", str(out), "--geometry", str(g), "--json"]) == 0
    solved = json.loads(capsys.readouterr().out)
    assert np.linalg.norm(np.array(solved["tool_tip_mm"]) - truth["tool_tip_mm"]) < 1.0  # 85 mm from the slice


def test_volume_truth_holds_the_tool_tip_and_a_geometry_without_tool_has_none(tmp_path, tool_geometry,
                                                                             neuro_geometry_file):
    from chic_register.model.geometry import write_geometry

    g = write_geometry(tool_geometry, tmp_path / "tool-geometry.yaml")
    vol = tmp_path / "v.nrrd"
    assert main(["simulate", "--geometry", str(g), "--depth", "25", "--volume-shape", "16", "16", "8",
                 "--voxel-size", "2", "--out", str(vol)]) == 0
    truth = json.loads(truth_path(vol).read_text())
    T = np.array(truth["T_scanner_from_fiducial"])
    np.testing.assert_allclose(truth["tool_tip_mm"], apply(T, truth["tool_tip_F_mm"]), atol=1e-9)
    plain = tmp_path / "plain.npy"
    assert main(["simulate", "--geometry", str(neuro_geometry_file), "--depth", "25", "--out", str(plain)]) == 0
    assert not {"tool_tip_mm", "tool_tip_F_mm"} & set(json.loads(truth_path(plain).read_text()))


def test_simulated_slice_truth_carries_the_tool_frame(tool_geometry, neuro_geometry):

    with_tool = simulate_slice(tool_geometry, 25.0, 10.0, rng=0).truth.to_dict()
    T = np.array(with_tool["T_scanner_from_fiducial"])
    np.testing.assert_allclose(with_tool["tool_tip_mm"], (T @ tool_geometry.tool.T_fiducial_from_tool)[:3, 3])
    assert "tool_tip_mm" not in simulate_slice(neuro_geometry, 25.0, 10.0, rng=0).truth.to_dict()


def test_simulate_cli_on_a_zframe_geometry_slices_and_volume(zframe_geometry, tmp_path, capsys):
    geo = write_geometry(zframe_geometry, tmp_path / "geometry.yaml")
    for tilt, bw in ((0.0, 1.0), (15.0, 2.0)):
        out = tmp_path / f"s{tilt:g}.npy"
        assert register_main(["simulate", "--geometry", str(geo), "--depth", "30", "--tilt", str(tilt),
                              "--azimuth", "40", "--size", "200", "--blob-width", str(bw), "--noise", "rician",
                              "--seed", "3", "--out", str(out)]) == 0
        truth = json.loads((tmp_path / f"s{tilt:g}.npy.truth.json").read_text())
        assert sorted(truth["centres_px"]) == sorted(zframe_geometry.ids) and truth["settings"]["blob_width"] == bw
        assert np.load(out).shape == (200, 200)
    vol = tmp_path / "v.nii.gz"
    assert register_main(["simulate", "--geometry", str(geo), "--depth", "30", "--tilt", "8", "--out", str(vol),
                          "--volume-shape", "150", "150", "9", "--voxel-size", "0.5", "0.5", "2",
                          "--blob-width", "1.5", "--noise", "none"]) == 0
    from chic_register.io.volumes import read_volume

    mid = np.asarray(read_volume(vol).voxels)[4]  # the middle k-plane: depth 30, tilt 8
    truth = json.loads((tmp_path / "v.nii.gz.truth.json").read_text())
    assert truth["settings"]["blob_width"] == 1.5
    assert ndimage.label(mid > 0.05 * mid.max())[1] == 7
    assert register_main(["simulate", "--geometry", str(geo), "--depth", "30", "--out", str(tmp_path / "x.npy"),
                          "--blob-width", "0"]) == 2
    assert "--blob-width must be 0.2..5" in capsys.readouterr().err


def test_scanner_effects_shift_the_pose_the_image_shows_and_the_solve_finds_that_pose(neuro_geometry_file, tmp_path,
                                                                                     capsys):
    """--scanner-scale, --nonlinearity, --shading, --tissue: the truth file records them and the pose the distorted
    image shows (0.3 deg from the world pose for a 0.5 % scale with 2 mm of non-linearity); the slice's solve lands
    on that pose, not on the world pose no image can show. A plain image's isocentre is its centre."""
    out = tmp_path / "distorted.dcm"
    effects = ["--scanner-scale", "0", "0.5", "--nonlinearity", "2", "--shading", "0.4"]
    assert main(["simulate", "--geometry", str(neuro_geometry_file), "--depth", "22", "--tilt", "20", "--azimuth",
                 "30", "--twist", "15", "--noise", "rician", "--snr", "30", "--seed", "3", "--out", str(out),
                 *effects]) == 0
    truth = json.loads(truth_path(out).read_text())
    assert truth["scanner_effects"] == {"scale_percent": [0.0, 0.5], "nonlinearity_mm_at_100mm": 2.0,
                                        "shading": 0.4, "tissue": 0, "isocentre_mm": [0.0, 0.0, 0.0]}
    geom = load_geometry(neuro_geometry_file)
    world, shown = np.array(truth["T_scanner_from_fiducial"]), np.array(truth["T_scanner_from_fiducial_shown"])
    assert pose_error(shown, world, geom.body.length)[1] > 0.2
    capsys.readouterr()
    assert register_main(["solve", str(out), "--geometry", str(neuro_geometry_file), "--json"]) == 0
    found = np.array(json.loads(capsys.readouterr().out)["T_scanner_from_fiducial"])
    tre, rot = pose_error(found, shown, geom.body.length)
    assert tre < 0.1 and rot < 0.15 and rot < pose_error(found, world, geom.body.length)[1], (tre, rot)
    plain = tmp_path / "distorted.npy"
    assert main(_simulate_args(neuro_geometry_file, plain, "--tissue", "2", "--seed", "1")) == 0
    iso = json.loads(truth_path(plain).read_text())["scanner_effects"]["isocentre_mm"]
    assert iso == pytest.approx([63.75, 63.75, 0.0])  # a plain image's centre: (256 - 1) / 2 pixels of 0.5 mm
    undistorted = tmp_path / "plain.npy"
    assert main(_simulate_args(neuro_geometry_file, undistorted)) == 0
    assert "scanner_effects" not in json.loads(truth_path(undistorted).read_text())
    assert (np.load(plain) - np.load(undistorted)).max() > 0.2  # tissue at 30-100 % of the fluid's signal
