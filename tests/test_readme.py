"""Every console example in README.md, run and compared with the output the README shows.

Format of an example (the convention the README follows):

- An example is one or more fenced ``console`` blocks, each right after an HTML comment
  ``<!-- example: NAME -->`` (``<!-- example: NAME slow -->`` marks it ``slow``: left out of a
  plain ``pytest``, run by ``.ci/run``'s ``-m ''``). Blocks of the same NAME run in README order as
  one test. A ``console`` block without such a comment fails the test: none goes unchecked.
- A line starting with ``$ `` is a command; a command line ending in ``\\`` goes on to the next
  line. It runs in ``bash -o pipefail`` and must exit 0 (show a refusal as ``... || echo "exit $?"``).
  The lines after it, up to the next command, are its expected output: stdout and stderr together,
  as a terminal shows them (``PYTHONUNBUFFERED=1`` keeps their order).
- A line that is exactly ``...`` stands for any number of lines (none included); ``...`` inside
  a line stands for any text in it.
- Numbers: an integer (no decimal point) must be equal. A decimal number must agree within
  ``REL_TOL`` (5 %) of the value shown or one unit in its last digit shown, whichever is larger
  (so ``0.004`` accepts 0.003-0.005 and ``19.921`` accepts 18.93-20.92). A number written
  ``~12.3`` (timings) is shown for information and matches any number.
- Runs of spaces match runs of spaces (aligned tables); trailing spaces and trailing empty
  lines are ignored. The folder the examples run in is removed from paths in the output
  (``/tmp/.../exports/neuro`` reads ``exports/neuro``).

Where the examples run: every example of one pytest session shares one temporary folder, as one
user's checkout would, holding links to the repository's ``designs/`` and ``docs/``; commands find
``chic-design``, ``chic-register`` and ``python`` in this interpreter's environment. Each example
writes into folders of its own: after it ran, no file that an earlier example wrote may have
changed (the test fails naming the file). An example whose commands read
``exports/NAME/geometry.yaml`` that no example built yet (a plain ``pytest`` leaves the slow
builds out) gets that file from ``designs/NAME.yaml`` through the library, without the CAD build.
"""

from __future__ import annotations

import functools
import os
import re
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
REL_TOL = 0.05
COMMAND_TIMEOUT_S = 900

_NUM = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?"
_TOKEN = re.compile(rf"(?P<ellipsis>\.\.\.)|~(?P<approx>{_NUM})|(?P<num>{_NUM})|(?P<space>\s+)")
_MARKER = re.compile(r"^<!--\s*example:\s*(?P<name>[\w.-]+)(?P<flags>(?:\s+\w+)*)\s*-->\s*$")
_GEOMETRY_REF = re.compile(r"exports/([\w.-]+)/geometry\.yaml")


@dataclass
class Command:
    text: str                     # what bash runs (continuation lines kept)
    expected: list[str]           # expected output lines
    line: int                     # README line of the command


@dataclass
class Example:
    name: str
    slow: bool = False
    commands: list[Command] = field(default_factory=list)
    line: int = 0


def parse_readme(text: str) -> tuple[list[Example], list[int]]:
    """The README's examples in order, and the lines of console blocks that lack a marker."""
    examples: dict[str, Example] = {}
    unmarked: list[int] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        if lines[i].strip() != "```console":
            i += 1
            continue
        start = i
        j = i - 1
        while j >= 0 and not lines[j].strip():
            j -= 1
        marker = _MARKER.match(lines[j].strip()) if j >= 0 else None
        body = []
        i += 1
        while i < len(lines) and lines[i].strip() != "```":
            body.append((i + 1, lines[i]))
            i += 1
        i += 1
        if marker is None:
            unmarked.append(start + 1)
            continue
        name = marker["name"]
        ex = examples.setdefault(name, Example(name, line=start + 1))
        ex.slow = ex.slow or "slow" in marker["flags"].split()
        k = 0
        while k < len(body):
            lineno, ln = body[k]
            if not ln.startswith("$ "):
                raise ValueError(f"README.md:{lineno}: output before any command in example {name!r}")
            cmd = [ln[2:]]
            while cmd[-1].endswith("\\") and k + 1 < len(body):
                k += 1
                cmd.append(body[k][1])
            k += 1
            expected = []
            while k < len(body) and not body[k][1].startswith("$ "):
                expected.append(body[k][1])
                k += 1
            ex.commands.append(Command("\n".join(cmd), expected, lineno))
    return list(examples.values()), unmarked


