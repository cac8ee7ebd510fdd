"""Are two sets of ``chic-design build`` exports the same? Parts byte for byte, apart from dates and the version.

Usage::

    python benchmarks/check_build_equality.py BASE_DIR NEW_DIR

BASE_DIR and NEW_DIR each hold export folders (``<name>/``), as written by
``chic-design build designs/X.yaml --out DIR`` (build from the same working
directory, so the spec paths recorded in ``source`` agree). For every design
folder in BASE_DIR the same folder must exist in NEW_DIR with the same file
names, and:

- ``*.stl``: identical bytes;
- ``*.step``: identical apart from the timestamp in the ``FILE_NAME`` header;
- ``*.3mf``: identical members after unzipping (the zip's dates are ignored, and so
  are the ``UUID`` attributes, which lib3mf draws at random on every write);
- ``geometry.yaml``: identical; if the generator version differs, identical
  apart from the generator line and the hash that covers it;
- ``feasibility.json`` and ``precision.md``: identical;
- ``report.md``: identical apart from its timing table and the generator version;
- pictures (``*.png``) are compared and reported, but a difference is not a failure
  (the renderers are not bit-stable across runs).

Prints one line per difference and exits 1 if there is any, else prints a
summary and exits 0.
"""

from __future__ import annotations

import re
import sys
import zipfile
from pathlib import Path

STEP_DATE = re.compile(rb"(FILE_NAME\('[^']*',)'[^']*'")
UUID = re.compile(rb'UUID="[^"]*"')
GENERATOR = re.compile(r"chic-design \d[\w.+-]*")
INFORMATIONAL = {".png"}


def step_text(path: Path) -> bytes:
    """A STEP file with its header timestamp blanked."""
    return STEP_DATE.sub(rb"\1''", path.read_bytes(), count=1)


def zip_members(path: Path) -> dict[str, bytes]:
    """Every member of a zip (a 3MF) by name, its bytes with UUIDs blanked; dates and compression ignored."""
    with zipfile.ZipFile(path) as z:
        return {info.filename: UUID.sub(b'UUID=""', z.read(info)) for info in z.infolist()}


def geometry_text(path: Path, normalise_generator: bool) -> str:
    text = path.read_text(encoding="utf-8")
    if normalise_generator:
        text = GENERATOR.sub("chic-design VERSION", text)
        text = re.sub(r"^sha256: .*$", "sha256: (covers the generator)", text, flags=re.M)
    return text


def generator_of(path: Path) -> str | None:
    m = re.search(r"^\s*generator: (.*)$", path.read_text(encoding="utf-8"), flags=re.M)
    return m.group(1).strip() if m else None


def report_text(path: Path) -> str:
    """report.md without the rows of its timing table (``| step | seconds |``), generator version blanked."""
    out, in_timings = [], False
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("| step | seconds |"):
            in_timings = True
            out.append(line)
            continue
        if in_timings:
            if line.startswith("|"):
                continue
            in_timings = False
        out.append(line)
    return GENERATOR.sub("chic-design VERSION", "\n".join(out))


def first_difference(a: bytes | str, b: bytes | str) -> str:
    """Where two texts first differ: the line number and both lines, shortened."""
    la, lb = a.splitlines(), b.splitlines()
    for i, (x, y) in enumerate(zip(la, lb), 1):
        if x != y:
            return f"line {i}: {x[:100]!r} != {y[:100]!r}"
    return f"{len(la)} lines vs {len(lb)} lines"


def compare_file(base: Path, new: Path) -> str | None:
    """None if the two files are the same by the rules above, else what differs."""
    suffix = base.suffix.lower()
    if suffix == ".stl":
        return None if base.read_bytes() == new.read_bytes() else "bytes differ"
    if suffix == ".step":
        a, b = step_text(base), step_text(new)
        return None if a == b else f"differs beyond the header date: {first_difference(a, b)}"
    if suffix == ".3mf":
        a, b = zip_members(base), zip_members(new)
        if sorted(a) != sorted(b):
            return f"members {sorted(a)} != {sorted(b)}"
        bad = [name for name in a if a[name] != b[name]]
        return None if not bad else f"members differ: {', '.join(bad)}"
    if base.name == "geometry.yaml":
        normalise = generator_of(base) != generator_of(new)
        a, b = geometry_text(base, normalise), geometry_text(new, normalise)
        return None if a == b else first_difference(a, b)
    if base.name == "report.md":
        a, b = report_text(base), report_text(new)
        return None if a == b else first_difference(a, b)
    a, b = base.read_bytes(), new.read_bytes()
    return None if a == b else f"bytes differ: {first_difference(a, b)}"


def compare_exports(base_dir: Path, new_dir: Path) -> tuple[list[str], list[str], int]:
    """(failures, notes, files compared) for every design folder in ``base_dir``."""
    failures, notes, compared = [], [], 0
    designs = sorted(p for p in base_dir.iterdir() if p.is_dir() and not p.name.startswith("."))
    if not designs:
        failures.append(f"{base_dir}: no export folders")
    for design in designs:
        other = new_dir / design.name
        if not other.is_dir():
            failures.append(f"{other}: missing")
            continue
        names = {p.name for p in design.iterdir() if p.is_file()}
        new_names = {p.name for p in other.iterdir() if p.is_file()}
        for name in sorted(names ^ new_names):
            failures.append(f"{design.name}/{name}: only in {base_dir if name in names else new_dir}")
        for name in sorted(names & new_names):
            why = compare_file(design / name, other / name)
            compared += 1
            if why is None:
                continue
            line = f"{design.name}/{name}: {why}"
            (notes if Path(name).suffix.lower() in INFORMATIONAL else failures).append(line)
    return failures, notes, compared


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        print(__doc__.split("Usage::")[1].split("\n\n")[1].strip(), file=sys.stderr)
        return 2
    base_dir, new_dir = Path(args[0]), Path(args[1])
    for d in (base_dir, new_dir):
        if not d.is_dir():
            print(f"{d}: not a folder", file=sys.stderr)
            return 2
    failures, notes, compared = compare_exports(base_dir, new_dir)
    for line in notes:
        print(f"note (not a failure): {line}")
    for line in failures:
        print(f"DIFFERENT: {line}")
    if failures:
        return 1
    print(f"same: {compared} files in {len({p.name for p in base_dir.iterdir() if p.is_dir()})} exports")
    return 0


if __name__ == "__main__":
    sys.exit(main())
