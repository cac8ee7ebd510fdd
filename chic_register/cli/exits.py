"""How both command-line programs end on a failure: one line on stderr, or quietly on a closed pipe.

Shared by ``chic-design`` and ``chic-register`` so their ``main`` functions
treat OS errors and a vanished reader (``chic-design schema | head``) alike.
"""

from __future__ import annotations

import os
import sys

SIGPIPE_EXIT = 141  # what a shell reports for a process ended by SIGPIPE (128 + 13)


def report(prog: str, text: str, code: int) -> int:
    """Print ``<prog>: <text>`` on stderr (if stderr is still there) and return ``code``."""
    try:
        print(f"{prog}: {text}", file=sys.stderr)
    except (BrokenPipeError, OSError):
        pass
    return code


def os_error(prog: str, exc: OSError) -> int:
    """An output that could not be written (disk full, permission, vanished folder): one line, exit 1."""
    where = f"{exc.filename}: " if exc.filename else ""
    return report(prog, f"error: {where}{exc.strerror or exc}", 1)


def broken_pipe() -> int:
    """The reader left: point stdout at /dev/null (so the interpreter's last flush cannot fail) and exit 141."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):
        pass
    return SIGPIPE_EXIT
