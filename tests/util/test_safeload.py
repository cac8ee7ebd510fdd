"""The shared input loader: regular files only, bounded size, a YAML dialect without surprises."""

from __future__ import annotations

import os
import time

import pytest

from chic_register.errors import InputFileError
from chic_register.util.safeload import (
    MAX_DEPTH,
    load_yaml_file,
    load_yaml_text,
    read_regular_file,
)


@pytest.mark.parametrize("text, value", [
    ("a: 1:10", "1:10"),          # YAML 1.1 would read 70
    ("a: 190:20:30.15", "190:20:30.15"),
    ("a: 010", "010"),            # YAML 1.1 would read 8
    ("a: 0x1F", "0x1F"),
    ("a: 1_000", "1_000"),
    ("a: 2024-01-02", "2024-01-02"),  # a date stays text, so it can never break JSON
    ("a: 1.5", 1.5),
    ("a: -3", -3),
    ("a: 2.0e-05", 2.0e-05),
    ("a: .5", 0.5),
])
def test_scalars_read_as_written(text, value):
    got = load_yaml_text(text)["a"]
    assert got == value and type(got) is type(value)


@pytest.mark.parametrize("text, fragment", [
    ("a: 1\nb: 2\na: 3", "duplicate key 'a' (line 3)"),
    ("a: !!binary aGVsbG8=", "!!binary"),
    ("a: !!set {x, y}", "!!set"),
    ("a: !!timestamp 2024-01-02", "!!timestamp"),
    ("a: !!omap [x: 1]", "!!omap"),
    ("b: &x {c: 1}\na:\n  <<: *x", "merge keys"),
    ("a: !!python/object:os.system x", "not valid YAML"),
    ("a: [1, 2", "not valid YAML"),
    ("{[1]: 2}", "plain value"),
])
def test_refused_constructs_are_one_line_errors(text, fragment):
    with pytest.raises(InputFileError) as err:
        load_yaml_text(text, "f.yaml")
    msg = str(err.value)
    assert msg.startswith("f.yaml: ") and "\n" not in msg and fragment in msg


def test_billion_laughs_is_refused_quickly():
    text = "a: &a [x, x, x, x, x, x, x, x, x]\n" + "".join(
        f"{chr(98 + i)}: &{chr(98 + i)} [" + ", ".join(["*" + chr(97 + i)] * 9) + "]\n" for i in range(9))
    t0 = time.process_time()
    with pytest.raises(InputFileError, match="expands to more than"):
        load_yaml_text(text)
    assert time.process_time() - t0 < 2.0
    # a few aliases are fine: they are ordinary YAML
    assert load_yaml_text("x: &p [1, 2]\ny: *p") == {"x": [1, 2], "y": [1, 2]}


@pytest.mark.parametrize("text", [
    "a: " + "[" * 5000 + "]" * 5000,
    "a: " + "{b: " * 5000 + "1" + "}" * 5000,
    "".join(" " * i + f"k{i}:\n" for i in range(2000)),
])
def test_deep_nesting_is_refused_not_a_recursion_error(text):
    with pytest.raises(InputFileError, match=f"nested deeper than {MAX_DEPTH} levels"):
        load_yaml_text(text)


def test_only_small_regular_files_are_read(tmp_path):
    fifo = tmp_path / "pipe.yaml"
    os.mkfifo(fifo)
    t0 = time.monotonic()
    with pytest.raises(InputFileError, match="is a FIFO .named pipe., not a spec file"):
        load_yaml_file(fifo, "spec file")  # would block forever in open() without O_NONBLOCK
    assert time.monotonic() - t0 < 5.0
    with pytest.raises(InputFileError, match="is a directory"):
        load_yaml_file(tmp_path, "spec file")
    with pytest.raises(InputFileError, match="no such spec file"):
        load_yaml_file(tmp_path / "missing.yaml", "spec file")
    big = tmp_path / "big.yaml"
    big.write_bytes(b"a: 1\n" + b"# " + b"x" * (2 << 20) + b"\n")
    with pytest.raises(InputFileError, match="is 2097160 bytes; a spec file is at most 262144 bytes"):
        load_yaml_file(big, "spec file")
    latin = tmp_path / "latin.yaml"
    latin.write_bytes(b"name: caf\xe9\n")
    with pytest.raises(InputFileError, match="not UTF-8 text"):
        load_yaml_file(latin)
    assert read_regular_file(latin, max_bytes=100) == b"name: caf\xe9\n"


def test_a_document_with_too_many_values_is_refused_while_parsing():
    t0 = time.process_time()
    with pytest.raises(InputFileError, match="holds more than 20000 values"):
        load_yaml_text("a: [" + ",".join(["1"] * 100_000) + "]")
    assert time.process_time() - t0 < 5.0
