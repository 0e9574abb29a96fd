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
from typing import Any

SCHEMA = """
CREATE TABLE IF NOT EXISTS axis_params (
    axis_key TEXT NOT NULL,
    name TEXT NOT NULL,
    value INTEGER NOT NULL,
    updated_s REAL NOT NULL,
    PRIMARY KEY (axis_key, name)
);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS runs (
    id TEXT PRIMARY KEY,
    axis_key TEXT NOT NULL,
    axis_id TEXT NOT NULL,
    created_s REAL NOT NULL,
    status TEXT NOT NULL,
    baseline INTEGER NOT NULL DEFAULT 0,
    meta TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS runs_by_axis ON runs (axis_key, created_s);
CREATE TABLE IF NOT EXISTS param_sets (
    axis_key TEXT NOT NULL,
    name TEXT NOT NULL,
    created_s REAL NOT NULL,
    device TEXT NOT NULL,
    params TEXT NOT NULL,
    note TEXT NOT NULL DEFAULT '',
    PRIMARY KEY (axis_key, name)
);
CREATE TABLE IF NOT EXISTS run_chunks (
    run_id TEXT NOT NULL REFERENCES runs (id) ON DELETE CASCADE,
    seq INTEGER NOT NULL,
    samples TEXT NOT NULL,
    PRIMARY KEY (run_id, seq)
);
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
        self._db.execute("PRAGMA foreign_keys=ON")
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

    # --- parameter sets ----------------------------------------------------------------

    def save_param_set(
        self, axis_key: str, name: str, device: str, params: dict[str, int], note: str
    ) -> None:
        with self._lock:
            self._db.execute(
                "INSERT INTO param_sets(axis_key, name, created_s, device, params, note) "
                "VALUES (?, ?, ?, ?, ?, ?) ON CONFLICT(axis_key, name) DO UPDATE SET "
                "created_s = excluded.created_s, params = excluded.params, note = excluded.note",
                (axis_key, name, time.time(), device, json.dumps(params), note),
            )

    def list_param_sets(self, axis_key: str) -> list[dict[str, Any]]:
        with self._lock:
            rows = self._db.execute(
                "SELECT name, created_s, device, params, note FROM param_sets "
                "WHERE axis_key = ? ORDER BY created_s",
                (axis_key,),
            ).fetchall()
        return [
            {"name": n, "created_s": c, "device": d, "params": json.loads(p), "note": note}
            for n, c, d, p, note in rows
        ]

    def delete_param_set(self, axis_key: str, name: str) -> bool:
        with self._lock:
            cursor = self._db.execute(
                "DELETE FROM param_sets WHERE axis_key = ? AND name = ?", (axis_key, name)
            )
            return cursor.rowcount > 0

    def get_meta(self, key: str) -> Any:
        with self._lock:
            row = self._db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else json.loads(row[0])

    def set_meta(self, key: str, value: Any) -> None:
        with self._lock:
            self._db.execute(
                "INSERT INTO meta(key, value) VALUES (?, ?) "
                "ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                (key, json.dumps(value)),
            )

    # --- runs of the test bench -------------------------------------------------------
    # A run's row is written when the test starts; its samples follow in chunks while
    # it records, so a link loss or a server crash keeps everything recorded so far.

    def create_run(
        self, run_id: str, axis_key: str, axis_id: str, created_s: float, meta: dict[str, Any]
    ) -> None:
        with self._lock:
            self._db.execute(
                "INSERT INTO runs(id, axis_key, axis_id, created_s, status, meta) "
                "VALUES (?, ?, ?, ?, 'recording', ?)",
                (run_id, axis_key, axis_id, created_s, json.dumps(meta)),
            )

    def append_samples(self, run_id: str, seq: int, samples: list[list[Any]]) -> None:
        with self._lock:
            self._db.execute(
                "INSERT INTO run_chunks(run_id, seq, samples) VALUES (?, ?, ?)",
                (run_id, seq, json.dumps(samples)),
            )

    def finish_run(self, run_id: str, status: str, meta: dict[str, Any]) -> None:
        with self._lock:
            self._db.execute(
                "UPDATE runs SET status = ?, meta = ? WHERE id = ?",
                (status, json.dumps(meta), run_id),
            )

    def set_baseline(self, run_id: str) -> bool:
        """Mark ``run_id`` as the baseline of its axis (and no other run of it)."""
        with self._lock:
            row = self._db.execute("SELECT axis_key FROM runs WHERE id = ?", (run_id,)).fetchone()
            if row is None:
                return False
            self._db.execute("BEGIN")
            self._db.execute("UPDATE runs SET baseline = 0 WHERE axis_key = ?", (row[0],))
            self._db.execute("UPDATE runs SET baseline = 1 WHERE id = ?", (run_id,))
            self._db.execute("COMMIT")
            return True

    def delete_run(self, run_id: str) -> bool:
        with self._lock:
            cursor = self._db.execute("DELETE FROM runs WHERE id = ?", (run_id,))
            return cursor.rowcount > 0

    def list_runs(self, axis_key: str) -> list[dict[str, Any]]:
        with self._lock:
            rows = self._db.execute(
                "SELECT id, axis_id, created_s, status, baseline, meta FROM runs "
                "WHERE axis_key = ? ORDER BY created_s",
                (axis_key,),
            ).fetchall()
        return [_run_row(row) for row in rows]

    def get_run(self, run_id: str) -> dict[str, Any] | None:
        with self._lock:
            row = self._db.execute(
                "SELECT id, axis_id, created_s, status, baseline, meta FROM runs WHERE id = ?",
                (run_id,),
            ).fetchone()
            if row is None:
                return None
            chunks = self._db.execute(
                "SELECT samples FROM run_chunks WHERE run_id = ? ORDER BY seq", (run_id,)
            ).fetchall()
        run = _run_row(row)
        run["samples"] = [sample for (chunk,) in chunks for sample in json.loads(chunk)]
        return run

    def mark_interrupted_runs(self) -> int:
        """At start-up: runs still 'recording' were cut off by a crash: incomplete."""
        with self._lock:
            cursor = self._db.execute(
                "UPDATE runs SET status = 'incomplete' WHERE status = 'recording'"
            )
            return cursor.rowcount

    def close(self) -> None:
        with self._lock:
            self._db.close()


def _run_row(row: tuple[Any, ...]) -> dict[str, Any]:
    run_id, axis_id, created_s, status, baseline, meta = row
    return {
        "id": run_id,
        "axis_id": axis_id,
        "created_s": created_s,
        "status": status,
        "baseline": bool(baseline),
        **json.loads(meta),
    }
