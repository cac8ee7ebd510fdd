"""Atomic file output: write beside the target, then rename, so nobody ever sees half a file.

Used by every writer in the project (geometry files, images, DICOM, volumes,
transforms, plots, JSON, scenes): a failed or interrupted write leaves the
earlier file untouched and no temporary behind.

Two rules every output follows:

- the file gets the permissions an ordinary ``open()`` would give it
  (``0o666`` less the process umask), not ``mkstemp``'s private ``0o600``;
- the folder it goes into must exist: a missing parent folder is the user's
  typo more often than a wish, so it is an :class:`OutputError` naming the
  folder, never silently created.
"""

from __future__ import annotations

import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from chic_register.errors import OutputError


def current_umask() -> int:
    """The process umask (read by setting it and putting it back: there is no getter)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def check_parent(path) -> Path:
    """``path`` as a Path whose parent folder exists; else :class:`OutputError`."""
    path = Path(path)
    parent = path.parent
    if not parent.is_dir():
        what = "is not a folder" if parent.exists() else "does not exist"
        raise OutputError(f"{path}: the folder {parent} {what} (create it first)")
    return path


@contextmanager
def atomic_path(path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``, else delete it.

    ``suffix`` (default: ``path``'s own suffix) ends the temporary name, for
    writers that choose the format from the file name. The parent folder must
    exist (:class:`OutputError` otherwise); the final file has mode
    ``0o666 & ~umask``.
    """
    path = check_parent(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}-", suffix=path.suffix if suffix is None else suffix,
                               dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        if Path(tmp).is_file():
            os.chmod(tmp, 0o666 & ~current_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_text(path, text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_json(path, doc) -> Path:
    """Write ``doc`` as indented JSON (with a final newline) to ``path`` atomically."""
    return write_text(path, json.dumps(doc, indent=2) + "\n")


def save_figure(fig, path, dpi: int = 110) -> Path:
    """Save a matplotlib figure to ``path`` as PNG atomically, then close it (also on failure)."""
    import matplotlib.pyplot as plt  # deferred: loads matplotlib only when used (one-shot start-up)

    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format="png")
    finally:
        plt.close(fig)
    return Path(path)
