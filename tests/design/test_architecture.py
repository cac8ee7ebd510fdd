"""The shape of chic_design, read from its source: stage layers, no import cycle, no private name across modules,
no family switch outside the families, no re-export facades, a reason for every function-local import."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

from tests.conftest import ROOT

PACKAGE = ROOT / "chic_design"

#: Stage components of chic_design, lowest first. A module may import its own component, and any
#: component of a lower layer; components of one layer are independent of each other.
LAYERS = (
    {"chic_design", "chic_design.errors", "chic_design.progress", "chic_design.lifeline"},
    {"chic_design.cad", "chic_design.feasibility"},
    {"chic_design.printing"},
    {"chic_design.families", "chic_design.verify"},
    {"chic_design.spec", "chic_design.report"},
    {"chic_design.build", "chic_design.optimize"},
    {"chic_design.cli"},
)


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


SOURCES = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}
TREES = {name: ast.parse(path.read_text(encoding="utf-8")) for name, path in SOURCES.items()}


def _resolve(module: str, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".") if SOURCES[module].name == "__init__.py" else module.split(".")[:-1]
    base = base[: len(base) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def _imports(module: str):
    """Every import in ``module`` (module level, in functions and under TYPE_CHECKING alike):
    ``(line, imported module, imported name or None)``."""
    for node in ast.walk(TREES[module]):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name, None
        elif isinstance(node, ast.ImportFrom):
            target = _resolve(module, node)
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                if sub in SOURCES:  # `from package import submodule`
                    yield node.lineno, sub, None
                else:
                    yield node.lineno, target, alias.name


def _graph() -> dict[str, set[str]]:
    return {m: {t for _, t, _ in _imports(m) if t in SOURCES and t != m} for m in SOURCES}


def _component(module: str) -> str:
    parts = module.split(".")
    return ".".join(parts[:2])


def _layer(component: str) -> int:
    for i, layer in enumerate(LAYERS):
        if component in layer:
            return i
    raise AssertionError(f"{component} is in no layer of this test: add it to LAYERS")


def test_every_module_is_in_a_layer():
    for module in SOURCES:
        _layer(_component(module))


def test_no_import_cycle_of_any_kind():
    graph = _graph()
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            scc = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                scc.append(w)
                if w == v:
                    break
            if len(scc) > 1:
                cycles.append(sorted(scc))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not cycles, cycles


def test_a_lower_stage_never_imports_a_higher_one_and_siblings_are_independent():
    bad = []
    for module, targets in _graph().items():
        src = _component(module)
        for target in targets:
            dst = _component(target)
            if src != dst and _layer(dst) >= _layer(src) and dst != "chic_design":
                bad.append(f"{module} imports {target}")
    assert not bad, bad


def test_no_private_name_is_imported_from_another_module():
    bad = []
    for module in SOURCES:
        for line, target, name in _imports(module):
            private_name = name is not None and name.startswith("_") and not name.startswith("__")
            private_module = any(p.startswith("_") and not p.startswith("__") for p in target.split("."))
            if private_name or private_module:
                bad.append(f"{SOURCES[module].relative_to(ROOT)}:{line}: {target} {name or ''}")
    assert not bad, bad


def test_tests_of_chic_design_import_no_private_name_and_nothing_from_benchmarks():
    bad = []
    for path in sorted((ROOT / "tests" / "design").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ImportFrom):
                names = [a.name for a in node.names]
                if (node.module or "").startswith("benchmarks") or any(
                        n.startswith("_") and not n.startswith("__") for n in names):
                    bad.append(f"{path.relative_to(ROOT)}:{node.lineno}")
            elif isinstance(node, ast.Import) and any(a.name.startswith("benchmarks") for a in node.names):
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not bad, bad


def _outside_families():
    return [m for m in SOURCES if not m.startswith("chic_design.families")]


def test_no_family_switch_outside_the_families():
    """Generic code asks the family; it never compares a family name or tests for one family's spec."""
    bad = []
    names = {"chic", "zframe", "nlocalizer"}
    for module in _outside_families():
        for node in ast.walk(TREES[module]):
            if isinstance(node, ast.Compare) and not all(isinstance(op, (ast.Is, ast.IsNot)) for op in node.ops):
                sides = [node.left, *node.comparators]  # `x.family is None` asks whether one was given: no switch
                if any(isinstance(s, (ast.Attribute, ast.Name)) and (getattr(s, "attr", None) or getattr(s, "id", None))
                       == "family" for s in sides) or any(isinstance(s, ast.Constant) and s.value in names
                                                          for s in sides):
                    bad.append(f"{module}:{node.lineno}: compares a family")
            elif isinstance(node, ast.Constant) and node.value in names:
                bad.append(f"{module}:{node.lineno}: names the family {node.value!r}")
    # the optimiser searches the CHIC design space: its one tie to a family is an isinstance on the CHIC spec
    assert not bad, bad


def test_no_reexport_facades():
    bad = [f"{m}" for m, p in SOURCES.items() if re.search(r"noqa: *F401", p.read_text(encoding="utf-8"))]
    assert not bad, bad


def test_function_local_imports_say_why():
    """An import inside a function is there to keep start-up fast: the first of each function says so."""
    bad = []
    for module, path in SOURCES.items():
        lines = path.read_text(encoding="utf-8").splitlines()
        for fn in ast.walk(TREES[module]):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            local = sorted(n.lineno for n in ast.walk(fn) if isinstance(n, (ast.Import, ast.ImportFrom)))
            if local and "#" not in lines[local[0] - 1]:
                bad.append(f"{path.relative_to(ROOT)}:{local[0]}")
    assert not bad, bad


@pytest.mark.parametrize("module", ["chic_design.cli.build", "chic_design.cli.check", "chic_design.cli.optimize",
                                    "chic_design.cli.schema"])
def test_each_subcommand_module_has_add_parser_and_run(module):
    defs = {n.name for n in TREES[module].body if isinstance(n, ast.FunctionDef)}
    assert {"add_parser", "run"} <= defs
