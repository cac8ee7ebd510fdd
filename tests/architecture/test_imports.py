"""The packages' shape: no import cycle of any kind, stages imported only downwards, lazy imports said why."""

from __future__ import annotations

import ast

import pytest

from tests.architecture.import_graph import ROOT, cycles, import_graph, module_files

#: chic_register's stages, lowest first: a module may import its own stage and the ones before it.
STAGES = ("errors", "version", "util", "options", "model", "io", "imaging", "detect", "guess", "fit", "verify",
          "precision", "pipeline", "outputs", "live", "studies", "cli")
#: Stages side by side: neither imports the other.
SIBLINGS = {frozenset({"live", "studies"})}


@pytest.mark.parametrize("package", ["chic_register", "chic_design"])
def test_no_import_cycle(package):
    """Counting imports inside functions and under TYPE_CHECKING: a cycle of any length fails."""
    assert cycles(import_graph((package,))) == []


def test_the_cycle_finder_finds_one():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def _stage(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else None


def test_a_lower_stage_never_imports_a_higher_one():
    rank = {s: i for i, s in enumerate(STAGES)}
    bad = []
    for mod, targets in import_graph(("chic_register",)).items():
        a = _stage(mod)
        for t in targets:
            b = _stage(t)
            if a is None or b is None or a == b:
                continue
            if rank[b] > rank[a] or frozenset({a, b}) in SIBLINGS:
                bad.append(f"{mod} -> {t}")
    assert not bad, bad
    assert set(_stage(m) for m in module_files("chic_register")) - {None} <= set(STAGES)


def test_the_solver_never_imports_the_design_side():
    graph = import_graph(("chic_register", "chic_design"))
    assert not [(m, t) for m, ts in graph.items() if m.startswith("chic_register") for t in ts
                if t.startswith("chic_design")]


def _import_blocks(tree: ast.AST):
    """Runs of consecutive import statements in a function's body or a block inside it."""
    inner = {n for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef)) for n in ast.walk(f)}
    for node in inner:
        for field in ("body", "orelse", "finalbody"):
            stmts = getattr(node, field, None)
            if not isinstance(stmts, list):
                continue
            block = []
            for st in stmts + [None]:
                if isinstance(st, (ast.Import, ast.ImportFrom)):
                    block.append(st)
                elif block:
                    yield block
                    block = []


@pytest.mark.parametrize("package", ["chic_register", "chic_design"])
def test_every_function_local_import_says_why(package):
    """An import inside a function exists only to keep start-up fast: a comment on one of its block's imports, or
    on the line above the block, says so."""
    missing = []
    for path in module_files(package).values():
        lines = path.read_text().splitlines()
        for block in _import_blocks(ast.parse("\n".join(lines))):
            text = lines[block[0].lineno - 2:block[-1].end_lineno]
            if not any("#" in line for line in text):
                missing.append(f"{path.relative_to(ROOT)}:{block[0].lineno}")
    assert not missing, missing
