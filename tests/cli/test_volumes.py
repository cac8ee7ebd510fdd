"""Volumes on the command line: simulate --volume-shape, reslice, solve of a volume or of one series of several."""

from __future__ import annotations

import json

import numpy as np
import pydicom

from chic_register.cli.main import main
from chic_register.io.volumes import Volume, write_volume
from chic_register.model.pose import apply, invert


def test_cli_simulate_volume_then_reslice(tmp_path, neuro_geometry_file, capsys):
    vol = tmp_path / "vol.nrrd"
    rc = main(["simulate", "--geometry", str(neuro_geometry_file), "--depth", "25", "--tilt", "5", "--azimuth", "30",
               "--volume-shape", "112", "112", "56", "--voxel-size", "0.5", "0.5", "1", "--noise", "rician",
               "--snr", "25", "--seed", "2", "--out", str(vol)])
    assert rc == 0
    truth = json.loads((tmp_path / "vol.nrrd.truth.json").read_text())
    T = np.array(truth["T_scanner_from_fiducial"])
    # the volume centre (scanner origin) is on the fiducial axis at depth 25
    np.testing.assert_allclose(apply(invert(T), [0.0, 0.0, 0.0]), [0, 0, 25.0], atol=1e-9)
    capsys.readouterr()
    rc = main(["reslice", str(vol), "--geometry", str(neuro_geometry_file), "--reference", str(tmp_path / "vol.nrrd.truth.json"),
               "--depths", "15", "33", "--size", "112", "--json", "--save-slices", str(tmp_path / "rs")])
    stdout, err = capsys.readouterr()
    out = json.loads(stdout)  # stdout: the JSON object alone; the bar and the written files on stderr
    assert rc == 0 and out["n_slices"] == 2 and out["n_locked"] >= 1
    assert "reslice and register" in err and "2/2" in err
    for name in ("reslice_000_depth_15.00.dcm", "reslice_001_depth_33.00.dcm"):
        assert (tmp_path / "rs" / name).is_file() and f"chic-register: wrote {tmp_path / 'rs' / name}" in err
    assert out["summary"]["z_mm"]["rms"] < 0.3
    assert [s["depth_mm"] for s in out["slices"]] == [15.0, 33.0]


def test_cli_bad_volume_inputs(tmp_path, neuro_geometry_file, capsys):
    g = str(neuro_geometry_file)
    assert main(["simulate", "--geometry", g, "--depth", "25", "--volume-shape", "8", "8", "8", "--out",
                 str(tmp_path / "v.dcm")]) == 2
    assert "volume output must end in" in capsys.readouterr().err
    bad = tmp_path / "ref.json"
    bad.write_text('{"T_scanner_from_fiducial": [[1, 0], [0, 1]]}')
    write_volume(Volume(np.random.default_rng(7).random((6, 7, 9)).astype(np.float32) * 500, (0.5, 0.7, 1.3),
                        (10.0, -20.0, 35.0), np.eye(3), "random"), tmp_path / "v.nii")
    assert main(["reslice", str(tmp_path / "v.nii"), "--geometry", g, "--reference", str(bad)]) == 2
    assert "needs key 'T_scanner_from_fiducial' holding a rigid 4x4 matrix" in capsys.readouterr().err
    # without --slices every slice is tried: random voxels hold no fiducial, so no slice locks (exit 3, not 2)
    assert main(["solve", str(tmp_path / "v.nii"), "--geometry", g]) == 3
    assert "no lock: no slice of 6 locked (" in capsys.readouterr().err
    for bad_range in (["3-1"], ["x"], ["2-99"]):
        assert main(["solve", str(tmp_path / "v.nii"), "--geometry", g, "--slices", *bad_range]) == 2
        err = capsys.readouterr().err
        assert f"--slices {bad_range[0]}:" in err and err.count("\n") == 1


def test_a_folder_of_several_series_lists_them_and_solves_the_one_named(tmp_path, neuro_geometry_file, capsys):
    """A scanner export puts a localiser and the scan in one folder: the refusal lists both (number, description,
    file count, UID); --series picks one by its SeriesNumber (or UID), and it registers."""
    g = str(neuro_geometry_file)
    for name, depth in (("scan", "25"), ("other", "20")):
        assert main(["simulate", "--geometry", g, "--depth", depth, "--tilt", "5", "--azimuth", "30",
                     "--volume-shape", "96", "96", "24", "--voxel-size", "0.5", "0.5", "2", "--noise", "rician",
                     "--snr", "25", "--seed", "2", "--out", str(tmp_path / name)]) == 0
    both = tmp_path / "both"
    both.mkdir()
    for number, name in ((7, "scan"), (2, "other")):
        for k, f in enumerate(sorted((tmp_path / name).glob("*.dcm"))):
            ds = pydicom.dcmread(f)
            ds.SeriesNumber, ds.SeriesDescription = number, f"{name} series"
            ds.save_as(both / f"{name}-{k:03d}.dcm")
    capsys.readouterr()
    assert main(["solve", str(both), "--geometry", g, "--json"]) == 2
    err = capsys.readouterr().err
    assert "holds 2 DICOM series" in err and "#7 'scan series' (24 files" in err and "--series" in err
    assert main(["solve", str(both), "--geometry", g, "--series", "7", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    truth = json.loads((tmp_path / "scan.truth.json").read_text())
    tre = np.linalg.norm(np.array(out["T_scanner_from_fiducial"])[:3, 3] - np.array(truth["T_scanner_from_fiducial"])[:3, 3])
    assert out["status"] == "ok" and tre < 0.5
    assert main(["solve", str(both), "--geometry", g, "--series", "07"]) == 0  # a number as the scanner shows it
    capsys.readouterr()
    assert main(["solve", str(both), "--geometry", g, "--series", "9"]) == 2
    assert "no DICOM series '9'" in capsys.readouterr().err
    assert main(["reslice", str(tmp_path / "scan.truth.json"), "--geometry", g, "--reference",
                 str(tmp_path / "scan.truth.json"), "--series", "7"]) == 2
