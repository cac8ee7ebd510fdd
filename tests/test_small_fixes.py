"""The smaller things a newcomer hit (issue 10), each pinned by a test."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from chic_register.cli.main import main

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text(encoding="utf-8")


def test_readme_links_stay_inside_the_repository():
    links = re.findall(r"\]\(([^)#\s]+)", README)
    local = [x for x in links if not x.startswith(("http://", "https://", "mailto:"))]
    assert "docs/interfaces.md" in local
    for link in local:
        target = (ROOT / link).resolve()
        assert target.is_relative_to(ROOT) and target.exists(), link


def test_readme_defines_G_before_using_it():
    blocks = re.findall(r"```(?:sh|console)\n(.*?)```", README, flags=re.S)
    assert not any("--geometry G " in b for b in blocks)  # shell commands use $G, defined first
    first = next(b for b in blocks if "$G" in b)
    assert re.search(r"^(\$ )?G=\S+geometry.yaml$", first[: first.index("$G")], flags=re.M), first[:200]


def test_interfaces_doc_keeps_the_contract_and_adds_the_decisions():
    doc = (ROOT / "docs" / "interfaces.md").read_text(encoding="utf-8")
    for heading in ("## 1. The fiducial frame F", "## 2. The geometry file", "## 3. Image coordinates",
                    "## 4. Commands and their JSON", "## 5. 3D Slicer, OpenIGTLink and robots"):
        assert heading in doc
    for fact in ("SPACE=LPS", "CHICToRAS", "CHICTool", "T_scanner_from_tool", "exit code is 4"):
        assert fact in doc


def test_simulate_with_no_tube_in_view_is_an_error_and_writes_nothing(tmp_path, neuro_geometry_file, capsys):
    out = tmp_path / "s.npy"
    assert main(["simulate", "--geometry", str(neuro_geometry_file), "--depth", "80", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "no tube crosses the image" in err and "0..50" in err and len(err.strip().splitlines()) == 1
    assert list(tmp_path.iterdir()) == [neuro_geometry_file]
    assert main(["simulate", "--geometry", str(neuro_geometry_file), "--depth", "80", "--out", str(out),
                 "--allow-empty"]) == 0  # a deliberately missed slice, with a warning
    assert out.is_file() and "warning: only 0 of 9 tubes in view" in capsys.readouterr().err


def test_simulate_warns_when_some_tubes_are_out_of_view(tmp_path, neuro_geometry_file, capsys):
    out = tmp_path / "s.npy"
    assert main(["simulate", "--geometry", str(neuro_geometry_file), "--depth", "25", "--size", "64",
                 "--center-offset", "12", "0", "--out", str(out)]) == 0
    assert "warning: only" in capsys.readouterr().err


def test_overlay_view_shows_the_rejected_blobs_too():
    from chic_register.outputs.overlay import view_bounds

    tubes = np.array([[120.0, 120.0], [140.0, 135.0]])
    extra = np.array([[5.0, 250.0]])
    lo, hi = view_bounds(np.vstack([tubes, extra]), (256, 256))
    assert lo[0] == 0.0 and hi[1] == 255.0  # the far blob is inside the view
    lo, hi = view_bounds(np.zeros((0, 2)), (256, 256))
    assert list(lo) == [0, 0] and list(hi) == [255, 255]


@pytest.mark.parametrize("ratio, text", [(3.21, "3.2x better"), (1.0, "1.0x better"), (0.7, "1.4x worse"),
                                         (0.25, "4.0x worse")])
def test_evaluate_says_worse_when_worse(ratio, text):
    from chic_register.studies.evaluate import versus_paper

    assert versus_paper(ratio) == text




def test_a_spec_given_as_geometry_gets_a_hint(capsys, tmp_path):
    img = tmp_path / "x.npy"
    np.save(img, np.zeros((16, 16)))
    assert main(["solve", str(img), "--geometry", str(ROOT / "designs" / "neuro.yaml"),
                 "--pixel-spacing", "1", "1"]) == 2
    err = capsys.readouterr().err
    assert "looks like a design spec" in err and "chic-design build" in err and "None" not in err


@pytest.mark.parametrize("module, argv", [("chic_register.cli.main", ["solve", "--help"]),
                                          ("chic_design.cli.main", ["check", "--help"])])
def test_help_points_at_the_projects_own_interface_document(module, argv, capsys):
    import importlib

    with pytest.raises(SystemExit):
        importlib.import_module(module).main(argv)
    out = capsys.readouterr().out
    assert "docs/interfaces.md" in out and "CONTRACT.md" not in out
