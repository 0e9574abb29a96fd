"""Modes, the start-up rules of exposed mode, and the state the security checks share.

Local mode (default): bound to loopback, no login, every request is the implicit
``LOCAL_PRINCIPAL``. The browser-borne attacks are still stopped (see
``servotune.auth.middleware``): Host allowlist (DNS rebinding), websocket Origin check,
CSRF token on every state-changing request, no CORS.

Exposed mode: any non-loopback bind, or a TLS certificate, or a reverse proxy in front
(a proxy means the clients are elsewhere, even when servotune itself listens on
127.0.0.1). It refuses to start unless accounts exist and the server has TLS or knows
the proxy's address; login is required for everything but the login call itself.
"""

from __future__ import annotations

import asyncio
import functools
import hashlib
import hmac
import ipaddress
import logging
import secrets
import socket
import sqlite3
import tempfile
import time
from collections.abc import Awaitable, Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, ParamSpec, TypeVar

from servotune.auth.audit import ANONYMOUS_RETENTION_DAYS, AuditLog
from servotune.auth.passwords import PRODUCT_PASSWORD_COST, PasswordCost, PasswordWorkers
from servotune.auth.principal import Principal
from servotune.auth.store import AuthStore
from servotune.auth.throttle import LoginThrottle

logger = logging.getLogger(__name__)

LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})
AUTH_DB = "auth.db"
SESSION_COOKIE = "servotune_session"
CSRF_HEADER = "x-csrf-token"
CLIENT_HEADER = "x-servotune-client"
TICKET_TTL_S = 10.0
# Threads that run the accounts database's short lookups (who is asking, sessions,
# tokens): reserved for them, so no hash, run write or other pool user delays a STOP.
AUTH_DB_THREADS = 2

P = ParamSpec("P")
R = TypeVar("R")


class SecurityConfigError(ValueError):
    """Exposed mode cannot start as configured; the message says what to add."""


@dataclass(slots=True)
class SecurityConfig:
    """How the server is reached. ``mode`` None: decided from ``host``/TLS/proxy."""

    mode: Literal["local", "exposed"] | None = None
    host: str = "127.0.0.1"
    tls_cert: Path | None = None
    tls_key: Path | None = None
    proxy: list[str] = field(default_factory=list)  # addresses, CIDRs or host names
    public_hosts: list[str] = field(default_factory=list)  # names the dashboard is reached by
    # Days the audit rows of anonymous callers (refusals, failed logins) are kept.
    audit_anonymous_days: float = ANONYMOUS_RETENTION_DAYS

    @property
    def exposed(self) -> bool:
        if self.mode is not None:
            return self.mode == "exposed"
        return self.host not in LOOPBACK_NAMES or bool(self.proxy) or self.tls_cert is not None

    @property
    def tls(self) -> bool:
        return self.tls_cert is not None and self.tls_key is not None


def is_loopback(host: str) -> bool:
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def proxy_networks(
    proxies: list[str],
) -> list[ipaddress.IPv4Network | ipaddress.IPv6Network]:
    """Parse ``--proxy`` values; a host name is resolved once, at start-up."""
    networks: list[ipaddress.IPv4Network | ipaddress.IPv6Network] = []
    for text in proxies:
        try:
            networks.append(ipaddress.ip_network(text, strict=False))
            continue
        except ValueError:
            pass
        try:
            infos = socket.getaddrinfo(text, None)
        except OSError as exc:
            raise SecurityConfigError(
                f"--proxy {text!r} is neither an address, a network nor a resolvable name: {exc}"
            ) from None
        for info in infos:
            networks.append(ipaddress.ip_network(str(info[4][0]), strict=False))
    return networks


