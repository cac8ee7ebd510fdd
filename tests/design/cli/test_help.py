"""The command line a newcomer meets: plain-text help, a status line before every slow step, a line per file written."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

import chic_design.build.pipeline as pipeline_mod
from chic_design.cli.main import main
from tests.conftest import NEURO


@pytest.mark.parametrize("argv", [[], ["build"], ["check"], ["schema"], ["optimize"]])
def test_help_is_plain_text(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv + ["--help"])
    assert exc.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: chic-design")
    for markup in ("``", ":mod:", ":func:", ":class:", "**", "`"):
        assert markup not in out, (argv, markup)


def test_build_says_what_it_does_before_the_cad_kernel_loads_and_lists_what_it_wrote(tmp_path, capsys, monkeypatch):
    seen = {}

    class Result:
        folder = tmp_path / "out" / "neuro"
        files = ("body.stl", "geometry.yaml")

        def summary_text(self):
            return "built it"

    def fake_build(spec_path, out_root, force, progress, printcheck):
        seen["stderr before the build"] = capsys.readouterr().err
        return Result()

    monkeypatch.setattr(pipeline_mod, "build_design", fake_build)
    assert main(["build", str(NEURO), "--out", str(tmp_path / "out")]) == 0
    assert seen["stderr before the build"] == (f"chic-design: building neuro from {NEURO} into {tmp_path / 'out'}/neuro/ "
                                               "(loading the CAD kernel)\n")
    out, err = capsys.readouterr()
    assert out == "built it\n"
    assert err.splitlines() == [f"chic-design: wrote {Result.folder / 'body.stl'}",
                                f"chic-design: wrote {Result.folder / 'geometry.yaml'}"]
    monkeypatch.setattr(pipeline_mod, "build_design", lambda *a, **k: Result())
    assert main(["build", str(NEURO), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    assert capsys.readouterr().err == ""


def test_check_json_keeps_stdout_clean_and_says_what_it_checks_on_stderr(capsys):
    assert main(["check", str(NEURO), "--json"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["feasible"] is True
    assert err == "chic-design: checking neuro: tilt limits at every depth and azimuth, walls, overhangs, symmetry\n"


def test_python_dash_m_runs_the_same_program():
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[3]
    done = subprocess.run([sys.executable, "-m", "chic_design.cli", "--version"], cwd=root, capture_output=True,
                          text=True, encoding="utf-8", errors="replace", timeout=60)
    assert done.returncode == 0 and done.stdout.startswith("chic-design ")
