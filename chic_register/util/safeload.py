"""Read user input files safely: regular files only, bounded size, a restricted YAML dialect.

Every file a user hands the programs (design specs, geometry files, images)
goes through :func:`read_regular_file` or :func:`open_regular_file`: the path
is opened without blocking and checked with ``fstat`` before any read, so a
FIFO, a device or a socket is refused instead of hanging the program, and a
file larger than the caller's limit is refused before it is read.

:func:`load_yaml_file` / :func:`load_yaml_text` parse the YAML of specs and
geometry files (one loader for both) with PyYAML's safe loader, narrowed so
that what a user reads is what the program reads:

- duplicate keys are an error (PyYAML keeps the last one silently);
- nesting deeper than ``MAX_DEPTH`` is an error (before Python's recursion
  limit could be reached), as are more than ``MAX_NODES`` nodes after alias
  expansion (the "billion laughs" document) and merge keys (``<<``);
- numbers are decimal: YAML 1.1 sexagesimal (``1:10`` = 70), octal
  (``010`` = 8), hexadecimal and ``1_000`` stay strings and fail the caller's
  type check; dates stay strings too;
- the tags that build non-JSON values (``!!binary``, ``!!set``, ``!!omap``,
  ``!!pairs``, ``!!timestamp``) are refused.

Failures raise :class:`~chic_register.errors.InputFileError` with a one-line
message naming the file; callers re-raise it as their own domain error.
"""

from __future__ import annotations

import os
import re
import stat
from pathlib import Path

import yaml

from chic_register.errors import InputFileError

MAX_YAML_BYTES = 1 << 18  # 256 KiB: a geometry file is a few kB, a spec < 2 kB (pure-Python parsing: ~2 s worst)
MAX_DEPTH = 32
MAX_NODES = 20_000  # values in a document, aliases expanded (a 16-tube geometry file has ~250)


def _a(what: str) -> str:
    """``what`` with its indefinite article ("an image file", "a spec file")."""
    return f"{'an' if what[:1] in 'aeiou' else 'a'} {what}"


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
                       (stat.S_ISSOCK, "a socket"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device")):
        if test(mode):
            return name
    return "not a regular file"


def open_regular_file(path, what: str = "file", max_bytes: int | None = None):
    """Open ``path`` for binary reading if it is a regular file (at most ``max_bytes``).

    The open does not block (``O_NONBLOCK``: a FIFO without a writer would
    otherwise wait forever) and the type is checked on the open descriptor,
    so a path swapped between check and read cannot slip through. Returns a
    binary file object; raises :class:`InputFileError`.
    """
    p = Path(path)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0)
    try:
        fd = os.open(p, flags)
    except FileNotFoundError:
        raise InputFileError(p, "no such file" if what in ("file", "image file") else f"no such {what}") from None
    except IsADirectoryError:
        raise InputFileError(p, f"is a directory, not {_a(what)}") from None
    except OSError as exc:
        raise InputFileError(p, f"cannot be read ({exc.strerror or exc})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise InputFileError(p, f"is {_kind(st.st_mode)}, not {_a(what)}: only regular files are read")
        if max_bytes is not None and st.st_size > max_bytes:
            raise InputFileError(p, f"is {st.st_size} bytes; {_a(what)} is at most {max_bytes} bytes")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        fh = os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise
    return fh


def read_regular_file(path, what: str = "file", max_bytes: int | None = None) -> bytes:
    """The bytes of a regular file of at most ``max_bytes``; raises :class:`InputFileError`."""
    with open_regular_file(path, what, max_bytes) as fh:
        try:
            data = fh.read() if max_bytes is None else fh.read(max_bytes + 1)
        except OSError as exc:
            raise InputFileError(path, f"cannot be read ({exc.strerror or exc})") from None
    if max_bytes is not None and len(data) > max_bytes:  # grew while we read it
        raise InputFileError(path, f"is over {max_bytes} bytes; {_a(what)} is at most {max_bytes} bytes")
    return data


# --------------------------------------------------------------------------- YAML

# Decimal numbers only; a float needs its dot (as in YAML 1.1, so that PyYAML's dumper, which quotes
# what YAML 1.1 would read as a number, never writes a string that this loader reads as one).
_INT = re.compile(r"^[-+]?(?:0|[1-9][0-9]*)$")
_FLOAT = re.compile(
    r"^(?:[-+]?(?:\.[0-9]+|[0-9]+\.[0-9]*)(?:[eE][-+]?[0-9]+)?"
    r"|[-+]?\.(?:inf|Inf|INF)|\.(?:nan|NaN|NAN))$"
)
_REFUSED_TAGS = ("binary", "set", "omap", "pairs", "timestamp")


class _Error(Exception):
    """Internal: a refused construct, with a message and a line number."""

    def __init__(self, message: str, node=None):
        line = getattr(getattr(node, "start_mark", None), "line", None)
        super().__init__(message + (f" (line {line + 1})" if line is not None else ""))


class _SafeLoader(yaml.SafeLoader):
    """SafeLoader with YAML 1.2-like scalars, no duplicate keys, bounded depth and size."""

    yaml_implicit_resolvers = {
        first: [(tag, rx) for tag, rx in resolvers
                if tag not in ("tag:yaml.org,2002:int", "tag:yaml.org,2002:float",
                               "tag:yaml.org,2002:timestamp", "tag:yaml.org,2002:merge")]
        for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
    }

    def __init__(self, stream):
        super().__init__(stream)
        self._depth = 0
        self._nodes = 0

    def compose_node(self, parent, index):
        self._depth += 1
        self._nodes += 1
        try:
            if self._depth > MAX_DEPTH:
                raise _Error(f"nested deeper than {MAX_DEPTH} levels", self.peek_event())
            if self._nodes > MAX_NODES:  # stop parsing early: the cost is in the pure-Python parser
                raise _Error(f"holds more than {MAX_NODES} values", self.peek_event())
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node, deep=False):
        if isinstance(node, yaml.MappingNode):
            seen = set()
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge" or (
                        key_node.tag == "tag:yaml.org,2002:str" and key_node.value == "<<"
                        and key_node.style is None):
                    raise _Error("merge keys (<<) are not allowed", key_node)
                if not isinstance(key_node, yaml.ScalarNode):
                    raise _Error("a mapping key must be a plain value, not a list or mapping", key_node)
                key = (key_node.tag, key_node.value)
                if key in seen:
                    raise _Error(f"duplicate key '{key_node.value}'", key_node)
                seen.add(key)
        return super().construct_mapping(node, deep=deep)


