"""Accounts, sessions and API tokens in SQLite (``auth.db`` next to ``servotune.db``).

Why a separate file rather than tables in ``servotune.db``: accounts and the audit log
outlive the run data (a lab wipes runs, never its accounts or its audit trail), the
file holding password hashes is created with mode 0600, and the auth code keeps its
own connection and lock so a login never waits behind a bulk run write.

Secrets are never stored: session ids and token secrets are 256-bit random strings
kept as SHA-256 digests (a fast hash is right for high-entropy secrets; Argon2 is for
passwords, which are not). A session's public id (on a Principal, in the audit log)
is the first 16 hex digits of that digest.

Every method is synchronous and short; async callers run them with
``asyncio.to_thread`` so the event loop never waits for a disk flush.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path

from servotune.auth.permissions import permissions_of, role_at_most
from servotune.private_files import private_dir, private_file

SCHEMA = """
CREATE TABLE IF NOT EXISTS users (
    name TEXT PRIMARY KEY,
    role TEXT NOT NULL,
    password_hash TEXT NOT NULL,
    created_s REAL NOT NULL,
    password_changed_s REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS sessions (
    digest TEXT PRIMARY KEY,
    user TEXT NOT NULL REFERENCES users (name) ON DELETE CASCADE,
    created_s REAL NOT NULL,
    last_seen_s REAL NOT NULL,
    password_s REAL NOT NULL,
    address TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS sessions_by_user ON sessions (user);
CREATE TABLE IF NOT EXISTS tokens (
    id TEXT PRIMARY KEY,
    user TEXT NOT NULL REFERENCES users (name) ON DELETE CASCADE,
    name TEXT NOT NULL,
    role TEXT NOT NULL,
    digest TEXT NOT NULL,
    created_s REAL NOT NULL,
    expires_s REAL NOT NULL,
    last_used_s REAL
);
CREATE TABLE IF NOT EXISTS meta (key TEXT PRIMARY KEY, value TEXT NOT NULL);
"""

USER_NAME = re.compile(r"[A-Za-z0-9_.@-]{1,64}")
TOKEN_PREFIX = "stk"
SESSION_IDLE_S = 3600.0  # an hour without a request ends a session
SESSION_LIFETIME_S = 12 * 3600.0  # a lab day; then log in again whatever happens
TOKEN_DEFAULT_DAYS = 90
TOKEN_MAX_DAYS = 366
_LAST_SEEN_RESOLUTION_S = 30.0  # write last_seen at most this often (no write per request)


def _expired(session: Session, now: float) -> bool:
    return (
        now - session.last_seen_s > SESSION_IDLE_S or now - session.created_s > SESSION_LIFETIME_S
    )


class AccountError(ValueError):
    """A refused account operation; the message names the field and the rule."""


@dataclass(frozen=True, slots=True)
class User:
    name: str
    role: str
    created_s: float
    password_changed_s: float


@dataclass(frozen=True, slots=True)
class Session:
    digest: str
    user: str
    role: str
    created_s: float
    last_seen_s: float
    password_s: float

    @property
    def public_id(self) -> str:
        """Safe to log and to put on a Principal: it cannot be turned back into the cookie."""
        return self.digest[:16]


@dataclass(frozen=True, slots=True)
class Token:
    id: str
    user: str
    name: str
    role: str
    created_s: float
    expires_s: float
    last_used_s: float | None


def digest(secret: str) -> str:
    return hashlib.sha256(secret.encode()).hexdigest()


def check_user_name(name: str) -> str:
    if not USER_NAME.fullmatch(name):
        raise AccountError("user name must be 1..64 letters, digits or . _ @ -")
    return name


class AuthStore:
    """Users, sessions and tokens. Thread-safe: one connection behind a lock."""

    def __init__(self, path: Path) -> None:
        # The directory 0700 and the file 0600 before SQLite opens it: password hashes.
        private_dir(path.parent)
        private_file(path)
        self.path = path
        self._lock = threading.Lock()
        self._db = sqlite3.connect(path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA foreign_keys=ON")
        self._db.executescript(SCHEMA)

    def close(self) -> None:
        with self._lock:
            self._db.close()

    # --- server secret (CSRF tokens are HMACs under it) --------------------------------

    def server_secret(self) -> bytes:
        """A random 32-byte key made on first use and kept in the database."""
        with self._lock:
            row = self._db.execute("SELECT value FROM meta WHERE key='secret'").fetchone()
            if row is None:
                value = secrets.token_hex(32)
                self._db.execute("INSERT INTO meta (key, value) VALUES ('secret', ?)", (value,))
                return bytes.fromhex(value)
            return bytes.fromhex(str(row[0]))

    # --- users ----------------------------------------------------------------------

    def count_users(self) -> int:
        with self._lock:
            return int(self._db.execute("SELECT COUNT(*) FROM users").fetchone()[0])

    def list_users(self) -> list[User]:
        with self._lock:
            rows = self._db.execute(
                "SELECT name, role, created_s, password_changed_s FROM users ORDER BY name"
            ).fetchall()
        return [User(*row) for row in rows]

    def get_user(self, name: str) -> User | None:
        with self._lock:
            row = self._db.execute(
                "SELECT name, role, created_s, password_changed_s FROM users WHERE name=?",
                (name,),
            ).fetchone()
        return User(*row) if row else None

    def password_hash(self, name: str) -> str | None:
        with self._lock:
            row = self._db.execute(
                "SELECT password_hash FROM users WHERE name=?", (name,)
            ).fetchone()
        return str(row[0]) if row else None

    def add_user(self, name: str, role: str, password_hash: str) -> User:
        check_user_name(name)
        permissions_of(role)
        now = time.time()
        with self._lock:
            try:
                self._db.execute(
                    "INSERT INTO users VALUES (?, ?, ?, ?, ?)",
                    (name, role, password_hash, now, now),
                )
            except sqlite3.IntegrityError:
                raise AccountError(f"user {name!r} exists already") from None
        return User(name, role, now, now)

    def remove_user(self, name: str) -> None:
        """Delete the user with their sessions and tokens (cascade)."""
        with self._lock:
            if self._db.execute("DELETE FROM users WHERE name=?", (name,)).rowcount == 0:
                raise AccountError(f"no user {name!r}")

    def set_password_hash(self, name: str, password_hash: str) -> None:
        """New password: every session of the user ends (tokens stay: they are not passwords)."""
        with self._lock:
            changed = self._db.execute(
                "UPDATE users SET password_hash=?, password_changed_s=? WHERE name=?",
                (password_hash, time.time(), name),
            ).rowcount
            if changed == 0:
                raise AccountError(f"no user {name!r}")
            self._db.execute("DELETE FROM sessions WHERE user=?", (name,))

    def set_role(self, name: str, role: str) -> None:
        """New role: sessions end, and tokens above the new role are deleted."""
        permissions_of(role)
        with self._lock:
            if self._db.execute("UPDATE users SET role=? WHERE name=?", (role, name)).rowcount == 0:
                raise AccountError(f"no user {name!r}")
            self._db.execute("DELETE FROM sessions WHERE user=?", (name,))
            for token_id, token_role in self._db.execute(
                "SELECT id, role FROM tokens WHERE user=?", (name,)
            ).fetchall():
                if not role_at_most(str(token_role), role):
                    self._db.execute("DELETE FROM tokens WHERE id=?", (token_id,))

    def count_admins(self) -> int:
        with self._lock:
            return int(
                self._db.execute("SELECT COUNT(*) FROM users WHERE role='admin'").fetchone()[0]
            )

    # --- sessions -------------------------------------------------------------------

    def create_session(self, user: str, address: str) -> tuple[str, Session]:
        """A new session for ``user``: returns (cookie value, session). Shown once."""
        cookie = secrets.token_urlsafe(32)
        now = time.time()
        key = digest(cookie)
        with self._lock:
            row = self._db.execute("SELECT role FROM users WHERE name=?", (user,)).fetchone()
            if row is None:
                raise AccountError(f"no user {user!r}")
            self._db.execute(
                "INSERT INTO sessions VALUES (?, ?, ?, ?, ?, ?)",
                (key, user, now, now, now, address),
            )
        return cookie, Session(key, user, str(row[0]), now, now, now)

    def lookup_session(self, cookie: str) -> Session | None:
        """The live session for a cookie value, or None (unknown, idle too long, too old)."""
        key = digest(cookie)
        now = time.time()
        with self._lock:
            row = self._db.execute(
                "SELECT s.digest, s.user, u.role, s.created_s, s.last_seen_s, s.password_s "
                "FROM sessions s JOIN users u ON u.name = s.user WHERE s.digest=?",
                (key,),
            ).fetchone()
            if row is None:
                return None
            session = Session(*row)
            if _expired(session, now):
                self._db.execute("DELETE FROM sessions WHERE digest=?", (key,))
                return None
            if now - session.last_seen_s > _LAST_SEEN_RESOLUTION_S:
                self._db.execute("UPDATE sessions SET last_seen_s=? WHERE digest=?", (now, key))
        return session

    def session_by_public_id(self, public_id: str) -> Session | None:
        """The session with this public id if it exists and has not expired (idle for
        SESSION_IDLE_S or older than SESSION_LIFETIME_S: then it is deleted)."""
        now = time.time()
        with self._lock:
            row = self._db.execute(
                "SELECT s.digest, s.user, u.role, s.created_s, s.last_seen_s, s.password_s "
                "FROM sessions s JOIN users u ON u.name = s.user WHERE substr(s.digest,1,16)=?",
                (public_id,),
            ).fetchone()
            if row is None:
                return None
            session = Session(*row)
            if _expired(session, now):
                self._db.execute("DELETE FROM sessions WHERE digest=?", (session.digest,))
                return None
        return session

    def touch_session(self, public_id: str) -> None:
        """The user acted over a websocket (a control action): not idle."""
        now = time.time()
        with self._lock:
            self._db.execute(
                "UPDATE sessions SET last_seen_s=? WHERE substr(digest,1,16)=? AND last_seen_s<?",
                (now, public_id, now - _LAST_SEEN_RESOLUTION_S),
            )

    def mark_password_entered(self, session_digest: str) -> None:
        with self._lock:
            self._db.execute(
                "UPDATE sessions SET password_s=? WHERE digest=?", (time.time(), session_digest)
            )

    def end_session(self, session_digest: str) -> None:
        with self._lock:
            self._db.execute("DELETE FROM sessions WHERE digest=?", (session_digest,))

    def sessions_of(self, user: str) -> int:
        with self._lock:
            return int(
                self._db.execute("SELECT COUNT(*) FROM sessions WHERE user=?", (user,)).fetchone()[
                    0
                ]
            )

    # --- API tokens -----------------------------------------------------------------

    def create_token(
        self, user: str, name: str, role: str, days: int = TOKEN_DEFAULT_DAYS
    ) -> tuple[str, Token]:
        """A new token: returns (the secret, shown once, and the stored record)."""
        if not 1 <= len(name) <= 64:
            raise AccountError("token name must have 1..64 characters")
        if not 1 <= days <= TOKEN_MAX_DAYS:
            raise AccountError(f"days must be in 1..{TOKEN_MAX_DAYS}, got {days}")
        owner = self.get_user(user)
        if owner is None:
            raise AccountError(f"no user {user!r}")
        permissions_of(role)
        if not role_at_most(role, owner.role):
            raise AccountError(f"role {role!r} is above the user's role {owner.role!r}")
        token_id = secrets.token_hex(6)
        secret = secrets.token_urlsafe(32)
        now = time.time()
        token = Token(token_id, user, name, role, now, now + days * 86400.0, None)
        with self._lock:
            self._db.execute(
                "INSERT INTO tokens VALUES (?, ?, ?, ?, ?, ?, ?, NULL)",
                (token_id, user, name, role, digest(secret), now, token.expires_s),
            )
        return f"{TOKEN_PREFIX}_{token_id}_{secret}", token

    def list_tokens(self, user: str | None = None) -> list[Token]:
        query = "SELECT id, user, name, role, created_s, expires_s, last_used_s FROM tokens"
        with self._lock:
            if user is None:
                rows = self._db.execute(query + " ORDER BY user, created_s").fetchall()
            else:
                rows = self._db.execute(
                    query + " WHERE user=? ORDER BY created_s", (user,)
                ).fetchall()
        return [Token(*row) for row in rows]

    def revoke_token(self, token_id: str, user: str | None = None) -> Token:
        """Delete a token (only the user's own when ``user`` is given)."""
        tokens = [t for t in self.list_tokens(user) if t.id == token_id]
        if not tokens:
            raise AccountError(f"no token {token_id!r}")
        with self._lock:
            self._db.execute("DELETE FROM tokens WHERE id=?", (token_id,))
        return tokens[0]

    def token_alive(self, token_id: str) -> bool:
        """The token exists, has not expired and is within its user's role."""
        with self._lock:
            row = self._db.execute(
                "SELECT t.role, t.expires_s, u.role FROM tokens t JOIN users u "
                "ON u.name = t.user WHERE t.id=?",
                (token_id,),
            ).fetchone()
        if row is None:
            return False
        return float(row[1]) > time.time() and role_at_most(str(row[0]), str(row[2]))

    def lookup_token(self, presented: str) -> Token | None:
        """The live token for a presented ``stk_<id>_<secret>``, compared in constant time."""
        prefix, _, rest = presented.partition("_")
        token_id, _, secret = rest.partition("_")
        if prefix != TOKEN_PREFIX or not token_id or not secret:
            return None
        now = time.time()
        with self._lock:
            row = self._db.execute(
                "SELECT t.id, t.user, t.name, t.role, t.created_s, t.expires_s, t.last_used_s, "
                "t.digest, u.role FROM tokens t JOIN users u ON u.name = t.user WHERE t.id=?",
                (token_id,),
            ).fetchone()
            if row is None:
                return None
            # The digest comparison is the secret check: constant time (hmac.compare_digest),
            # so response timing tells nothing about how many characters were right.
            if not hmac.compare_digest(str(row[7]), digest(secret)):
                return None
            token = Token(*row[:7])
            if token.expires_s <= now or not role_at_most(token.role, str(row[8])):
                return None
            if token.last_used_s is None or now - token.last_used_s > _LAST_SEEN_RESOLUTION_S:
                self._db.execute("UPDATE tokens SET last_used_s=? WHERE id=?", (now, token_id))
        return token
