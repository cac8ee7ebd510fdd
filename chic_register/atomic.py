"""Atomic file output: write beside the target, then rename, so nobody ever sees half a file.

Used by every writer in the project (geometry files, images, DICOM, volumes,
transforms, plots, JSON): a failed or interrupted write leaves the earlier
file untouched and no temporary behind.
"""

from __future__ import annotations

import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator


@contextmanager
def atomic_path(path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``, else delete it.

    ``suffix`` (default: ``path``'s own suffix) ends the temporary name, for
    writers that choose the format from the file name.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}-", suffix=path.suffix if suffix is None else suffix,
                               dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_text(path, text: str) -> Path:
    """Write UTF-8 ``text`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


def write_json(path, doc) -> Path:
    """Write ``doc`` as indented JSON (with a final newline) to ``path`` atomically."""
    return write_text(path, json.dumps(doc, indent=2) + "\n")
