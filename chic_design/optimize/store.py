"""Finished candidates in SQLite, keyed by a hash of their parameters: a rerun never recomputes them.

One row per candidate key (see :func:`.space.candidate_key`), the result as
JSON. Each result is committed as soon as it arrives, so a run killed midway
keeps every candidate finished before the kill. Only the driver process
writes.
"""

from __future__ import annotations

import json
import sqlite3
from pathlib import Path

_SCHEMA = """CREATE TABLE IF NOT EXISTS candidates (
    key TEXT PRIMARY KEY, params TEXT NOT NULL, result TEXT NOT NULL,
    created REAL NOT NULL DEFAULT (julianday('now')))"""


class ResultStore:
    """A SQLite file of finished candidates (``path``), or an in-memory one (``path=None``)."""

    def __init__(self, path=None):
        self.path = None if path is None else Path(path)
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(":memory:" if self.path is None else str(self.path), timeout=30.0)
        self._db.execute("PRAGMA journal_mode=WAL" if self.path is not None else "PRAGMA journal_mode=MEMORY")
        self._db.execute(_SCHEMA)
        self._db.commit()

    def get_many(self, keys) -> dict[str, dict]:
        """Stored results of those ``keys`` that are stored."""
        keys = list(dict.fromkeys(keys))
        out = {}
        for i in range(0, len(keys), 500):
            chunk = keys[i:i + 500]
            rows = self._db.execute(
                f"SELECT key, result FROM candidates WHERE key IN ({','.join('?' * len(chunk))})", chunk)
            out.update((k, json.loads(r)) for k, r in rows)
        return out

    def put(self, key: str, params: dict, result: dict) -> None:
        """Store one finished candidate (committed at once)."""
        self._db.execute("INSERT OR REPLACE INTO candidates (key, params, result) VALUES (?, ?, ?)",
                         (key, json.dumps(params, sort_keys=True), json.dumps(result)))
        self._db.commit()

    def __len__(self) -> int:
        return int(self._db.execute("SELECT COUNT(*) FROM candidates").fetchone()[0])

    def close(self) -> None:
        self._db.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
