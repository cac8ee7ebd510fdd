"""chic-register solve: the JSON and the human summary, bad input (exit 2), no lock (exit 3), failing outputs (exit 4)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from chic_register.cli.main import main
from chic_register.imaging.simulate import simulate_slice, write_simulated
from chic_register.model.geometry import write_geometry

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def dicom_slice(tmp_path_factory, neuro_geometry):
    sim = simulate_slice(neuro_geometry, 25.0, 10.0, 30.0, 20.0, noise="rician", snr=25.0, rng=1)
    path, _ = write_simulated(sim, tmp_path_factory.mktemp("dcm") / "ok.dcm")
    return path, sim.truth.T_scanner_from_fiducial


def _simulate_cli(tmp_path, geom_file, name="s.dcm", *extra):
    out = tmp_path / name
    assert main(["simulate", "--geometry", str(geom_file), "--out", str(out), *extra]) == 0
    return out


def test_cli_solve_json_matches_the_truth(tmp_path, neuro_geometry_file, capsys):
    img = _simulate_cli(tmp_path, neuro_geometry_file, "s.dcm", "--depth", "22", "--tilt", "25", "--azimuth",
                        "60", "--twist", "15", "--noise", "uniform", "--seed", "4")
    capsys.readouterr()
    overlay = tmp_path / "o.png"
    assert main(["solve", str(img), "--geometry", str(neuro_geometry_file), "--json", "--overlay", str(overlay)]) == 0
    doc = json.loads(capsys.readouterr().out)
    truth = json.loads((tmp_path / "s.dcm.truth.json").read_text())
    assert doc["status"] == "ok" and set(doc["timing_ms"]) >= {"total"}
    s = doc["slices"][0]
    for key in ("source", "depth_mm", "tilt_deg", "azimuth_deg", "twist_deg", "residual_rms_mm"):
        assert key in s
    assert s["depth_mm"] == pytest.approx(22, abs=0.1) and s["tilt_deg"] == pytest.approx(25, abs=0.3)
    T = np.array(doc["T_scanner_from_fiducial"])
    assert np.abs(T - np.array(truth["T_scanner_from_fiducial"]))[:3].max() < 0.2
    assert overlay.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # the human summary
    assert main(["solve", str(img), "--geometry", str(neuro_geometry_file)]) == 0
    assert "status: ok" in capsys.readouterr().out


def test_cli_bad_inputs_exit_2(tmp_path, neuro_geometry, neuro_geometry_file, capsys):
    g = str(neuro_geometry_file)
    img = _simulate_cli(tmp_path, neuro_geometry_file, "s.dcm", "--depth", "20")
    capsys.readouterr()
    cases = {}
    cases["missing file"] = ["solve", str(tmp_path / "nope.dcm"), "--geometry", g]
    text = tmp_path / "notes.png"
    text.write_text("this is not an image\n")
    cases["not an image"] = ["solve", str(text), "--geometry", g, "--pixel-spacing", "0.5", "0.5"]
    trunc = tmp_path / "trunc.dcm"
    trunc.write_bytes(img.read_bytes()[: len(img.read_bytes()) // 2])
    cases["truncated DICOM"] = ["solve", str(trunc), "--geometry", g]
    tampered = tmp_path / "tampered.yaml"
    tampered.write_text(neuro_geometry_file.read_text().replace("pitch_deg_per_mm: 1.4", "pitch_deg_per_mm: 1.5", 1))
    cases["tampered geometry"] = ["solve", str(img), "--geometry", str(tampered)]
    cases["missing geometry"] = ["solve", str(img), "--geometry", str(tmp_path / "none.yaml")]
    for name, argv in cases.items():
        rc = main(argv)
        err = capsys.readouterr()
        assert rc == 2, name
        assert err.err.count("\n") == 1 and "error" in err.err, name
        assert '"ok"' not in err.out, name


def test_cli_no_lock_exit_3_with_json_reason(tmp_path, neuro_geometry_file, needle_geometry, capsys):
    blank = tmp_path / "blank.npy"
    np.save(blank, np.zeros((256, 256)))
    rng = np.random.default_rng(0)
    noise = tmp_path / "noise.npy"
    np.save(noise, rng.uniform(0, 1, (256, 256)))
    miss = _simulate_cli(tmp_path, neuro_geometry_file, "miss.dcm", "--depth", "80", "--noise", "rician", "--seed", "1",
                        "--allow-empty")
    good = _simulate_cli(tmp_path, neuro_geometry_file, "good.dcm", "--depth", "25", "--tilt", "10")
    wrong_geom = write_geometry(needle_geometry, tmp_path / "needle.yaml")
    capsys.readouterr()
    runs = [
        [str(blank), "--pixel-spacing", "0.5", "0.5"],
        [str(noise), "--pixel-spacing", "0.5", "0.5"],
        [str(miss)],
    ]
    for r in runs:
        assert main(["solve", *r, "--geometry", str(neuro_geometry_file), "--json"]) == 3, r
        doc = json.loads(capsys.readouterr().out)
        assert doc["status"] == "no_lock" and doc["reason"] and "T_scanner_from_fiducial" not in doc
    assert main(["solve", str(good), "--geometry", str(wrong_geom)]) == 3
    assert "no lock" in capsys.readouterr().err


def test_a_failing_output_does_not_lose_the_pose(tmp_path, capsys, dicom_slice, neuro_geometry_file):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    # an output path that cannot work is bad input, refused before any work (exit 2, nothing created)
    rc = main(["solve", str(dicom_slice[0]), "--geometry", str(neuro_geometry_file), "--json",
                        "--tfm", str(blocker / "pose.tfm")])
    out, err = capsys.readouterr()
    assert rc == 2 and out == "" and "is not a folder" in err
    # an output that fails after the solve (here: --scene over a folder that is not a scene) keeps the pose: exit 4
    (tmp_path / "notes").mkdir()
    (tmp_path / "notes" / "thesis.tex").write_text("x")
    rc = main(["solve", str(dicom_slice[0]), "--geometry", str(neuro_geometry_file), "--json",
                        "--scene", str(tmp_path / "notes"), "--tfm", str(tmp_path / "pose.tfm")])
    out, err = capsys.readouterr()
    assert rc == 4
    doc = json.loads(out)
    assert doc["status"] == "ok"
    assert np.allclose(doc["T_scanner_from_fiducial"], dicom_slice[1], atol=0.5)
    assert "chic-register: output failed: --scene" in err and "Traceback" not in err
    assert (tmp_path / "pose.tfm").is_file() and (tmp_path / "notes" / "thesis.tex").read_text() == "x"


def test_a_spec_given_as_geometry_gets_a_hint(capsys, tmp_path):
    img = tmp_path / "x.npy"
    np.save(img, np.zeros((16, 16)))
    assert main(["solve", str(img), "--geometry", str(ROOT / "designs" / "neuro.yaml"),
                 "--pixel-spacing", "1", "1"]) == 2
    err = capsys.readouterr().err
    assert "looks like a design spec" in err and "chic-design build" in err and "None" not in err


@pytest.mark.parametrize("as_json", [True, False])
def test_every_file_solve_writes_is_reported(tmp_path, capsys, dicom_slice, neuro_geometry_file, as_json):
    """One "wrote" line per output: on stderr (prefixed) under --json so stdout stays one JSON object, else stdout."""
    tfm, overlay, scene = tmp_path / "pose.tfm", tmp_path / "o.png", tmp_path / "scene"
    rc = main(["solve", str(dicom_slice[0]), "--geometry", str(neuro_geometry_file), "--tfm", str(tfm),
               "--overlay", str(overlay), "--scene", str(scene)] + (["--json"] if as_json else []))
    assert rc == 0
    out, err = capsys.readouterr()
    notes = err if as_json else out
    prefix = "chic-register: " if as_json else ""
    assert f"{prefix}wrote {tfm} (T_fiducial_from_scanner, ITK/LPS)" in notes
    assert f"{prefix}wrote {overlay}" in notes
    line = next(x for x in notes.splitlines() if x.startswith(f"{prefix}wrote {scene / 'scene.mrml'}"))
    for name in sorted(p.name for p in scene.iterdir() if p.name != "scene.mrml"):
        assert name in line, name
    if as_json:
        assert json.loads(out)["status"] == "ok"  # nothing but the JSON object on stdout
        assert "wrote" not in out
