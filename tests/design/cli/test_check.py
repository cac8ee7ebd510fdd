"""chic-design check beyond the feasibility numbers: the precision map and the status lines."""

from __future__ import annotations

import json

import pytest

from chic_design.cli.main import main as design_main
from chic_register.precision.report import report_section
from tests.conftest import NEURO


@pytest.mark.slow
def test_design_check_precision_section(tmp_path, capsys):
    """``chic-design check --precision``: the design's precision map for its own protocol, in JSON and a plot."""
    plot = tmp_path / "p.png"
    assert design_main(["check", str(NEURO), "--json", "--precision", "--precision-plot", str(plot)]) == 0
    out, err = capsys.readouterr()
    doc = json.loads(out)
    assert "chic-design: precision map of neuro: Cramer-Rao bound over depth and tilt" in err
    assert "tilt_limits" in doc and doc["precision"]["protocol"]["pixel_size_mm"] == 0.5
    rows = doc["precision"]["rows"]
    assert len(rows) == 15 and {r["tilt_deg"] for r in rows} == {0.0, 15.0, 30.0}
    mid = [r for r in rows if r["depth_mm"] == 25.0]
    assert mid[0]["sd_normal_deg"] == pytest.approx(0.21, rel=0.15)  # the bound's figure for one slice at tilt 0
    assert plot.read_bytes()[:4] == b"\x89PNG"
    assert design_main(["check", str(NEURO), "--precision", "--pixel-size", "0"]) == 0
    assert "precision: not computed" in capsys.readouterr().out
    assert "Not computed" in report_section(None)
    assert design_main(["check", str(NEURO), "--precision", "--snr", "-1"]) == 2
