"""Atomic export folders: a build writes into a temporary folder and swaps it in with one rename.

Temporary folders carry the owner's pid (``.<name>.tmp-<pid>-<random>``), so
a later build can tell the leftovers of a build that was killed hard from
those of one running now.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from pathlib import Path

TMP_PREFIX = ".{name}.tmp-"  # + "<owner pid>-<random>"
OLD_PREFIX = ".{name}.old-"
_OWNER = re.compile(r"^(\d+)-[A-Za-z0-9_]+$")  # owner pid, then mkdtemp's random letters


def default_permissions(folder: Path) -> None:
    """mkdtemp/mkstemp make private (0700/0600) entries; give the export the usual umask modes."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(folder, 0o777 & ~umask)
    for path in folder.iterdir():
        if path.is_file():
            os.chmod(path, 0o666 & ~umask)


def _pid_alive(pid: int) -> bool:
    """True when a process ``pid`` exists (also when it belongs to another user)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale_temporaries(out_root, name: str) -> list[Path]:
    """Remove the temporary folders of earlier builds of ``name`` whose owner process is dead.

    A build killed hard (SIGKILL, power loss) cannot clean up. Its
    ``.<name>.tmp-<pid>-*`` folder is removed here; a ``.<name>.old-<pid>-*``
    folder (the previous export, moved aside just before the final rename) is
    renamed back to ``<name>`` if that is missing, else removed. Folders of a
    live process (a build running now) are left alone. Returns what was removed.
    """
    out_root = Path(out_root)
    removed = []
    try:
        entries = sorted(out_root.iterdir(), key=lambda p: p.stat().st_mtime if p.exists() else 0.0)
    except OSError:
        return removed
    for path in entries:
        for prefix in (TMP_PREFIX.format(name=name), OLD_PREFIX.format(name=name)):
            if not path.name.startswith(prefix) or not path.is_dir():
                continue
            m = _OWNER.match(path.name[len(prefix):])
            if m is None or _pid_alive(int(m.group(1))):
                continue
            final = out_root / name
            if prefix.endswith(".old-") and not final.exists():
                os.rename(path, final)  # the kill came between the two renames: restore the export
            else:
                shutil.rmtree(path, ignore_errors=True)
                removed.append(path)
    return removed


def owned_mkdtemp(prefix: str, parent: Path) -> Path:
    """``mkdtemp`` with this process's pid in the name, so a later build can tell a stale folder."""
    return Path(tempfile.mkdtemp(prefix=f"{prefix}{os.getpid()}-", dir=parent))


def replace_folder(tmp: Path, final: Path) -> None:
    """Put ``tmp`` at ``final``: move an old ``final`` aside, rename ``tmp`` in, delete the old one."""
    old = None
    if final.exists():
        old = owned_mkdtemp(OLD_PREFIX.format(name=final.name), final.parent)
        os.rmdir(old)
        os.rename(final, old)
    try:
        os.rename(tmp, final)
    except BaseException:
        if old is not None:
            os.rename(old, final)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
