"""Freed heap memory goes back to the OS: a process that churns through many small arrays shrinks again."""

from __future__ import annotations

import os
import platform
from pathlib import Path

import numpy as np
import pytest

from chic_register.util.memory import release_freed_memory


def _rss_mib() -> float:
    for line in Path(f"/proc/{os.getpid()}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise AssertionError("no VmRSS")


@pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc", reason="glibc only")
def test_freed_small_blocks_are_returned_after_a_trim():
    release_freed_memory()
    before = _rss_mib()
    keep = [np.ones(4000) for _ in range(20000)]  # 20000 blocks of 32 KB, below mmap's threshold: on the heap
    del keep[:-1]  # all but the last freed: the heap's top stays in use, so free() cannot shrink it
    assert _rss_mib() - before > 300  # the allocator kept the freed pages
    assert release_freed_memory()
    assert _rss_mib() - before < 100
