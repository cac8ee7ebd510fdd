"""chic-register precision: the map as JSON, text and plot; bad flags."""

from __future__ import annotations

import json

from chic_register.cli.main import main


def test_precision_command(tmp_path, neuro_geometry_file, capsys):
    plot = tmp_path / "map.png"
    args = ["precision", "--geometry", str(neuro_geometry_file), "--depths", "25", "--tilts", "0", "30",
            "--azimuths", "1"]
    assert main(args + ["--json", "--plot", str(plot)]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [r["tilt_deg"] for r in doc["rows"]] == [0.0, 30.0]
    normal = [r["sd_normal_deg"] for r in doc["rows"]]
    assert 0.1 < normal[0] < 0.4 and normal[1] < normal[0]  # about 0.21 deg at tilt 0, 0.07 at 30
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(args) == 0
    assert "TRE mm" in capsys.readouterr().out
    for bad in (["--snr", "0"], ["--tilts", "95"], ["--plot", str(tmp_path / "x.jpg")], ["--slices", "0"]):
        assert main(args + bad) == 2, bad
        assert capsys.readouterr().err.count("\n") == 1


def test_precision_shows_progress_on_stderr_and_keeps_json_stdout_clean(tmp_path, neuro_geometry_file, capsys):
    """The map is computed cell by cell behind a progress bar (stderr); the cells are the library's map."""
    from chic_register.model.geometry import load_geometry
    from chic_register.precision.crlb import Protocol, precision_map

    plot = tmp_path / "map.png"
    assert main(["precision", "--geometry", str(neuro_geometry_file), "--depths", "15", "35", "--tilts", "0", "20",
                 "--azimuths", "1", "--json", "--plot", str(plot)]) == 0
    out, err = capsys.readouterr()
    doc = json.loads(out)  # stdout: the JSON object alone
    assert "precision map" in err and "4/4" in err and f"chic-register: wrote {plot}" in err
    whole = precision_map(load_geometry(neuro_geometry_file), Protocol(0.5, 2.0, 20.0, 1, 2.0), [15, 35], [0, 20],
                          n_azimuths=1)
    assert doc["rows"] == json.loads(json.dumps([dict(r) for r in whole.rows]))
    assert doc["target_F_mm"] == list(whole.target_F_mm) and doc["azimuths_deg"] == list(whole.azimuths_deg)


def test_precision_default_depths_span_the_body(neuro_geometry_file, capsys):
    assert main(["precision", "--geometry", str(neuro_geometry_file), "--tilts", "0", "--azimuths", "1",
                 "--json"]) == 0
    depths = [r["depth_mm"] for r in json.loads(capsys.readouterr().out)["rows"]]
    assert depths == [5.0 * k for k in range(1, 10)]  # 10 % to 90 % of the 50 mm body, 9 depths
