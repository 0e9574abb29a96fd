"""The audit log: who did what, when, from where, to which axis, and how it ended.

Append-only SQLite table in ``auth.db``. :meth:`AuditLog.record` never blocks the event
loop: it puts the entry on a queue and one writer thread (own connection) inserts it.
Reads (the admin page, the CSV export) run in a worker thread too.

What is recorded: logins and failed logins, logouts, password/role/user/token changes,
every state-changing request (command, parameter write with before/after, bench run,
parameter set, console line) with its HTTP result, refusals by the Host/Origin/CSRF
checks and by the permission table, and the control lock's events (the control module
calls :meth:`record`). Telemetry is not recorded.

Never recorded: a password, a token, a cookie or a ticket. :func:`scrub` removes any
key that names one from ``before``/``after`` before the entry is queued, so a caller's
mistake cannot write one.

Refusals of anonymous callers (``who`` "?": not logged in, a foreign Host or Origin, a
missing CSRF token, an unknown user name, a throttled login) are what a scan or a
flood produces: per address and result, the first in ANONYMOUS_WINDOW_S is written
and the rest of that window become one summary row ("N more ..."), written when the
window has passed. Rows of anonymous callers are deleted after
``anonymous_retention_days`` (30 by default; ``servotune serve
--audit-anonymous-days``); every other row is kept.
"""

from __future__ import annotations

import csv
import io
import json
import logging
import math
import queue
import sqlite3
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

logger = logging.getLogger(__name__)

SCHEMA = """
CREATE TABLE IF NOT EXISTS audit (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    t_s REAL NOT NULL,
    who TEXT NOT NULL,
    action TEXT NOT NULL,
    axis TEXT,
    address TEXT,
    before TEXT,
    after TEXT,
    result TEXT NOT NULL,
    detail TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS audit_by_time ON audit (t_s);
CREATE INDEX IF NOT EXISTS audit_by_who ON audit (who, t_s);
"""

ANONYMOUS = "?"
ANONYMOUS_RESULTS = frozenset({"refused", "throttled", "failed"})
ANONYMOUS_WINDOW_S = 60.0
ANONYMOUS_RETENTION_DAYS = 30.0
_MAX_WINDOWS = 4096  # addresses tracked at once; beyond, one shared window ("*")
_PRUNE_PERIOD_S = 3600.0
SECRET_KEYS = ("password", "token", "secret", "cookie", "ticket", "authorization", "csrf")
COLUMNS = ("id", "t_s", "who", "action", "axis", "address", "before", "after", "result", "detail")
MAX_TEXT = 4000  # a console reply or a big parameter block is cut, not refused


def scrub(value: object) -> object:
    """``value`` with every mapping key that names a secret replaced by ``"<redacted>"``."""
    if isinstance(value, dict):
        return {
            str(k): "<redacted>"
            if any(word in str(k).lower() for word in SECRET_KEYS)
            else scrub(v)
            for k, v in value.items()
        }
    if isinstance(value, list | tuple):
        return [scrub(v) for v in value]
    return value


def _json(value: object) -> str | None:
    if value is None:
        return None
    text = json.dumps(scrub(value), default=str, sort_keys=True)
    return text if len(text) <= MAX_TEXT else text[: MAX_TEXT - 1] + "…"


@dataclass(frozen=True, slots=True)
class AuditQuery:
    """Filters of the admin page; every field optional."""

    who: str | None = None
    action: str | None = None  # substring
    axis: str | None = None
    result: str | None = None  # "ok" or a prefix such as "refused"
    since_s: float | None = None
    until_s: float | None = None
    limit: int = 500


@dataclass
class _Window:
    """The refusals of one anonymous (address, result) after the row that opened it."""

    opened_s: float
    count: int = 0
    last: str = ""


class _AnonymousWindows:
    """Which anonymous refusals are written, which only counted (see the module doc).

    ``admit`` is called by ``record`` (the event loop), ``due`` by the writer thread:
    one lock guards both."""

    def __init__(self, window_s: float, clock: Callable[[], float]) -> None:
        self.window_s = window_s
        self._clock = clock
        self._lock = threading.Lock()
        self._windows: dict[tuple[str, str], _Window] = {}

    def admit(self, address: str, result: str, what: str) -> tuple[bool, list[tuple[Any, ...]]]:
        """(write this refusal?, summary rows due for writing first)."""
        now = self._clock()
        with self._lock:
            key = (address, result)
            if key not in self._windows and len(self._windows) >= _MAX_WINDOWS:
                key = ("*", result)  # an address spray shares one window
            window = self._windows.get(key)
            if window is not None and now - window.opened_s < self.window_s:
                window.count += 1
                window.last = what
                return False, []
            due = self._summary(key, window, now) if window is not None else []
            self._windows[key] = _Window(now)
            return True, due

    def due(self, flush_all: bool = False) -> list[tuple[Any, ...]]:
        """Summary rows of the windows that have passed (all of them: ``flush_all``)."""
        now = self._clock()
        rows: list[tuple[Any, ...]] = []
        with self._lock:
            for key, window in list(self._windows.items()):
                if flush_all or now - window.opened_s >= self.window_s:
                    rows += self._summary(key, window, now)
                    del self._windows[key]
        return rows

    def _summary(self, key: tuple[str, str], window: _Window, now: float) -> list[tuple[Any, ...]]:
        if window.count == 0:
            return []
        address, result = key
        span = min(now - window.opened_s, self.window_s)
        detail = (
            f"{window.count} more like this from {address} within {span:.0f} s "
            f"(written as one row); the last: {window.last}"
        )
        return [(time.time(), ANONYMOUS, "refusals summarised", None, address, None, None,
                 result, detail[:MAX_TEXT])]  # fmt: skip


