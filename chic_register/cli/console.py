"""Where chic-register's messages go: results on stdout, notes and progress on stderr.

With --json, stdout holds only the JSON document(s); every other line (what
was written, what is being done) goes to stderr prefixed with the program name.
"""

from __future__ import annotations

import sys

PROG = "chic-register"


def note(args, text: str) -> None:
    """A line about an output ("wrote FILE"): stdout for people, stderr under --json."""
    if getattr(args, "json", False):
        print(f"{PROG}: {text}", file=sys.stderr, flush=True)
    else:
        print(text, flush=True)


def wrote(args, path, detail: str = "") -> None:
    """Report one written file: ``wrote PATH`` and an optional detail in brackets."""
    note(args, f"wrote {path}" + (f" ({detail})" if detail else ""))


def status(text: str) -> None:
    """A status line on stderr (a listening server, a step that takes a while)."""
    print(f"{PROG}: {text}", file=sys.stderr, flush=True)


def progress_bar(total: int, desc: str, unit: str):
    """A tqdm bar on stderr for a step of ``total`` units (stderr, so --json stdout stays clean)."""
    from tqdm import tqdm  # here, not at the top: only the slow commands draw a bar

    return tqdm(total=total, desc=f"{PROG}: {desc}", unit=unit, file=sys.stderr, dynamic_ncols=True)