def _compile(expected_line: str):
    """A regex for one expected line, and the numbers it compares (None for a ``~`` number)."""
    pattern, numbers, pos = [], [], 0
    for m in _TOKEN.finditer(expected_line):
        pattern.append(re.escape(expected_line[pos:m.start()]))
        pos = m.end()
        if m["ellipsis"]:
            pattern.append(".*?")
        elif m["approx"]:
            pattern.append(f"(?:{_NUM})")
        elif m["num"]:
            pattern.append(f"({_NUM})")
            numbers.append(m["num"])
        else:
            pattern.append(r"\s+")
    pattern.append(re.escape(expected_line[pos:]))
    return re.compile("".join(pattern)), numbers


def _number_ok(shown: str, actual: str) -> bool:
    a, e = float(actual), float(shown)
    mantissa = re.split("[eE]", shown)[0]
    if "." not in mantissa:
        return "." not in re.split("[eE]", actual)[0] and a == e
    decimals = len(mantissa.split(".")[1])
    unit = 10.0 ** -decimals
    if "e" in shown.lower():
        unit *= 10.0 ** int(re.split("[eE]", shown)[1])
    return abs(a - e) <= max(REL_TOL * abs(e), unit) * (1 + 1e-9)


def line_matches(expected_line: str, actual_line: str) -> bool:
    regex, numbers = _compile(expected_line.rstrip())
    m = regex.fullmatch(actual_line.rstrip())
    if m is None:
        return False
    return all(_number_ok(e, a) for e, a in zip(numbers, m.groups(), strict=True))


def output_matches(expected: list[str], actual: list[str]) -> bool:
    """Expected lines (with ``...`` lines for any number of lines) against the actual ones."""

    @functools.cache
    def match(i: int, j: int) -> bool:
        if i == len(expected):
            return j == len(actual)
        if expected[i].strip() == "...":
            return any(match(i + 1, k) for k in range(j, len(actual) + 1))
        return j < len(actual) and line_matches(expected[i], actual[j]) and match(i + 1, j + 1)

    return match(0, 0)


def _trim(lines: list[str]) -> list[str]:
    lines = [ln.rstrip() for ln in lines]
    while lines and not lines[-1]:
        lines.pop()
    return lines


def design_geometry(spec_path: Path, source: dict):
    """The geometry of a design spec through the library (no CAD)."""
    from chic_design.families import geometry_of
    from chic_design.spec import load_spec

    return geometry_of(load_spec(spec_path), source)


def _seed_geometry(work: Path, name: str) -> None:
    """``exports/NAME/geometry.yaml`` from ``designs/NAME.yaml`` without the CAD build."""
    out = work / "exports" / name / "geometry.yaml"
    spec_path = ROOT / "designs" / f"{name}.yaml"
    if out.exists() or not spec_path.exists():
        return
    from chic_register.model.geometry import write_geometry

    geometry = design_geometry(spec_path, {"spec": f"designs/{name}.yaml"})
    if geometry is None:  # the library moved: build it the slow way
        subprocess.run([str(Path(sys.executable).parent / "chic-design"), "build", f"designs/{name}.yaml",
                        "--quiet"], cwd=work, check=True, capture_output=True, timeout=COMMAND_TIMEOUT_S)
        return
    out.parent.mkdir(parents=True)
    write_geometry(geometry, out)


def _snapshot(work: Path) -> dict[str, tuple[int, int]]:
    files = {}
    for dirpath, dirnames, filenames in os.walk(work):
        dirnames[:] = [d for d in dirnames if not (Path(dirpath) / d).is_symlink()]
        for f in filenames:
            p = Path(dirpath) / f
            if p.is_symlink():
                continue
            st = p.stat()
            files[str(p.relative_to(work))] = (st.st_mtime_ns, st.st_size)
    return files


EXAMPLES, UNMARKED = parse_readme(README.read_text(encoding="utf-8"))


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    work = tmp_path_factory.mktemp("readme")
    for name in ("designs", "docs"):
        (work / name).symlink_to(ROOT / name)
    return work


