"""chic-register evaluate: the study's JSON, plots and study file."""

from __future__ import annotations

import json

from chic_register.cli.main import main


def test_cli_evaluate_writes_plots_and_json(tmp_path, neuro_geometry_file, capsys):
    out = tmp_path / "study"
    rc = main(["evaluate", "--geometry", str(neuro_geometry_file), "--draws", "1", "--noise", "uniform",
               "--out", str(out), "--json"])
    assert rc == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc) == {"uniform"} and len(doc["uniform"]["cases"]) == 18
    assert doc["uniform"]["summary"]["twist"]["paper_max"] == 0.032
    for name in ("fig7-uniform.png", "fig8-uniform.png", "study-uniform.json"):
        assert (out / name).stat().st_size > 0
    assert main(["evaluate", "--geometry", str(neuro_geometry_file), "--draws", "0"]) == 2
