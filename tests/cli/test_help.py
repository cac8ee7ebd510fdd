"""The shape of the chic-register CLI: one module per subcommand, plain-text help, no private names across modules."""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest

from chic_register.cli import main as cli_main

ROOT = Path(__file__).resolve().parents[2]
SUBCOMMANDS = ("solve", "map", "calibrate", "precision", "simulate", "evaluate", "reslice", "track")
#: reStructuredText and Sphinx markup that has no place in a terminal
MARKUP = re.compile(r"``|:(mod|func|class|meth|data|attr):|`[^`]+`_?")


def _help(capsys, argv) -> str:
    with pytest.raises(SystemExit) as stop:
        cli_main.main(argv)
    assert stop.value.code == 0
    return capsys.readouterr().out


@pytest.mark.parametrize("argv", [["--help"]] + [[c, "--help"] for c in SUBCOMMANDS])
def test_help_is_plain_text(argv, capsys):
    text = _help(capsys, argv)
    assert text.startswith("usage: chic-register")
    assert not MARKUP.search(text), MARKUP.search(text).group(0)
    assert "chic_register." not in text  # no module paths either


def test_top_level_help_lists_every_subcommand_with_its_help(capsys):
    text = _help(capsys, ["--help"])
    for command in cli_main.COMMANDS:
        name = command.__name__.rsplit(".", 1)[1]
        assert re.search(rf"^\s+{name}\b", text, flags=re.M), name
        assert " ".join(command.HELP.split()[:4]) in " ".join(text.split()), name


def test_each_subcommand_is_one_module_owning_its_parser_and_its_run():
    assert [m.__name__.rsplit(".", 1)[1] for m in cli_main.COMMANDS] == list(SUBCOMMANDS)
    parser = cli_main.build_parser()
    for command in cli_main.COMMANDS:
        name = command.__name__.rsplit(".", 1)[1]
        assert callable(command.add_parser) and callable(command.run)
        argv = {"solve": ["solve", "x.dcm"], "reslice": ["reslice", "v.nii", "--reference", "r.json"],
                "calibrate": ["calibrate", "v.nii", "--out", "g2.yaml"],
                "simulate": ["simulate", "--depth", "1", "--out", "x.npy"],
                "map": ["map", "--pose", "p.json", "--to", "frame"]}.get(name, [name])
        args = parser.parse_args([*argv, "--geometry", "g.yaml"])
        assert args.command == name and args.run is command.run


def test_main_holds_no_command_of_its_own():
    tree = ast.parse((ROOT / "chic_register" / "cli" / "main.py").read_text())
    functions = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert functions == {"build_parser", "main"}
    assert "add_argument(\"--geometry\"" not in (ROOT / "chic_register" / "cli" / "main.py").read_text()


@pytest.mark.parametrize("path", sorted((ROOT / "chic_register" / "cli").glob("*.py"))
                         + [ROOT / "chic_register" / "outputs" / n for n in ("deliver.py", "overlay.py", "scene.py")]
                         + [ROOT / "docs" / "render_scene.py"], ids=lambda p: p.name)
def test_no_private_name_is_imported_from_another_module(path):
    tree = ast.parse(path.read_text())
    private = [f"{node.module}.{alias.name}" for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)
               for alias in node.names if alias.name.startswith("_") and alias.name != "__version__"
               and node.module != "__future__"]
    assert not private, private


def test_function_local_imports_in_the_cli_say_why(tmp_path):
    """A function-local import is there to keep start-up fast: each block of them carries a comment saying so."""
    imports = re.compile(r"\s+(from \S+ )?import ")
    for path in sorted((ROOT / "chic_register" / "cli").glob("*.py")):
        lines = path.read_text().splitlines()
        for k, line in enumerate(lines):
            if not imports.match(line):
                continue
            above = [x for x in lines[:k] if x.strip()][-2:]  # the two lines above, blank lines skipped
            if imports.match(above[-1]):  # inside a block of imports: its first line carries the comment
                continue
            if "TYPE_CHECKING" in above[-1]:  # annotations only, never imported at run time
                continue
            assert "# here" in " ".join(above[-1:] + [line]), f"{path.name}:{k + 1}: {line.strip()}"


def test_one_shot_start_up_imports_no_library_module(tmp_path):
    """Building the parser (every command's module) loads no solver, imaging or plotting code."""
    import json
    import subprocess
    import sys

    code = ("import json, sys\nfrom chic_register.cli.main import build_parser\nbuild_parser()\n"
            "print(json.dumps(sorted(sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, encoding="utf-8", errors="replace", check=True, timeout=120)
    mods = set(json.loads(out.stdout))
    loaded = sorted(m for m in mods if m.startswith("chic_register.") and not m.startswith(
        ("chic_register.cli", "chic_register.errors", "chic_register.version")))
    assert not loaded and "numpy" not in mods, loaded


@pytest.mark.parametrize("module, argv", [("chic_register.cli.main", ["solve", "--help"]),
                                          ("chic_design.cli.main", ["check", "--help"])])
def test_help_points_at_the_projects_own_interface_document(module, argv, capsys):
    with pytest.raises(SystemExit):
        importlib.import_module(module).main(argv)
    out = capsys.readouterr().out
    assert "docs/interfaces.md" in out and "CONTRACT.md" not in out


#: Libraries a one-shot solve of one DICOM slice does not need: each costs tens to hundreds of ms of start-up.
HEAVY_FOR_ONE_SLICE = ("scipy", "SimpleITK", "matplotlib", "skimage", "trimesh", "pyvista", "build123d",
                       "chic_design", "dask", "optuna", "pyigtl")


def test_a_one_shot_solve_of_a_dicom_slice_loads_only_what_it_needs(tmp_path, neuro_geometry):
    """The first solve in a fresh process pays for its imports: a DICOM slice's solve, verification included,
    loads none of the heavy libraries the other commands use (the start-up budget: docs/benchmarks.md)."""
    import json
    import subprocess
    import sys

    from chic_register.imaging.simulate import simulate_slice, write_simulated
    from chic_register.model.geometry import write_geometry

    g = write_geometry(neuro_geometry, tmp_path / "geometry.yaml")
    sim = simulate_slice(neuro_geometry, 22, 20, 30, 15, noise="rician", snr=20, rng=3)
    image, _ = write_simulated(sim, tmp_path / "slice.dcm")
    code = ("import json, sys\nfrom chic_register.cli.main import main\n"
            f"status = main(['solve', {str(image)!r}, '--geometry', {str(g)!r}, '--json'])\n"
            "print(json.dumps({'status': status, 'modules': sorted(sys.modules)}), file=sys.stderr)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, encoding="utf-8",
                         errors="replace", check=True, timeout=120)
    doc = json.loads(out.stderr.strip().splitlines()[-1])
    assert doc["status"] == 0 and json.loads(out.stdout)["status"] == "ok"
    heavy = sorted({m.split(".")[0] for m in doc["modules"]} & set(HEAVY_FOR_ONE_SLICE))
    assert not heavy, heavy