def test_every_console_block_is_an_example():
    assert not UNMARKED, f"README.md: console blocks without an '<!-- example: NAME -->' line: {UNMARKED}"
    assert EXAMPLES, "README.md has no console examples"


def test_matcher_conventions():
    assert line_matches("depth 22.010 mm, 9 tubes", "depth 22.9 mm, 9 tubes")
    assert not line_matches("depth 22.010 mm, 9 tubes", "depth 23.2 mm, 9 tubes")
    assert not line_matches("9 tubes", "8 tubes") and not line_matches("9 tubes", "9.0 tubes")
    assert line_matches("D0 0.004, D1 0.003", "D0 0.005, D1 0.002")
    assert not line_matches("D0 0.004", "D0 0.006")
    assert line_matches("ok (~11.4 ms)", "ok (117.7 ms)") and line_matches("built ... in ~8.7 s", "built x in 9 s")
    assert line_matches("   0.91600      0.22994", " 0.91601  0.22994") and line_matches("-0.00000", "0.00000")
    assert output_matches(["a", "...", "z"], ["a", "b", "c", "z"]) and output_matches(["a", "...", "z"], ["a", "z"])
    assert not output_matches(["a", "z"], ["a", "b", "z"])


def _run(example: Example, work: Path) -> None:
    env = dict(os.environ, PYTHONUNBUFFERED="1", MPLBACKEND="Agg",
               PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    env.pop("VIRTUAL_ENV", None)
    for name in sorted({m for c in example.commands for m in _GEOMETRY_REF.findall(c.text)}):
        _seed_geometry(work, name)
    before = _snapshot(work)
    prefixes = sorted({f"{work}/", f"{work.resolve()}/"}, key=len, reverse=True)
    for cmd in example.commands:
        proc = subprocess.run(["bash", "-o", "pipefail", "-c", cmd.text], cwd=work, env=env, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=COMMAND_TIMEOUT_S)
        out = proc.stdout
        for p in prefixes:
            out = out.replace(p, "")
        actual, expected = _trim(out.splitlines()), _trim(cmd.expected)
        shown = "\n".join(f"    {ln}" for ln in actual)
        assert proc.returncode == 0, f"README.md:{cmd.line}: exit {proc.returncode}: $ {cmd.text}\n{shown}"
        assert output_matches(expected, actual), (
            f"README.md:{cmd.line}: the output of\n$ {cmd.text}\ndiffers from the README's.\nREADME:\n"
            + "\n".join(f"    {ln}" for ln in expected) + f"\nactual:\n{shown}")
    after = _snapshot(work)
    changed = sorted(p for p, s in before.items() if p in after and after[p] != s)
    removed = sorted(p for p in before if p not in after)
    assert not changed and not removed, (
        f"example {example.name!r} (README.md:{example.line}) changed files an earlier example wrote: "
        f"{changed + removed}")


@pytest.mark.parametrize(
    "example", [pytest.param(ex, id=ex.name, marks=[pytest.mark.slow] if ex.slow else []) for ex in EXAMPLES])
def test_readme_example(example, workspace):
    _run(example, workspace)


def test_benchmarks_file_matches_its_script():
    """docs/benchmarks.md has one section per benchmarks/report.py section, and the README names real ones."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("chic_benchmarks_report", ROOT / "benchmarks" / "report.py")
    report = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = report  # its dataclasses look their module up
    spec.loader.exec_module(report)
    text = (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8")
    sections, notes = report.split_file(text)
    assert list(sections) == [s.name for s in report.SECTIONS]
    assert notes.startswith(report.NOTES_MARKER)
    assert report.assemble(sections, notes) == text, "docs/benchmarks.md is not as report.py would write it"
    table = README.read_text(encoding="utf-8").split("## Measured figures", 1)[1].split("\n## ", 1)[0]
    named = set(re.findall(r"`([a-z_]+)`", "".join(ln.rsplit("|", 2)[-2] for ln in table.splitlines()
                                                    if ln.startswith("|") and ln.count("|") > 3)))
    unknown = named - set(report.BY_NAME)
    assert named and not unknown, f"README's figures name unknown benchmark sections: {unknown}"