def check_exposed_startup(config: SecurityConfig, store: AuthStore) -> None:
    """Raise SecurityConfigError when exposed mode would start unsafe."""
    if not config.exposed:
        return
    if (config.tls_cert is None) != (config.tls_key is None):
        raise SecurityConfigError("--tls-cert and --tls-key go together: give both")
    if not config.tls and not config.proxy:
        raise SecurityConfigError(
            f"refusing to listen on {config.host} without TLS: give --tls-cert/--tls-key, "
            "or --proxy ADDRESS of the TLS reverse proxy in front of servotune"
        )
    if store.count_users() == 0:
        raise SecurityConfigError(
            "refusing to start exposed without accounts: create the first admin with "
            "'servotune users add NAME --role admin' (same --data-dir)"
        )


@dataclass
class _Ticket:
    principal: Principal
    address: str
    expires: float


CloseCallback = Callable[[], Awaitable[None] | None]


class WsRegistry:
    """The app's open websockets by user, each with the session (or token) it was opened
    under, so logout, revocation and the periodic re-check can close them."""

    def __init__(self) -> None:
        self._entries: dict[int, tuple[Principal, CloseCallback]] = {}

    def add(self, principal: Principal, callback: CloseCallback) -> None:
        self._entries[id(callback)] = (principal, callback)

    def remove(self, callback: CloseCallback) -> None:
        self._entries.pop(id(callback), None)

    def entries(self) -> list[tuple[Principal, CloseCallback]]:
        return list(self._entries.values())

    def matching(self, user: str, session_id: str | None) -> list[CloseCallback]:
        return [
            callback
            for principal, callback in self._entries.values()
            if principal.user == user and (session_id is None or principal.session_id == session_id)
        ]

    def count(self, user: str) -> int:
        return len(self.matching(user, None))


