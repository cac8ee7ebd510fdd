"""chic-design optimize end to end: every written spec validates, one builds and registers; a killed run resumes."""

from __future__ import annotations

import csv
import os
import signal
import sqlite3
import subprocess
import sys
import time

import numpy as np
import pytest

from chic_design.build.pipeline import build_design
from chic_design.cli.main import main
from chic_design.families import family_of
from chic_design.optimize import space
from chic_design.optimize.engine import SerialEngine
from chic_design.optimize.requirements import baseline_path, load_requirements
from chic_design.optimize.search import run_search
from chic_design.optimize.store import ResultStore
from chic_design.spec import load_spec
from chic_register.imaging.simulate import simulate_slice
from chic_register.model.geometry import load_geometry
from chic_register.pipeline.register import register
from tests.conftest import ROOT

SMALL = ROOT / "tests" / "data" / "optimize-small.yaml"


@pytest.mark.slow
def test_optimize_specs_validate_and_the_chosen_one_builds_and_registers(tmp_path, capsys):
    out = tmp_path / "opt"
    assert main(["optimize", str(SMALL), "--out", str(out), "--trials", "4", "--seed", "3", "--workers", "1",
                 "--quiet"]) == 0
    summary = capsys.readouterr().out
    assert "chosen: small-p01" in summary
    rows = list(csv.DictReader((out / "pareto.csv").open(encoding="utf-8")))
    specs = sorted((out / "specs").glob("*.yaml"))
    assert sorted(r["name"] for r in rows) == [p.stem for p in specs]
    for p in specs:  # every spec written validates and is feasible for its protocol
        spec = load_spec(p)
        assert spec.name == p.stem and family_of(spec).check(spec).feasible
    for f in ("report.md", "pareto.png", "chosen/preview.png", "chosen/tilt_limits.png",
              "chosen/precision_map.png", "confirm.json", "candidates.sqlite"):
        assert (out / f).is_file(), f
    report = (out / "report.md").read_text(encoding="utf-8")
    assert "Against the baseline" in report and "Confirmed by simulation" in report
    # the chosen design builds, and its geometry file registers a simulated slice
    res = build_design(out / "specs" / "small-p01.yaml", out_root=tmp_path / "exports", progress=False,
                       printcheck=False)
    geom = load_geometry(res.folder / "geometry.yaml")
    # three parallel slices 1.5 mm apart (one slice of this slim design is refused as too imprecise)
    truth, slices = None, []
    for i, depth in enumerate((11.5, 13.0, 14.5)):
        sim = simulate_slice(geom, depth, 8.0, 40.0, 15.0, pixel_spacing_mm=(0.3, 0.3), slice_thickness_mm=1.5,
                             noise="rician", snr=20.0, rng=5 + i, T_scanner_from_fiducial=truth)
        truth = sim.truth.T_scanner_from_fiducial
        slices.append(sim.slice)
    reg = register(slices, geom)
    pts = np.array([[0, 0, 0, 1], [0, 0, -30, 1]], float).T  # axis point and the target
    d = (reg.T_scanner_from_fiducial @ pts - truth @ pts)[:3]
    assert np.abs(d).max() < 1.0


@pytest.mark.slow
def test_killed_run_resumes_without_recomputing(tmp_path):
    out = tmp_path / "opt"
    cmd = [sys.executable, "-m", "chic_design.cli", "optimize", str(SMALL), "--out", str(out), "--trials", "8",
           "--seed", "3", "--workers", "1", "--quiet"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    db = out / "candidates.sqlite"
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.3)
        if db.exists():
            try:
                with sqlite3.connect(db) as c:
                    if c.execute("SELECT COUNT(*) FROM candidates").fetchone()[0] >= 2:
                        break
            except sqlite3.OperationalError:
                continue
    assert proc.poll() is None, "the run finished before it could be killed"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (out / "report.md").exists()
    with sqlite3.connect(db) as c:
        stored = {k for (k,) in c.execute("SELECT key FROM candidates")}
    assert len(stored) >= 2
    # the same search again (what the command runs) on the killed run's store
    req = load_requirements(SMALL)
    start = space.params_from_spec(load_spec(baseline_path(req, SMALL)), req)
    with ResultStore(db) as store:
        res = run_search(req, SerialEngine(), store, trials=8, seed=3, population=4, start_params=start,
                         progress=False)
        total = len(store)
    keys = [c["key"] for c in res.candidates]
    assert stored <= set(keys) and res.cached >= len(stored)
    assert res.evaluated == len(set(keys) - stored) and total == len(set(keys))
