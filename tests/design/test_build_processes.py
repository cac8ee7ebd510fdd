"""A killed build leaves no worker process, and its temporary folders are cleaned (or an export moved aside
restored).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.conftest import ROOT


def _descendants(pid: int) -> list[int]:
    parents = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                parents[int(d.name)] = int((d / "stat").read_text().rsplit(")", 1)[1].split()[1])
            except (OSError, IndexError, ValueError):
                pass
    out, todo = [], [pid]
    while todo:
        parent = todo.pop()
        kids = [c for c, p in parents.items() if p == parent]
        out += kids
        todo += kids
    return out


def _running(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):
        return False


@pytest.mark.slow  # a real build process: its start-up (CAD imports) takes 3-20 s depending on load
@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs /proc to list child processes")
def test_a_killed_build_leaves_no_worker_and_its_temp_folder_is_cleaned(tmp_path):
    from chic_design.build import remove_stale_temporaries

    out = tmp_path / "exports"
    p = subprocess.Popen([sys.executable, "-m", "chic_design.cli", "build", "designs/neuro.yaml", "--out", str(out),
                          "--quiet"], cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    workers = []
    while time.monotonic() < deadline and p.poll() is None:
        workers = [c for c in _descendants(p.pid) if b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes()]
        if workers:
            break
        time.sleep(0.05)
    assert workers, "the build started no preview worker"
    time.sleep(0.5)
    children = _descendants(p.pid)
    p.send_signal(signal.SIGKILL)
    p.wait()
    deadline = time.monotonic() + 10
    while any(_running(c) for c in children) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not [c for c in children if _running(c)], "a child of the killed build survived"
    p.stderr.read()  # returns: no survivor holds the pipe open
    stale = list(out.glob(".neuro.tmp-*"))
    assert [s.name.split("-")[1] for s in stale] == [str(p.pid)]
    assert remove_stale_temporaries(out, "neuro") == stale
    assert not any(out.iterdir())


def test_stale_folders_of_live_owners_are_kept_and_a_moved_aside_export_is_restored(tmp_path):
    from chic_design.build import remove_stale_temporaries

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    live_tmp = tmp_path / f".neuro.tmp-{os.getpid()}-abc123"
    dead_tmp = tmp_path / f".neuro.tmp-{dead.pid}-abc123"
    dead_old = tmp_path / f".neuro.old-{dead.pid}-xyz_9"
    other = tmp_path / f".neuro2.tmp-{dead.pid}-abc123"
    for d in (live_tmp, dead_tmp, dead_old, other):
        d.mkdir()
    (dead_old / "geometry.yaml").write_text("earlier export")
    assert remove_stale_temporaries(tmp_path, "neuro") == [dead_tmp]
    assert (tmp_path / "neuro" / "geometry.yaml").read_text() == "earlier export"  # killed between renames
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([live_tmp.name, other.name, "neuro"])
