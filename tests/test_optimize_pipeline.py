"""chic-design optimize end to end: every written spec validates, one builds and registers; a killed run resumes."""

from __future__ import annotations

import csv
import os
import re
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from chic_design.build import build_design
from chic_design.cli import main
from chic_design.feasibility import check_design
from chic_design.spec import load_spec
from chic_register.geometry import load_geometry
from chic_register.simulate import simulate_slice
from chic_register.solve import register

ROOT = Path(__file__).resolve().parents[1]
SMALL = ROOT / "tests" / "data" / "optimize-small.yaml"


@pytest.mark.slow
def test_optimize_specs_validate_and_the_chosen_one_builds_and_registers(tmp_path, capsys):
    out = tmp_path / "opt"
    assert main(["optimize", str(SMALL), "--out", str(out), "--trials", "8", "--seed", "3", "--workers", "1",
                 "--quiet"]) == 0
    summary = capsys.readouterr().out
    assert "chosen: small-p01" in summary
    rows = list(csv.DictReader((out / "pareto.csv").open()))
    specs = sorted((out / "specs").glob("*.yaml"))
    assert sorted(r["name"] for r in rows) == [p.stem for p in specs]
    for p in specs:  # every spec written validates and is feasible for its protocol
        spec = load_spec(p)
        assert spec.name == p.stem and check_design(spec).feasible
    for f in ("report.md", "pareto.png", "chosen/preview.png", "chosen/tilt_limits.png",
              "chosen/precision_map.png", "confirm.json", "candidates.sqlite"):
        assert (out / f).is_file(), f
    report = (out / "report.md").read_text()
    assert "Against the baseline" in report and "Confirmed by simulation" in report
    # the chosen design builds, and its geometry file registers a simulated slice
    res = build_design(out / "specs" / "small-p01.yaml", out_root=tmp_path / "exports", progress=False)
    geom = load_geometry(res.folder / "geometry.yaml")
    sim = simulate_slice(geom, 13.0, 8.0, 40.0, 15.0, pixel_spacing_mm=(0.3, 0.3), slice_thickness_mm=1.5,
                         noise="rician", snr=20.0, rng=5)
    reg = register([sim.slice], geom)
    pts = np.array([[0, 0, 0, 1], [0, 0, -30, 1]], float).T  # axis point and the target
    d = (reg.T_scanner_from_fiducial @ pts - sim.truth.T_scanner_from_fiducial @ pts)[:3]
    assert np.abs(d).max() < 1.0


@pytest.mark.slow
def test_killed_run_resumes_without_recomputing(tmp_path):
    out = tmp_path / "opt"
    cmd = [sys.executable, "-m", "chic_design.cli", "optimize", str(SMALL), "--out", str(out), "--trials", "12",
           "--seed", "3", "--workers", "1", "--quiet"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    db = out / "candidates.sqlite"
    done = 0
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.5)
        if db.exists():
            try:
                with sqlite3.connect(db) as c:
                    done = c.execute("SELECT COUNT(*) FROM candidates").fetchone()[0]
            except sqlite3.OperationalError:
                continue
            if done >= 3:
                break
    assert proc.poll() is None, "the run finished before it could be killed"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (out / "report.md").exists()
    with sqlite3.connect(db) as c:
        stored = c.execute("SELECT COUNT(*) FROM candidates").fetchone()[0]
    assert stored >= 3
    again = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr
    m = re.search(r"\((\d+) evaluated, (\d+) from the store\)", again.stdout)
    evaluated, cached = int(m.group(1)), int(m.group(2))
    assert cached >= stored and evaluated + cached >= 12 - 1
    with sqlite3.connect(db) as c:
        total = c.execute("SELECT COUNT(*) FROM candidates").fetchone()[0]
    assert total == stored + evaluated
