"""SQLite storage of what must outlive the server: settings, parameter sets, bench runs.

One file (default ``~/.local/share/servotune/servotune.db``, or ``$SERVOTUNE_DATA``);
WAL mode so a reader never blocks the writer. Calls are synchronous and short; callers
run them in a worker thread so the event loop never waits for a disk flush.

Failures are never silent: every SQLite error of a write is raised as
``StorageError`` (the API answers 507 with the reason, the hub raises an event and a
"settings are not being saved" banner). A database that cannot be opened for writing
at start-up (read-only directory or file, full disk) is opened read-only, or in
memory if it cannot be read either, and ``Storage.problem`` says why: the server
still runs, nothing is written, and every write answers ``StorageError``.

JSON written here is strict: NaN and infinities are refused (``StorageError``), and
JSON read back is cleaned (non-finite numbers become null), so a value stored by an
older version can never make a run unreadable.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import sqlite3
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from servotune.private_files import private_dir, private_file

logger = logging.getLogger(__name__)


class StorageError(RuntimeError):
    """A write to the database failed (read-only, full disk, ...): nothing was saved."""


def clean_json(value: Any) -> Any:
    """``value`` with every non-finite float replaced by None (recursively)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: clean_json(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [clean_json(v) for v in value]
    return value


def dumps_strict(value: Any) -> str:
    """JSON text of ``value``; StorageError for NaN or an infinity anywhere in it."""
    try:
        return json.dumps(value, allow_nan=False, separators=(",", ":"))
    except ValueError as exc:
        raise StorageError(f"not stored: a number is not finite ({exc})") from None


def loads_clean(text: str) -> Any:
    """Parse stored JSON; NaN, Infinity and overflowing numbers (1e400) come back None."""
    return clean_json(json.loads(text))


# Tokens a stored chunk may hold that are not valid JSON, or overflow a double.
_UNSAFE_JSON = re.compile(r"NaN|Infinity|[eE]\+?\d{3,}")

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
    """Settings, parameter sets and bench runs per axis, keyed by a stable axis key.

    ``problem`` is None while the database is writable, else why it is not (set at
    start-up or by the first failing write, cleared by the next write that works).
    """

    def __init__(self, path: Path) -> None:
        self.path = path
        self._lock = threading.Lock()
        self.problem: str | None = None
        # axis key -> values applied to a device but not saved yet (see save_params)
        self.unsaved: dict[str, dict[str, int]] = {}
        try:
            private_dir(path.parent)
            private_file(path)
            self._db = self._open_writable(path)
        except (OSError, sqlite3.Error) as exc:
            self.problem = f"the database {path} cannot be written ({exc})"
            logger.error("settings are not being saved: %s", self.problem)
            self._db = self._open_fallback(path)

    @staticmethod
    def _open_writable(path: Path) -> sqlite3.Connection:
        db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        try:
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=NORMAL")
            db.execute("PRAGMA foreign_keys=ON")
            db.executescript(SCHEMA)
            db.execute(
                "INSERT OR IGNORE INTO meta(key, value) VALUES ('schema', ?)", (json.dumps(1),)
            )
            # A read-only file can pass the statements above when nothing changes:
            # prove that a write works.
            db.execute(
                "INSERT INTO meta(key, value) VALUES ('opened_s', ?) "
                "ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                (json.dumps(time.time()),),
            )
        except sqlite3.Error:
            db.close()
            raise
        return db

    @staticmethod
    def _open_fallback(path: Path) -> sqlite3.Connection:
        """Read-only view of an existing database, else an empty one in memory."""
        if path.exists():
            try:
                db = sqlite3.connect(
                    f"file:{path}?mode=ro", uri=True, check_same_thread=False, isolation_level=None
                )
                db.execute("SELECT count(*) FROM runs").fetchone()
                return db
            except sqlite3.Error as exc:
                logger.error("cannot read %s either (%s): nothing stored is shown", path, exc)
        db = sqlite3.connect(":memory:", check_same_thread=False, isolation_level=None)
        db.executescript(SCHEMA)
        # Writes must fail loudly, not vanish into memory.
        db.execute("PRAGMA query_only=ON")
        return db

    def _write(self, sql: str, args: tuple[Any, ...] = ()) -> sqlite3.Cursor:
        """One write statement under the lock held by the caller; StorageError on failure."""
        try:
            cursor = self._db.execute(sql, args)
        except sqlite3.Error as exc:
            raise self._failed(exc) from None
        self.problem = None
        return cursor

    def _failed(self, exc: sqlite3.Error) -> StorageError:
        self.problem = f"the database {self.path} cannot be written ({exc})"
        return StorageError(f"not saved: {self.problem}")

    def last_params(self, axis_key: str) -> dict[str, int]:
        with self._lock:
            rows = self._db.execute(
                "SELECT name, value FROM axis_params WHERE axis_key = ?", (axis_key,)
            ).fetchall()
        return {name: int(value) for name, value in rows}

    def save_params(self, axis_key: str, values: dict[str, int]) -> None:
        """Store the last applied values; StorageError if the database cannot be written.

        Values that could not be saved are kept in memory and written with the next
        save of the same axis that works (``unsaved`` lists them meanwhile)."""
        now = time.time()
        with self._lock:
            values = {**self.unsaved.get(axis_key, {}), **values}
            self.unsaved[axis_key] = values
            try:
                self._db.execute("BEGIN")
                try:
                    self._db.executemany(
                        "INSERT INTO axis_params(axis_key, name, value, updated_s) "
                        "VALUES (?, ?, ?, ?) ON CONFLICT(axis_key, name) DO UPDATE SET "
                        "value = excluded.value, updated_s = excluded.updated_s",
                        [(axis_key, name, int(value), now) for name, value in values.items()],
                    )
                    self._db.execute("COMMIT")
                except BaseException:
                    if self._db.in_transaction:
                        self._db.execute("ROLLBACK")
                    raise
            except sqlite3.Error as exc:
                raise self._failed(exc) from None
            self.unsaved.pop(axis_key, None)
            self.problem = None

    # --- parameter sets ----------------------------------------------------------------

    def save_param_set(
        self, axis_key: str, name: str, device: str, params: dict[str, int], note: str
    ) -> None:
        text = dumps_strict(params)
        with self._lock:
            self._write(
                "INSERT INTO param_sets(axis_key, name, created_s, device, params, note) "
                "VALUES (?, ?, ?, ?, ?, ?) ON CONFLICT(axis_key, name) DO UPDATE SET "
                "created_s = excluded.created_s, params = excluded.params, note = excluded.note",
                (axis_key, name, time.time(), device, text, note),
            )

    def list_param_sets(self, axis_key: str) -> list[dict[str, Any]]:
        with self._lock:
            rows = self._db.execute(
                "SELECT name, created_s, device, params, note FROM param_sets "
                "WHERE axis_key = ? ORDER BY created_s",
                (axis_key,),
            ).fetchall()
        return [
            {"name": n, "created_s": c, "device": d, "params": loads_clean(p), "note": note}
            for n, c, d, p, note in rows
        ]

    def delete_param_set(self, axis_key: str, name: str) -> bool:
        with self._lock:
            cursor = self._write(
                "DELETE FROM param_sets WHERE axis_key = ? AND name = ?", (axis_key, name)
            )
            return cursor.rowcount > 0

    def get_meta(self, key: str) -> Any:
        with self._lock:
            row = self._db.execute("SELECT value FROM meta WHERE key = ?", (key,)).fetchone()
        return None if row is None else loads_clean(row[0])

    def set_meta(self, key: str, value: Any) -> None:
        text = dumps_strict(value)
        with self._lock:
            self._write(
                "INSERT INTO meta(key, value) VALUES (?, ?) "
                "ON CONFLICT(key) DO UPDATE SET value = excluded.value",
                (key, text),
            )

    # --- runs of the test bench -------------------------------------------------------
    # A run's row is written when the test starts; its samples follow in chunks while
    # it records, so a link loss or a server crash keeps everything recorded so far.

    def create_run(
        self, run_id: str, axis_key: str, axis_id: str, created_s: float, meta: dict[str, Any]
    ) -> None:
        text = dumps_strict(meta)
        with self._lock:
            self._write(
                "INSERT INTO runs(id, axis_key, axis_id, created_s, status, meta) "
                "VALUES (?, ?, ?, ?, 'recording', ?)",
                (run_id, axis_key, axis_id, created_s, text),
            )

    def append_samples(self, run_id: str, seq: int, samples: list[list[Any]]) -> None:
        # Non-finite values become null: a sample row is a measurement, and the
        # rows must stay valid JSON for the verbatim streaming in iter_run_json.
        text = dumps_strict(clean_json(samples))
        with self._lock:
            self._write(
                "INSERT INTO run_chunks(run_id, seq, samples) VALUES (?, ?, ?)",
                (run_id, seq, text),
            )

    def finish_run(self, run_id: str, status: str, meta: dict[str, Any]) -> None:
        text = dumps_strict(meta)
        with self._lock:
            self._write("UPDATE runs SET status = ?, meta = ? WHERE id = ?", (status, text, run_id))

    def update_run_meta(self, run_id: str, changes: dict[str, Any]) -> bool:
        """Replace top-level keys of a stored run's metadata (False: no such run)."""
        with self._lock:
            row = self._db.execute("SELECT meta FROM runs WHERE id = ?", (run_id,)).fetchone()
            if row is None:
                return False
            meta = loads_clean(row[0]) | changes
            self._write("UPDATE runs SET meta = ? WHERE id = ?", (dumps_strict(meta), run_id))
        return True

    def set_baseline(self, run_id: str) -> bool:
        """Mark ``run_id`` as the baseline of its axis (and no other run of it)."""
        with self._lock:
            row = self._db.execute("SELECT axis_key FROM runs WHERE id = ?", (run_id,)).fetchone()
            if row is None:
                return False
            try:
                self._db.execute("BEGIN")
                try:
                    self._db.execute("UPDATE runs SET baseline = 0 WHERE axis_key = ?", (row[0],))
                    self._db.execute("UPDATE runs SET baseline = 1 WHERE id = ?", (run_id,))
                    self._db.execute("COMMIT")
                except BaseException:
                    if self._db.in_transaction:
                        self._db.execute("ROLLBACK")
                    raise
            except sqlite3.Error as exc:
                raise self._failed(exc) from None
            return True

    def delete_run(self, run_id: str) -> bool:
        with self._lock:
            cursor = self._write("DELETE FROM runs WHERE id = ?", (run_id,))
            return cursor.rowcount > 0

    def list_runs(self, axis_key: str) -> list[dict[str, Any]]:
        with self._lock:
            rows = self._db.execute(
                "SELECT id, axis_id, created_s, status, baseline, meta FROM runs "
                "WHERE axis_key = ? ORDER BY created_s",
                (axis_key,),
            ).fetchall()
        return [_run_row(row) for row in rows]

    def run_ids(self) -> list[str]:
        """Every stored run's id, oldest first."""
        with self._lock:
            rows = self._db.execute("SELECT id FROM runs ORDER BY created_s").fetchall()
        return [run_id for (run_id,) in rows]

    def get_run_meta(self, run_id: str) -> dict[str, Any] | None:
        """A run without its samples (the JSON export), None if there is no such run."""
        with self._lock:
            row = self._db.execute(
                "SELECT id, axis_id, created_s, status, baseline, meta FROM runs WHERE id = ?",
                (run_id,),
            ).fetchone()
        return None if row is None else _run_row(row)

    def get_run(self, run_id: str) -> dict[str, Any] | None:
        run = self.get_run_meta(run_id)
        if run is None:
            return None
        run["samples"] = [row for chunk in self.iter_chunks(run_id) for row in chunk]
        return run

    def chunk_seqs(self, run_id: str) -> list[int]:
        with self._lock:
            rows = self._db.execute(
                "SELECT seq FROM run_chunks WHERE run_id = ? ORDER BY seq", (run_id,)
            ).fetchall()
        return [seq for (seq,) in rows]

    def chunk_text(self, run_id: str, seq: int) -> str:
        """The rows of one chunk as JSON array text, valid strict JSON (cleaned if needed)."""
        with self._lock:
            row = self._db.execute(
                "SELECT samples FROM run_chunks WHERE run_id = ? AND seq = ?", (run_id, seq)
            ).fetchone()
        if row is None:
            return "[]"
        text: str = row[0]
        if _UNSAFE_JSON.search(text):
            text = json.dumps(loads_clean(text), allow_nan=False, separators=(",", ":"))
        return text

    def iter_chunks(self, run_id: str) -> Iterator[list[list[Any]]]:
        """The sample rows of a run chunk by chunk (bounded memory for big runs)."""
        for seq in self.chunk_seqs(run_id):
            rows: list[list[Any]] = json.loads(self.chunk_text(run_id, seq))
            yield rows

    def mark_interrupted_runs(self) -> int:
        """At start-up: runs still 'recording' were cut off by a crash: incomplete."""
        with self._lock:
            cursor = self._write("UPDATE runs SET status = 'incomplete' WHERE status = 'recording'")
            return cursor.rowcount

    def close(self) -> None:
        with self._lock:
            self._db.close()


def _run_row(row: tuple[Any, ...]) -> dict[str, Any]:
    run_id, axis_id, created_s, status, baseline, meta = row
    if not isinstance(created_s, int | float) or not math.isfinite(created_s):
        created_s = None
    return {
        "id": run_id,
        "axis_id": axis_id,
        "created_s": created_s,
        "status": status,
        "baseline": bool(baseline),
        **loads_clean(meta),
    }