class AuditLog:
    """Queue + writer thread in front of the ``audit`` table."""

    def __init__(
        self,
        path: Path,
        *,
        anonymous_retention_days: float = ANONYMOUS_RETENTION_DAYS,
        anonymous_window_s: float = ANONYMOUS_WINDOW_S,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.path = path
        self.anonymous_retention_days = anonymous_retention_days
        self._anonymous = _AnonymousWindows(anonymous_window_s, clock)
        self._queue: queue.SimpleQueue[tuple[Any, ...] | None] = queue.SimpleQueue()
        self._read_lock = threading.Lock()
        setup = sqlite3.connect(path)
        setup.executescript(SCHEMA)
        setup.close()
        self._reader = sqlite3.connect(path, check_same_thread=False)
        self._thread = threading.Thread(target=self._write_loop, name="audit-writer", daemon=True)
        self._thread.start()

    def record(
        self,
        *,
        who: str,
        action: str,
        axis: str | None = None,
        address: str | None = None,
        before: object = None,
        after: object = None,
        result: str = "ok",
        detail: str = "",
    ) -> None:
        """Queue one entry (returns at once; the writer thread inserts it). An anonymous
        refusal may only be counted into a later summary row (module doc)."""
        if who == ANONYMOUS and result in ANONYMOUS_RESULTS:
            what = f"{action}: {detail}"[:200]
            write, due = self._anonymous.admit(address or "?", result, what)
            for row in due:
                self._queue.put(row)
            if not write:
                return
        self._queue.put(
            (
                time.time(),
                who,
                action,
                axis,
                address,
                _json(before),
                _json(after),
                result,
                detail[:MAX_TEXT],
            )
        )

    def flush(self, timeout_s: float = 5.0) -> None:
        """Wait until everything queued so far is written (tests, shutdown)."""
        done = threading.Event()
        self._queue.put(("__flush__", done))
        done.wait(timeout_s)

    def close(self) -> None:
        """Write what is queued (and every pending summary), stop the writer, close the
        connections."""
        for row in self._anonymous.due(flush_all=True):
            self._queue.put(row)
        self._queue.put(None)
        self._thread.join(10)
        with self._read_lock:
            self._reader.close()

    def _write_loop(self) -> None:
        db = sqlite3.connect(self.path)
        pruned_at = due_at = -math.inf
        try:
            while True:
                if time.monotonic() - pruned_at >= _PRUNE_PERIOD_S:
                    self._prune(db)
                    pruned_at = time.monotonic()
                try:
                    item = self._queue.get(timeout=self._anonymous.window_s)
                except queue.Empty:
                    item = ("__idle__",)
                if item is None:
                    return
                if item[0] == "__flush__":
                    item[1].set()
                    continue
                rows = [] if item[0] == "__idle__" else [item]
                if time.monotonic() - due_at >= 1.0:  # the windows, once a second at most
                    rows = self._anonymous.due() + rows
                    due_at = time.monotonic()
                for row in rows:
                    self._insert(db, row)
        finally:
            db.close()

    @staticmethod
    def _insert(db: sqlite3.Connection, row: tuple[Any, ...]) -> None:
        try:
            with db:
                db.execute(
                    "INSERT INTO audit (t_s, who, action, axis, address, before, after,"
                    " result, detail) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    row,
                )
        except sqlite3.Error:
            # The audit must not take the server down; the failure itself is logged.
            logger.exception("audit entry could not be written (%s)", row[2])

    def _prune(self, db: sqlite3.Connection) -> None:
        """Delete anonymous callers' rows older than the retention (module doc)."""
        cutoff = time.time() - self.anonymous_retention_days * 86400.0
        try:
            with db:
                db.execute("DELETE FROM audit WHERE who = ? AND t_s < ?", (ANONYMOUS, cutoff))
        except sqlite3.Error:
            logger.exception("old anonymous audit entries could not be deleted")

    def query(self, filters: AuditQuery) -> list[dict[str, Any]]:
        """Entries matching ``filters``, newest first (synchronous: run in a thread)."""
        where: list[str] = []
        args: list[Any] = []
        if filters.who is not None:
            where.append("who = ?")
            args.append(filters.who)
        if filters.action:
            where.append("instr(action, ?) > 0")
            args.append(filters.action)
        if filters.axis is not None:
            where.append("axis = ?")
            args.append(filters.axis)
        if filters.result:
            where.append("substr(result, 1, ?) = ?")
            args.extend([len(filters.result), filters.result])
        if filters.since_s is not None:
            where.append("t_s >= ?")
            args.append(filters.since_s)
        if filters.until_s is not None:
            where.append("t_s <= ?")
            args.append(filters.until_s)
        sql = f"SELECT {', '.join(COLUMNS)} FROM audit"
        if where:
            sql += " WHERE " + " AND ".join(where)
        sql += " ORDER BY id DESC LIMIT ?"
        args.append(max(1, min(filters.limit, 10_000)))
        with self._read_lock:
            rows = self._reader.execute(sql, args).fetchall()
        return [dict(zip(COLUMNS, row, strict=True)) for row in rows]

    def csv(self, filters: AuditQuery) -> str:
        """The same entries as CSV with an ISO-8601 UTC time column."""
        out = io.StringIO()
        writer = csv.writer(out)
        writer.writerow(["time_utc", *COLUMNS])
        for row in self.query(filters):
            stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(row["t_s"]))
            writer.writerow([stamp, *(_cell(row[c]) for c in COLUMNS)])
        return out.getvalue()


def _cell(value: object) -> object:
    """A CSV cell a spreadsheet shows as text: a leading = + - @ would start a formula."""
    if value is None:
        return ""
    if isinstance(value, str) and value[:1] in ("=", "+", "-", "@", "\t", "\r"):
        return "'" + value
    return value