for _first in "-+0123456789.":
    _SafeLoader.add_implicit_resolver("tag:yaml.org,2002:int", _INT, list(_first))
    _SafeLoader.add_implicit_resolver("tag:yaml.org,2002:float", _FLOAT, list(_first))


def _refuse(tag: str):
    def construct(loader, node):
        raise _Error(f"the !!{tag} type is not allowed (plain numbers, strings, lists and mappings only)", node)
    return construct


for _tag in _REFUSED_TAGS:
    _SafeLoader.add_constructor(f"tag:yaml.org,2002:{_tag}", _refuse(_tag))


def _construct_int(loader, node):
    text = loader.construct_scalar(node)
    if not _INT.match(text.strip()):
        raise _Error(f"{text!r} is not an integer (YAML 1.2 form)", node)
    return int(text.strip())


def _construct_float(loader, node):
    text = loader.construct_scalar(node).strip()
    if not _FLOAT.match(text) and not _INT.match(text):
        raise _Error(f"{text!r} is not a number (YAML 1.2 form)", node)
    if _INT.match(text):
        return float(_construct_int(loader, node))
    low = text.lower()
    if low.endswith(".inf"):
        return float("-inf") if low.startswith("-") else float("inf")
    if low == ".nan":
        return float("nan")
    return float(text)


_SafeLoader.add_constructor("tag:yaml.org,2002:int", _construct_int)
_SafeLoader.add_constructor("tag:yaml.org,2002:float", _construct_float)


def _expanded_size_ok(root) -> None:
    """Refuse a node graph that expands (aliases followed) to more than MAX_NODES nodes."""
    count = 0
    stack = [root]
    while stack:
        node = stack.pop()
        count += 1
        if count > MAX_NODES:
            raise _Error(f"expands to more than {MAX_NODES} values (aliases): refused")
        if isinstance(node, yaml.SequenceNode):
            stack.extend(node.value)
        elif isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                stack.append(k)
                stack.append(v)


def load_yaml_text(text: str, path="<yaml>"):
    """Parse one YAML document with the rules of this module; raises :class:`InputFileError`."""
    loader = _SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _expanded_size_ok(node)
        return loader.construct_document(node)
    except _Error as exc:
        raise InputFileError(path, f"not accepted as YAML: {exc}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).strip().splitlines()[0]
        raise InputFileError(path, f"not valid YAML{where} ({problem})") from None
    except RecursionError:  # defensive: the depth limit comes first
        raise InputFileError(path, "not accepted as YAML: nested too deeply") from None
    finally:
        loader.dispose()


def load_yaml_file(path, what: str = "YAML file", max_bytes: int = MAX_YAML_BYTES):
    """Read a regular file of at most ``max_bytes`` and parse it (:func:`load_yaml_text`)."""
    data = read_regular_file(path, what, max_bytes)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputFileError(path, f"not UTF-8 text (byte {exc.start}): {_a(what)} is YAML text") from None
    return load_yaml_text(text, path)