class SecurityState:
    """Everything the checks share; lives on ``app.state.security``.

    ``password_cost``: the Argon2id parameters new password hashes are made at (the
    product's unless the code building the app passes others; see ``AppConfig``).
    """

    def __init__(
        self,
        config: SecurityConfig,
        data_dir: Path,
        *,
        password_cost: PasswordCost = PRODUCT_PASSWORD_COST,
    ) -> None:
        self.config = config
        self.password_cost = password_cost
        self.exposed = config.exposed
        self.auth_path = data_dir / AUTH_DB
        self.proxies = proxy_networks(config.proxy)
        hosts = {h.lower() for h in config.public_hosts}
        if not self.exposed:
            hosts |= LOOPBACK_NAMES
        # Exposed without --public-host: every Host is accepted (a rebinding page has no
        # session cookie for the rebound name, and every call needs a login anyway).
        self.allowed_hosts: frozenset[str] | None = frozenset(hosts) if hosts else None
        self.throttle = LoginThrottle()
        self.passwords: PasswordWorkers | None = None
        self._db_pool: ThreadPoolExecutor | None = None
        self._urgent_pool: ThreadPoolExecutor | None = None
        self.websockets = WsRegistry()
        self._tickets: dict[str, _Ticket] = {}
        self.store: AuthStore | None = None
        self._scratch: tempfile.TemporaryDirectory[str] | None = None
        self.audit: AuditLog | None = None
        self._secret = b""

    # --- lifetime (the app's lifespan) ----------------------------------------------

    def open(self) -> None:
        """Open the accounts database and the audit log.

        Local mode on a data directory that cannot be written (a read-only volume, a
        full disk) still starts, as the rest of the server does: the audit log and the
        CSRF secret then live in a temporary directory for this run, and the log says
        so. Exposed mode refuses to start: without its accounts nobody could log in,
        and a lab must not run without its audit log.
        """
        try:
            self.store = AuthStore(self.auth_path)
        except (OSError, sqlite3.Error) as exc:
            if self.exposed:
                raise SecurityConfigError(
                    f"the accounts database {self.auth_path} cannot be opened: {exc}"
                ) from exc
            self._scratch = tempfile.TemporaryDirectory(prefix="servotune-auth-")
            logger.error(
                "the accounts database %s cannot be written (%s): the audit log of this "
                "run is kept in a temporary directory only",
                self.auth_path,
                exc,
            )
            self.auth_path = Path(self._scratch.name) / AUTH_DB
            self.store = AuthStore(self.auth_path)
        check_exposed_startup(self.config, self.store)
        self.audit = AuditLog(
            self.auth_path, anonymous_retention_days=self.config.audit_anonymous_days
        )
        self._secret = self.store.server_secret()
        self.passwords = PasswordWorkers(cost=self.password_cost)
        self._db_pool = ThreadPoolExecutor(
            max_workers=AUTH_DB_THREADS, thread_name_prefix="servotune-auth-db"
        )
        self._urgent_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="servotune-stop")

    async def close(self) -> None:
        if self.passwords is not None:
            await self.passwords.close()
        for pool in (self._db_pool, self._urgent_pool):
            if pool is not None:
                await asyncio.to_thread(pool.shutdown, wait=True, cancel_futures=True)
        if self.audit is not None:
            self.audit.close()
        if self.store is not None:
            self.store.close()
        if self._scratch is not None:
            self._scratch.cleanup()
            self._scratch = None

    def require_store(self) -> AuthStore:
        if self.store is None:
            raise RuntimeError("security state used before the app's lifespan started")
        return self.store

    def require_audit(self) -> AuditLog:
        if self.audit is None:
            raise RuntimeError("security state used before the app's lifespan started")
        return self.audit

    def require_passwords(self) -> PasswordWorkers:
        if self.passwords is None:
            raise RuntimeError("security state used before the app's lifespan started")
        return self.passwords

    async def db(self, fn: Callable[P, R], *args: P.args, **kwargs: P.kwargs) -> R:
        """Run a short accounts-database call in the threads reserved for it.

        Never the shared default pool: a queue of other work there would delay the
        caller resolution of every request, STOP's included.
        """
        if self._db_pool is None:
            raise RuntimeError("security state used before the app's lifespan started")
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._db_pool, functools.partial(fn, *args, **kwargs))

    async def db_urgent(self, fn: Callable[P, R], *args: P.args, **kwargs: P.kwargs) -> R:
        """``db`` in the one thread reserved for the stops' lookups (STOP, the stop-group
        commands): no other request's lookup ever queues there."""
        if self._urgent_pool is None:
            raise RuntimeError("security state used before the app's lifespan started")
        loop = asyncio.get_running_loop()
        call = functools.partial(fn, *args, **kwargs)
        return await loop.run_in_executor(self._urgent_pool, call)

    # --- CSRF ------------------------------------------------------------------------

    def csrf_token(self, session_cookie: str | None) -> str:
        """The CSRF token bound to a session cookie (or to the local principal).

        An HMAC under the server secret: nothing to store, it changes with the session,
        and a page on another site can neither read it (no CORS) nor compute it.
        """
        subject = f"session|{session_cookie}" if session_cookie else "local|"
        return hmac.new(self._secret, subject.encode(), hashlib.sha256).hexdigest()

    def csrf_ok(self, session_cookie: str | None, presented: str | None) -> bool:
        if not presented or not self._secret:
            return False
        return hmac.compare_digest(self.csrf_token(session_cookie), presented)

    # --- websocket tickets -------------------------------------------------------------

    def issue_ticket(self, principal: Principal, address: str) -> str:
        """A single-use ticket valid TICKET_TTL_S for a websocket from ``address``."""
        now = time.monotonic()
        for key in [k for k, t in self._tickets.items() if t.expires <= now]:
            del self._tickets[key]
        ticket = secrets.token_urlsafe(32)
        key = hashlib.sha256(ticket.encode()).hexdigest()
        self._tickets[key] = _Ticket(principal, address, now + TICKET_TTL_S)
        return ticket

    def redeem_ticket(self, ticket: str, address: str) -> Principal | None:
        """The ticket's principal, once; None when unknown, used, expired or from elsewhere."""
        key = hashlib.sha256(ticket.encode()).hexdigest()
        entry = self._tickets.pop(key, None)  # popped first: a replay finds nothing
        if entry is None or entry.expires <= time.monotonic() or entry.address != address:
            return None
        return entry.principal

    def trusted_proxy(self, peer: str) -> bool:
        try:
            address = ipaddress.ip_address(peer)
        except ValueError:
            return False
        return any(address in network for network in self.proxies)
