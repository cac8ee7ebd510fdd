"""Bad input to chic-design: one line on stderr naming the file, key or value and what is allowed; never a traceback."""

from __future__ import annotations

import os
from types import SimpleNamespace

import pytest
import yaml

from chic_design.cli.main import main as design_main
from chic_design.errors import InfeasibleDesign
from tests.conftest import NEURO

NEURO_TEXT = NEURO.read_text()


def _one_line_error(capsys, prefix: str) -> str:
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and "\n" not in err, err
    assert err.startswith(prefix), err
    return err


def _spec(tmp_path, keys, value, name="spec.yaml"):
    data = yaml.safe_load(NEURO_TEXT)
    node = data
    for k in keys[:-1]:
        node = node[k]
    node[keys[-1]] = value
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("keys, value, fragment", [
    (["body", "length"], float("inf"), "body.length: Input should be a finite number"),
    (["helix", "pitch_deg_per_mm"], float("inf"), "helix.pitch_deg_per_mm: Input should be a finite number"),
    (["helix", "pitch_deg_per_mm"], float("nan"), "helix.pitch_deg_per_mm: Input should be a finite number"),
    (["body", "length"], 1e9, "body.length: Input should be less than or equal to 200"),
    (["body", "length"], 100000, "body.length: Input should be less than or equal to 200"),
    (["helix", "pitch_deg_per_mm"], 1e6, "helix.pitch_deg_per_mm: Input should be less than or equal to 90"),
    (["helix", "pitch_deg_per_mm"], 30.0, "turns the helix 1500 deg"),
    (["caps", "thickness"], float("inf"), "caps.thickness: Input should be a finite number"),
    (["caps", "skirt_wall"], 1e6, "caps.skirt_wall: Input should be less than or equal to 20"),
    (["name"], "a" * 255, "name: String should have at most 64 characters"),
    (["body", "length"], True, "body.length: Input should be a valid number"),
    (["print", "min_wall"], 0.01, "print.min_wall: Input should be greater than or equal to 0.1"),
])
def test_spec_values_out_of_range_are_one_line_errors(tmp_path, capsys, keys, value, fragment):
    path = _spec(tmp_path, keys, value)
    assert design_main(["check", str(path)]) == 2
    err = _one_line_error(capsys, f"chic-design: error: {path}: ")
    assert fragment in err


@pytest.mark.parametrize("text, fragment", [
    (NEURO_TEXT + "\nname: other\n", "duplicate key 'name'"),
    (NEURO_TEXT.replace("length: 50", "length: 1:10"), "body.length: Input should be a valid number (got '1:10')"),
    (NEURO_TEXT + "\nx: " + "[" * 5000 + "]" * 5000 + "\n", "nested deeper than 32 levels"),
])
def test_spec_yaml_traps_are_one_line_errors(tmp_path, capsys, text, fragment):
    path = tmp_path / "spec.yaml"
    path.write_text(text)
    assert design_main(["check", str(path)]) == 2
    assert fragment in _one_line_error(capsys, f"chic-design: error: {path}: ")


def test_a_50_mb_spec_and_a_fifo_are_refused_before_reading(tmp_path, capsys):
    big = tmp_path / "big.yaml"
    with open(big, "wb") as fh:
        fh.write(NEURO_TEXT.encode())
        fh.truncate(50 * 2**20)
    assert design_main(["check", str(big)]) == 2
    assert "a spec file is at most 262144 bytes" in _one_line_error(capsys, "chic-design: error: ")
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    assert design_main(["build", str(fifo), "--out", str(tmp_path / "out")]) == 2
    assert "is a FIFO (named pipe), not a spec file" in _one_line_error(capsys, "chic-design: error: ")


def test_check_flags_meet_the_spec_ranges(capsys):
    assert design_main(["check", str(NEURO), "--pixel-size", "1e9"]) == 2
    assert "imaging.pixel_size: Input should be less than or equal to 10" in _one_line_error(
        capsys, "chic-design: error: ")


def test_infeasible_build_lists_one_violation_per_line():
    vs = [SimpleNamespace(code=f"c{i}", where=f"w{i}", message=f"m{i}") for i in range(18)]
    text = str(InfeasibleDesign("spec.yaml", vs))
    lines = text.splitlines()
    assert len(lines) == 19 and "18 violations" in lines[0] and lines[5] == "  - c4 (w4): m4"
    assert max(len(x) for x in lines) < 200


def test_an_export_root_that_cannot_be_made_is_one_line(tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("x")
    assert design_main(["build", str(NEURO), "--out", str(blocker / "exports"), "--quiet"]) == 1
    assert str(blocker) in _one_line_error(capsys, "chic-design: error: ")


@pytest.mark.parametrize("argv, fragment", [
    (["optimize", "designs/requirements/neuro.yaml", "--scheduler", "udp://x"], "--scheduler 'udp://x': allowed are"),
    (["optimize", "designs/requirements/neuro.yaml", "--trials", "0"], "--trials must be >= 1, got 0"),
    (["check", str(NEURO), "--precision", "--snr", "-1"], "--snr must be > 0, got -1"),
    (["check", str(NEURO), "--precision", "--precision-plot", "p.txt"], "the plot is a PNG file"),
    (["schema", "--family", "tripod"], "--family: unknown family 'tripod'; allowed: chic, zframe, nlocalizer"),
])
def test_bad_flags_are_one_line_before_any_work(argv, fragment, capsys, monkeypatch):
    monkeypatch.chdir(NEURO.parents[1])
    assert design_main(argv) == 2
    assert fragment in _one_line_error(capsys, "chic-design: error: ")
