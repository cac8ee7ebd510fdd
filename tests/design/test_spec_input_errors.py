"""Out-of-range spec values, YAML traps, huge files and FIFOs are one-line errors of chic-design (exit 2)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import yaml

from chic_design.cli import main as design_main
from tests.conftest import ROOT
from tests.helpers import one_line_error

NEURO_TEXT = (ROOT / "designs" / "neuro.yaml").read_text()


def _spec(tmp_path, keys, value, name="spec.yaml") -> Path:
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
    err = one_line_error(capsys, f"chic-design: error: {path}: ")
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
    assert fragment in one_line_error(capsys, f"chic-design: error: {path}: ")


def test_a_50_mb_spec_and_a_fifo_are_refused_before_reading(tmp_path, capsys):
    big = tmp_path / "big.yaml"
    with open(big, "wb") as fh:
        fh.write(NEURO_TEXT.encode())
        fh.truncate(50 * 2**20)
    assert design_main(["check", str(big)]) == 2
    assert "a spec file is at most 262144 bytes" in one_line_error(capsys, "chic-design: error: ")
    fifo = tmp_path / "fifo.yaml"
    os.mkfifo(fifo)
    assert design_main(["build", str(fifo), "--out", str(tmp_path / "out")]) == 2
    assert "is a FIFO (named pipe), not a spec file" in one_line_error(capsys, "chic-design: error: ")


def test_schema_documents_the_physical_ranges():
    from chic_design.spec import json_schema

    body = json_schema()["$defs"]["BodySpec"]["properties"]
    assert body["length"]["maximum"] == 200 and body["length"]["minimum"] == 2
    assert json_schema()["properties"]["name"]["maxLength"] == 64


def test_check_flags_meet_the_spec_ranges(capsys):
    assert design_main(["check", str(ROOT / "designs" / "neuro.yaml"), "--pixel-size", "1e9"]) == 2
    assert "imaging.pixel_size: Input should be less than or equal to 10" in one_line_error(
        capsys, "chic-design: error: ")
