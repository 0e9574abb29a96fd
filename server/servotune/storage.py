"""SQLite storage of what must outlive the server: the last settings applied per axis.

One file (default ``~/.local/share/servotune/servotune.db``, or ``$SERVOTUNE_DATA``);
WAL mode so a reader never blocks the writer. Calls are synchronous and short; the
hub runs them in a worker thread so the event loop never waits for a disk flush.
"""

from __future__ import annotations

import json
import os
import sqlite3
import threading
import time
from pathlib import Path

SCHEMA = """
CREATE TABLE IF NOT EXISTS axis_params (
    axis_key TEXT NOT NULL,
    name TEXT NOT NULL,
    value INTEGER NOT NULL,
    updated_s REAL NOT NULL,
    PRIMARY KEY (axis_key, name)
);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
"""


def default_data_dir() -> Path:
    """``$SERVOTUNE_DATA``, else ``$XDG_DATA_HOME/servotune``, else ``~/.local/share/...``."""
    if env := os.environ.get("SERVOTUNE_DATA"):
        return Path(env)
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "servotune"


class Storage:
    """Last-known parameter values per axis, keyed by a stable axis key."""

    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._lock = threading.Lock()
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.executescript(SCHEMA)
        self._db.execute(
            "INSERT OR IGNORE INTO meta(key, value) VALUES ('schema', ?)", (json.dumps(1),)
        )

    def last_params(self, axis_key: str) -> dict[str, int]:
        with self._lock:
            rows = self._db.execute(
                "SELECT name, value FROM axis_params WHERE axis_key = ?", (axis_key,)
            ).fetchall()
        return {name: int(value) for name, value in rows}

    def save_params(self, axis_key: str, values: dict[str, int]) -> None:
        now = time.time()
        with self._lock:
            self._db.execute("BEGIN")
            try:
                self._db.executemany(
                    "INSERT INTO axis_params(axis_key, name, value, updated_s) "
                    "VALUES (?, ?, ?, ?) ON CONFLICT(axis_key, name) DO UPDATE SET "
                    "value = excluded.value, updated_s = excluded.updated_s",
                    [(axis_key, name, int(value), now) for name, value in values.items()],
                )
            except Exception:
                self._db.execute("ROLLBACK")
                raise
            self._db.execute("COMMIT")

    def close(self) -> None:
        with self._lock:
            self._db.close()
