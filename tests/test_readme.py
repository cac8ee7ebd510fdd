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

Where the examples run: every example of one pytest run shares one temporary folder, as one
user's checkout would, holding links to the repository's ``designs/`` and ``docs/``; commands find
``chic-design``, ``chic-register`` and ``python`` in this interpreter's environment. Each example
writes into folders of its own: after it ran, no file that an earlier example wrote may have
changed (the test fails naming the file). An example whose commands read
``exports/NAME/geometry.yaml`` that no example built yet (a plain ``pytest`` leaves the slow
builds out) gets that file from ``designs/NAME.yaml`` through the library, without the CAD build.

Update mode: ``CHIC_README_UPDATE=1 .venv/bin/python -m pytest tests/test_readme.py -m ''`` runs the
same examples and, where a command's output no longer matches, rewrites that command's expected
output in README.md from the actual output (once, after the last example). The README's own marks
are kept: a line ``...`` stays and goes on eliding what it covers, ``...`` inside a line stays where
the text around it is still found, a number written ``~12.3`` stays a ``~`` number (with the new
value), and a shown line that still matches is left as written. Lines the README did not show and no
``...`` covers are added verbatim: mark their timings ``~`` (or elide them) by hand and review the
diff. A command that exits non-zero, or an example that changes an earlier one's files, still fails.
Without the variable (or with ``0``) the run is the strict check above and never writes.
"""

from __future__ import annotations

import difflib
import functools
import os
import re
import subprocess
import sys
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
REL_TOL = 0.05
COMMAND_TIMEOUT_S = 900
UPDATE_ENV = "CHIC_README_UPDATE"
SIMILAR = 0.6                     # update mode: a shown line this alike (0-1) to an actual one is its old form

_NUM = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?"
_TOKEN = re.compile(rf"(?P<ellipsis>\.\.\.)|~(?P<approx>{_NUM})|(?P<num>{_NUM})|(?P<space>\s+)")
_MARKER = re.compile(r"^<!--\s*example:\s*(?P<name>[\w.-]+)(?P<flags>(?:\s+\w+)*)\s*-->\s*$")
_GEOMETRY_REF = re.compile(r"exports/([\w.-]+)/geometry\.yaml")


@dataclass
class Command:
    text: str                     # what bash runs (continuation lines kept)
    expected: list[str]           # expected output lines
    line: int                     # README line of the command
    out_start: int = 0            # index (0-based) in the README's lines of the first expected line


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
        fence = i
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
            out_start = body[k][0] - 1 if k < len(body) else fence
            expected = []
            while k < len(body) and not body[k][1].startswith("$ "):
                expected.append(body[k][1])
                k += 1
            ex.commands.append(Command("\n".join(cmd), expected, lineno, out_start))
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


# ---- update mode: the README's expected output rewritten from the actual output ----

_WORD = re.compile(rf"~{_NUM}|{_NUM}|\.\.\.|\s+|\w+|[^\w\s]")


def _tokens(text: str) -> list[str]:
    return _WORD.findall(text)


def _key(token: str) -> str:
    """What a token is compared by: any number (``~`` or not) is the same, runs of spaces are one space."""
    if re.fullmatch(rf"~?{_NUM}", token):
        return "0"
    return " " if token.isspace() else token


def _similarity(expected_line: str, actual_line: str) -> float:
    a, b = [_key(t) for t in _tokens(expected_line)], [_key(t) for t in _tokens(actual_line)]
    return difflib.SequenceMatcher(None, a, b, autojunk=False).ratio() if a or b else 1.0


def updated_line(expected_line: str, actual_line: str) -> str:
    """``actual_line`` in the README's notation: the ``~`` numbers and inline ``...`` of ``expected_line`` kept.

    A line that still matches is returned as written. When only numbers (or the text an inline ``...``
    covers) changed, every number takes its actual value and the marks stay in place; when the text
    changed too, marks are carried over where the tokens around them are still found.
    """
    expected_line, actual_line = expected_line.rstrip(), actual_line.rstrip()
    if line_matches(expected_line, actual_line):
        return expected_line
    pieces, pos = [], 0  # (kind, text): None for literal text, else the _TOKEN group
    for m in _TOKEN.finditer(expected_line):
        pieces += [(None, expected_line[pos:m.start()]), (m.lastgroup, m[0])]
        pos = m.end()
    pieces.append((None, expected_line[pos:]))
    regex = {"ellipsis": "(.*?)", "space": r"(\s+)", "approx": f"({_NUM})", "num": f"({_NUM})"}
    m = re.fullmatch("".join(re.escape(t) if k is None else regex[k] for k, t in pieces), actual_line)
    if m is not None:  # the same text: numbers (and what an inline ... covers) changed
        out, values = [], iter(m.groups())
        for kind, text in pieces:
            if kind is None:
                out.append(text)
                continue
            value = next(values)
            out.append("..." if kind == "ellipsis" else f"~{value}" if kind == "approx" else value)
        new = "".join(out)
    else:  # the text changed: carry the marks over where the tokens around them are still there
        exp, act = _tokens(expected_line), _tokens(actual_line)
        matcher = difflib.SequenceMatcher(None, [_key(t) for t in exp], [_key(t) for t in act], autojunk=False)
        out = []
        for op, i1, i2, j1, j2 in matcher.get_opcodes():
            if op == "equal":
                out += [f"~{b}" if a.startswith("~") and not b.startswith("~") else b
                        for a, b in zip(exp[i1:i2], act[j1:j2], strict=True)]
            elif "..." in exp[i1:i2]:
                out.append("...")
            else:
                out += act[j1:j2]
        new = "".join(out)
    return new if line_matches(new, actual_line) else actual_line


def updated_output(expected: list[str], actual: list[str]) -> list[str]:
    """The expected lines rewritten from ``actual``: a ``...`` line stays, shown lines become the actual ones.

    The README's lines are aligned with the actual ones: first so that shown lines stay on the actual
    lines most like them (a line that still matches counts 1, one whose words are alike, numbers aside,
    its similarity when that is at least ``SIMILAR``), then at least cost: a ``...`` line covers any run
    of actual lines for free, a shown line rewritten costs less the more alike the two are (at most 2),
    an actual line added costs 1 and a shown line dropped 2 (so a shown line is rewritten rather than
    left to a neighbouring ``...``).
    """
    n, m = len(expected), len(actual)
    # cost[i][j]: (-likeness kept, cost) of aligning expected[i:] with actual[j:]; step[i][j]: the first move
    cost: list[list[tuple[float, float]]] = [[(0.0, 0.0)] * (m + 1) for _ in range(n + 1)]
    step: list[list[tuple]] = [[("", 0, 0)] * (m + 1) for _ in range(n + 1)]
    for i in range(n, -1, -1):
        for j in range(m, -1, -1):
            if i == n and j == m:
                continue
            options = []

            def add(kept: float, c: float, move: str, ni: int, nj: int) -> None:
                rest = cost[ni][nj]
                options.append(((rest[0] - kept, rest[1] + c), (move, ni, nj)))

            if i < n and expected[i].strip() == "...":
                add(0, 0.0, "skip", i + 1, j)                    # covers nothing more
                if j < m:
                    add(0, 0.0, "cover", i, j + 1)               # covers actual[j]
            elif i < n:
                add(0, 2.0, "drop", i + 1, j)
                if j < m:
                    if line_matches(expected[i], actual[j]):
                        add(1.0, 0.0, "line", i + 1, j + 1)
                    else:
                        alike = _similarity(expected[i], actual[j])
                        add(alike if alike >= SIMILAR else 0.0, 0.01 + 2.0 * (1.0 - alike), "line", i + 1, j + 1)
            if j < m:
                add(0, 1.0, "add", i, j + 1)
            cost[i][j], step[i][j] = min(options, key=lambda o: o[0])
    out, i, j = [], 0, 0
    while (i, j) != (n, m):
        move, ni, nj = step[i][j]
        if move == "skip":
            out.append(expected[i].rstrip())
        elif move == "line":
            out.append(updated_line(expected[i], actual[j]))
        elif move == "add":
            out.append(actual[j].rstrip())
        i, j = ni, nj
    return out


def update_text(text: str, replacements: dict[int, tuple[int, list[str]]]) -> str:
    """``text`` with ``replacements[start] = (count, lines)``: lines ``start..start+count`` replaced."""
    lines = text.splitlines()
    for start in sorted(replacements, reverse=True):
        count, new = replacements[start]
        lines[start:start + count] = new
    return "\n".join(lines) + ("\n" if text.endswith("\n") else "")


def _update_mode() -> bool:
    return os.environ.get(UPDATE_ENV, "") not in ("", "0")


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


README_TEXT = README.read_text(encoding="utf-8")
EXAMPLES, UNMARKED = parse_readme(README_TEXT)


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    work = tmp_path_factory.mktemp("readme")
    for name in ("designs", "docs", "tests"):
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


def test_update_mode_keeps_the_readmes_marks():
    # only numbers changed: each takes its actual value, ~ and inline ... stay
    assert (updated_line("ok (~117.7 ms: detect ~5.4), depth 22.010 mm", "ok (28.8 ms: detect 3.8), depth 23.500 mm")
            == "ok (~28.8 ms: detect ~3.8), depth 23.500 mm")
    assert updated_line("files: a, ... z, 9 files", "files: a, b, c, z, 10 files") == "files: a, ... z, 10 files"
    # the text changed: the marks go where the tokens around them still are
    assert updated_line("[1/9] spec ~0.00 s, 3 files: a, ... z", "[1/9] spec done 0.01 s, 4 files: a, b, z") == (
        "[1/9] spec done ~0.01 s, 4 files: a, ... z")
    assert updated_line("depth 22.010 mm", "depth 22.3 mm") == "depth 22.010 mm"  # still matches: as written
    # a ... line stays and covers what it covered; shown lines are rewritten, unshown ones added
    assert updated_output(["a 1", "...", "z 2"], ["new", "a 5", "b", "c", "z 2"]) == ["new", "a 5", "...", "z 2"]
    assert updated_output(["...", "z 2", "gone"], ["b", "z 3", "w"]) == ["...", "z 3", "w"]
    # a shown line that still matches stays where it is; the new lines after it are added
    assert updated_output(["a", "...", "[9/9] done", "built"],
                          ["a", "b", "[9/9] done", "wrote x", "wrote y", "built"]) == [
        "a", "...", "[9/9] done", "wrote x", "wrote y", "built"]
    # so does one that is still most like its old form
    assert updated_output(["a", "...", "[9/9] done ~0.0 s", "built"],
                          ["a", "b", "[9/9] done: 0.1 s", "wrote x y z", "built"]) == [
        "a", "...", "[9/9] done: ~0.1 s", "wrote x y z", "built"]
    assert update_text("x\ny\nz\n", {1: (1, ["Y", "Y2"]), 3: (0, ["end"])}) == "x\nY\nY2\nz\nend\n"


def test_a_wrong_readme_fails(tmp_path, monkeypatch):
    """The strict check (no CHIC_README_UPDATE) fails on a number beyond tolerance; update mode records it."""
    example = Example("wrong", commands=[Command("echo 'depth 23.2 mm, ok (12.0 ms)'",
                                                 ["depth 22.010 mm, ok (~3.1 ms)"], 1, 0)])
    monkeypatch.delenv(UPDATE_ENV, raising=False)
    assert not _update_mode()
    with pytest.raises(AssertionError, match="differs from the README's"):
        _run(example, tmp_path)
    monkeypatch.setenv(UPDATE_ENV, "0")
    assert not _update_mode()
    monkeypatch.setenv(UPDATE_ENV, "1")
    assert _update_mode()
    updates = {}
    with pytest.warns(UserWarning, match="rewritten"):
        _run(example, tmp_path, updates)
    assert updates == {0: (1, ["depth 23.2 mm, ok (~12.0 ms)"])}


def _run(example: Example, work: Path, updates: dict[int, tuple[int, list[str]]] | None = None) -> None:
    """Run ``example`` in ``work`` and compare; with ``updates`` (update mode) a differing output is
    recorded there (``updates[out_start] = (count, new lines)``) instead of failing."""
    env = dict(os.environ, PYTHONUNBUFFERED="1", MPLBACKEND="Agg", PYTHONIOENCODING="utf-8",
               PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    env.pop("VIRTUAL_ENV", None)
    for name in sorted({m for c in example.commands for m in _GEOMETRY_REF.findall(c.text)}):
        _seed_geometry(work, name)
    before = _snapshot(work)
    prefixes = sorted({f"{work}/", f"{work.resolve()}/"}, key=len, reverse=True)
    for cmd in example.commands:
        proc = subprocess.run(["bash", "-o", "pipefail", "-c", cmd.text], cwd=work, env=env, text=True, encoding="utf-8", errors="replace",
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=COMMAND_TIMEOUT_S)
        out = proc.stdout
        for p in prefixes:
            out = out.replace(p, "")
        actual, expected = _trim(out.splitlines()), _trim(cmd.expected)
        shown = "\n".join(f"    {ln}" for ln in actual)
        assert proc.returncode == 0, f"README.md:{cmd.line}: exit {proc.returncode}: $ {cmd.text}\n{shown}"
        if updates is not None and not output_matches(expected, actual):
            new = updated_output(expected, actual)
            assert output_matches(new, actual), f"README.md:{cmd.line}: no README form of the output of\n{shown}"
            updates[cmd.out_start] = (len(cmd.expected), new)
            warnings.warn(f"README.md:{cmd.line}: the expected output of $ {cmd.text.splitlines()[0]} "
                          f"rewritten ({len(cmd.expected)} lines -> {len(new)})", stacklevel=1)
            continue
        assert output_matches(expected, actual), (
            f"README.md:{cmd.line}: the output of\n$ {cmd.text}\ndiffers from the README's.\nREADME:\n"
            + "\n".join(f"    {ln}" for ln in expected) + f"\nactual:\n{shown}")
    after = _snapshot(work)
    changed = sorted(p for p, s in before.items() if p in after and after[p] != s)
    removed = sorted(p for p in before if p not in after)
    assert not changed and not removed, (
        f"example {example.name!r} (README.md:{example.line}) changed files an earlier example wrote: "
        f"{changed + removed}")


@pytest.fixture(scope="module")
def readme_updates():
    """Update mode (``CHIC_README_UPDATE=1``): the outputs to rewrite, written into README.md after the
    last example; ``None`` (the strict check) otherwise."""
    if not _update_mode():
        yield None
        return
    updates: dict[int, tuple[int, list[str]]] = {}
    yield updates
    if updates:
        text = README.read_text(encoding="utf-8")
        if text != README_TEXT:
            pytest.fail("README.md changed while its examples ran: not updated; run the update again")
        README.write_text(update_text(text, updates), encoding="utf-8")


@pytest.mark.parametrize(
    "example", [pytest.param(ex, id=ex.name, marks=[pytest.mark.slow] if ex.slow else []) for ex in EXAMPLES])
def test_readme_example(example, workspace, readme_updates):
    _run(example, workspace, readme_updates)


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
