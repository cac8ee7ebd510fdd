"""Binary STL files that declare their coordinate system (``SPACE=LPS``), for 3D Slicer.

Every model this project exports is written in a frame of its own (F, the
tool frame) and read by Slicer as LPS (docs/interfaces.md section 5).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from chic_register.io.transforms import MODEL_SPACE
from chic_register.util.atomic import write_bytes

HEADER_BYTES = 80


def stl_header(space: str = MODEL_SPACE) -> bytes:
    """The 80-byte binary STL header declaring ``space`` (Slicer reads ``SPACE=...``)."""
    text = f"SPACE={space} chic: frame F (or tool) in mm, read as {space}; see docs/interfaces.md".encode("ascii")
    return text[:HEADER_BYTES].ljust(HEADER_BYTES, b" ")


def stl_bytes(vertices_mm, triangles, space: str = MODEL_SPACE) -> bytes:
    """A binary STL of ``triangles`` (M, 3) indexing ``vertices_mm`` (N, 3), with facet normals."""
    v = np.asarray(vertices_mm, dtype=float)
    tri = v[np.asarray(triangles, dtype=np.int64)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    rec = np.zeros(len(tri), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    rec["n"], rec["v"] = n, tri
    return stl_header(space) + np.uint32(len(tri)).tobytes() + rec.tobytes()


def write_stl(path, vertices_mm, triangles, space: str = MODEL_SPACE) -> Path:
    """Write a binary STL atomically (see :func:`stl_bytes`)."""
    return write_bytes(path, stl_bytes(vertices_mm, triangles, space))


def declare_space(path, space: str = MODEL_SPACE) -> Path:
    """Rewrite the 80 header bytes of the binary STL at ``path`` in place to declare ``space``.

    Used by ``chic-design build`` on every part (Slicer 4.11+ reads an STL
    without ``SPACE=`` as LPS, older versions as RAS: saying it removes the
    doubt). The triangles are untouched; a file that is not a binary STL
    (size not 84 + 50 bytes per triangle) is refused with ValueError.
    """
    path = Path(path)
    with open(path, "r+b") as f:
        head = f.read(HEADER_BYTES + 4)
        if len(head) < HEADER_BYTES + 4:
            raise ValueError(f"{path}: not a binary STL file (shorter than its header)")
        n = int.from_bytes(head[HEADER_BYTES:], "little")
        if path.stat().st_size != HEADER_BYTES + 4 + 50 * n:
            raise ValueError(f"{path}: not a binary STL file (size does not match {n} triangles)")
        f.seek(0)
        f.write(stl_header(space))
    return path
