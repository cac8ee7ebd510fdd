"""Status lines on stderr, so that no command sits silent for seconds; stdout stays for results and ``--json``.

Every line starts with ``chic-design:``. :class:`Steps` times the steps of a
pipeline and shows each one while it runs.
"""

from __future__ import annotations

import sys
import time
from contextlib import contextmanager

PREFIX = "chic-design:"


def status(text: str) -> None:
    """One status line on stderr: ``chic-design: <text>``."""
    print(f"{PREFIX} {text}", file=sys.stderr, flush=True)


class Steps:
    """Times named steps; with ``show``, ``[k/N] name ...`` on stderr while a step runs, then its time.

    A failed step ends its line with ``failed``, so that the error message that
    follows starts on a line of its own.
    """

    def __init__(self, show: bool, total: int):
        self.show = show
        self.total = total
        self.timings: dict[str, float] = {}

    @contextmanager
    def step(self, name: str):
        if self.show:
            print(f"{PREFIX} [{len(self.timings) + 1}/{self.total}] {name} ...", end="", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        try:
            yield
        except BaseException:
            if self.show:
                print(" failed", file=sys.stderr, flush=True)
            raise
        dt = time.perf_counter() - t0
        self.timings[name] = dt
        if self.show:
            print(f" {dt:.2f} s", file=sys.stderr, flush=True)
