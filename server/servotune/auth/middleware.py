"""The ASGI layer in front of every route: proxy headers, Host, Origin, CSRF, audit capture.

Order of the checks on each HTTP request or websocket handshake:

1. **Forwarded headers** (``X-Forwarded-For``/``-Proto``) are honoured only when the
   TCP peer is one of the ``--proxy`` addresses; from anyone else they are ignored.
   With ``--proxy`` and no TLS of its own, servotune refuses peers other than the
   proxy: a direct connection would bypass the proxy's TLS.
2. **Host** must be an allowed name (local mode: localhost, 127.0.0.1, ::1; plus every
   ``--public-host``). A DNS-rebinding page reaches us under its own name and is refused.
3. For state-changing methods (POST, PUT, PATCH, DELETE):
   - ``Sec-Fetch-Site`` other than ``same-origin``/``none`` is refused (the browser
     says the request comes from another site);
   - an ``Origin`` other than our own (``null`` included) is refused;
   - a body must be ``application/json`` (a cross-site HTML form can only send
     ``text/plain``, urlencoded or multipart without a preflight), except multipart
     uploads to the run import, which the CSRF token alone protects;
   - the ``X-CSRF-Token`` header must match the session's token, unless the request
     carries ``Authorization: Bearer`` (a browser never attaches that on its own).
4. No CORS: no ``Access-Control-*`` header is ever sent, so a page on another origin
   cannot read any answer (nor the CSRF token).
5. Body size, before anything parses it: a ``Content-Length`` over the route's cap is
   refused with 413 at once, a chunked body once it passes the cap (MAX_BODY_BYTES,
   1 MiB; the run import MAX_UPLOAD_BYTES, which holds its own 64 MiB limit).

Every HTTP answer carries ``X-Frame-Options: DENY`` and ``Content-Security-Policy:
frame-ancestors 'none'`` (no page of servotune may be framed by another site: a framed
dashboard under a decoy is one click from a command), except the 3D twin under
``/twin``, which the dashboard itself frames: ``SAMEORIGIN`` / ``'self'``. Under TLS
(own, or the proxy's ``X-Forwarded-Proto: https``) ``Strict-Transport-Security`` too.

The websocket's Origin and credentials are checked in ``servotune.auth.ws_auth`` (CORS
rules do not cover websockets); the Host check here covers the handshake too.

Every refusal is written to the audit log. After a state-changing request the
response status (and, for command/parameter routes, the answer's body) is added to the
audit context the authorization dependency prepared (``scope["state"]["audit"]``).
"""

from __future__ import annotations

import json
import re
from http.cookies import SimpleCookie
from typing import Any

from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from servotune.auth.security import CSRF_HEADER, SESSION_COOKIE, SecurityState

MUTATING = frozenset({"POST", "PUT", "PATCH", "DELETE"})
CSRF_EXEMPT_PATHS = frozenset({"/api/auth/login"})
_MAX_CAPTURE = 64 * 1024
# Request bodies: every JSON body of the API is a few hundred bytes to a few KiB.
MAX_BODY_BYTES = 1024 * 1024
# The run import (multipart run.json + samples.csv) checks its own 64 MiB
# (servotune.bench.files.MAX_IMPORT_BYTES); this cap leaves room for the multipart framing.
MAX_UPLOAD_BYTES = 65 * 1024 * 1024
HSTS = b"max-age=31536000"
_FRAME_DENY = [
    (b"x-frame-options", b"DENY"),
    (b"content-security-policy", b"frame-ancestors 'none'"),
]
_FRAME_SELF = [
    (b"x-frame-options", b"SAMEORIGIN"),
    (b"content-security-policy", b"frame-ancestors 'self'"),
]
# The one route that takes file uploads (a run's run.json + samples.csv). A cross-site
# form can post multipart without a preflight, so there the CSRF token below is what
# refuses it; everywhere else a non-JSON body is refused before that.
_UPLOAD_PATH = re.compile(r"^/api/axes/[^/]+/bench/runs/import$")


def header(scope: Scope, name: str) -> str | None:
    """The first header ``name`` (lower case) of an ASGI scope, decoded as latin-1."""
    key = name.encode()
    for k, v in scope.get("headers", ()):
        if k == key:
            return bytes(v).decode("latin-1")
    return None


def session_cookie(scope: Scope) -> str | None:
    raw = header(scope, "cookie")
    if not raw:
        return None
    jar: SimpleCookie = SimpleCookie()
    try:
        jar.load(raw)
    except Exception:  # a malformed Cookie header counts as no cookie
        return None
    morsel = jar.get(SESSION_COOKIE)
    return morsel.value if morsel is not None and morsel.value else None


def host_name(host_header: str) -> str:
    """``example.org:8000`` -> ``example.org``; ``[::1]:8000`` -> ``::1``."""
    text = host_header.strip().lower()
    if text.startswith("["):
        return text[1:].split("]", 1)[0]
    if text.count(":") > 1:
        return text  # a bare IPv6 address without brackets
    return text.rsplit(":", 1)[0] if ":" in text else text


def own_origin(scope: Scope) -> str:
    """``scheme://host[:port]`` the browser shows for this server (after proxy headers)."""
    scheme = scope.get("scheme", "http")
    scheme = {"ws": "http", "wss": "https"}.get(scheme, scheme)
    return f"{scheme}://{(header(scope, 'host') or '').strip().lower()}"


def client_address(scope: Scope) -> str:
    client = scope.get("client")
    return str(client[0]) if client else "?"


class SecurityMiddleware:
    """Pure ASGI middleware (it must see websocket handshakes too)."""

    def __init__(self, app: ASGIApp, security: SecurityState) -> None:
        self.app = app
        self.security = security

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        scope = self._forwarded(scope)
        if scope["type"] == "http":
            send = _with_headers(scope, send)
            receive = _capped(receive, _body_cap(scope))
        refusal = self._refusal(scope)
        if refusal is not None:
            status, detail = refusal
            self._audit_refusal(scope, detail)
            await _refuse(scope, send, status, detail)
            return
        if scope["type"] == "websocket" or scope["method"] not in MUTATING:
            await self.app(scope, receive, send)
            return
        await self._audited(scope, receive, send)

    # --- checks -----------------------------------------------------------------------

    def _forwarded(self, scope: Scope) -> Scope:
        peer = client_address(scope)
        if not self.security.proxies or not self.security.trusted_proxy(peer):
            return scope
        scope = dict(scope)
        forwarded_for = header(scope, "x-forwarded-for")
        if forwarded_for:
            # The right-most entry is the one our proxy appended: the address it saw.
            # Anything left of it was written by the client and proves nothing.
            scope["client"] = (forwarded_for.split(",")[-1].strip(), 0)
        proto = (header(scope, "x-forwarded-proto") or "").strip().lower()
        if proto in ("http", "https"):
            secure = proto == "https"
            if scope["type"] == "websocket":
                scope["scheme"] = "wss" if secure else "ws"
            else:
                scope["scheme"] = proto
        scope["servotune.via_proxy"] = True
        return scope

    def _refusal(self, scope: Scope) -> tuple[int, str] | None:
        security = self.security
        if security.proxies and not security.config.tls and not scope.get("servotune.via_proxy"):
            return 403, "connect through the configured reverse proxy"
        allowed = security.allowed_hosts
        host = host_name(header(scope, "host") or "")
        if allowed is not None and host not in allowed:
            return 403, f"Host {host!r} is not a name of this server"
        if scope["type"] == "websocket":
            return None
        length = header(scope, "content-length")
        if length is not None and length.strip().isdigit() and int(length) > _body_cap(scope):
            return 413, f"request body over {_body_cap(scope)} bytes"
        if scope["method"] not in MUTATING:
            return None
        fetch_site = header(scope, "sec-fetch-site")
        if fetch_site is not None and fetch_site not in ("same-origin", "none"):
            return 403, f"cross-site request refused (Sec-Fetch-Site: {fetch_site})"
        origin = header(scope, "origin")
        if origin is not None and origin.strip().lower() != own_origin(scope):
            return 403, "request from another origin refused"
        if _has_body(scope):
            media = (header(scope, "content-type") or "").split(";")[0].strip().lower()
            uploads = media == "multipart/form-data" and _UPLOAD_PATH.match(scope["path"])
            if media != "application/json" and not uploads:
                return 415, "the body must be application/json"
        authorization = header(scope, "authorization") or ""
        if authorization[:7].lower() == "bearer ":
            return None  # the token itself is checked by the authorization dependency
        if scope["path"] in CSRF_EXEMPT_PATHS:
            return None
        if not security.csrf_ok(session_cookie(scope), header(scope, CSRF_HEADER)):
            return 403, "missing or wrong CSRF token (GET /api/auth/session gives it)"
        return None

    def _audit_refusal(self, scope: Scope, detail: str) -> None:
        audit = self.security.audit
        if audit is None:
            return
        method = scope.get("method", "WS")
        audit.record(
            who="?",
            action=f"refused {method} {scope.get('path', '')}",
            address=client_address(scope),
            result="refused",
            detail=detail,
        )

    # --- audit of state-changing requests -----------------------------------------------

    async def _audited(self, scope: Scope, receive: Receive, send: Send) -> None:
        status = 500
        body = bytearray()

        async def capture(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = int(message["status"])
            elif message["type"] == "http.response.body" and len(body) < _MAX_CAPTURE:
                body.extend(message.get("body", b""))
            await send(message)

        try:
            await self.app(scope, receive, capture)
        finally:
            self._audit_result(scope, status, bytes(body))

    def _audit_result(self, scope: Scope, status: int, body: bytes) -> None:
        context: dict[str, Any] | None = scope.get("state", {}).get("audit")
        audit = self.security.audit
        if context is None or audit is None:
            return
        parsed: object = None
        if body:
            try:
                parsed = json.loads(body)
            except ValueError:
                parsed = None
        # A route may state "after" itself (the console: the parameters read back).
        stated = context.pop("after", None)
        if status < 400:
            result = "ok"
            after = parsed if context.pop("keep_after", False) else None
            if stated is not None:
                after = {"answer": after, "read_back": stated} if after is not None else stated
        else:
            context.pop("keep_after", None)
            detail = parsed.get("detail") if isinstance(parsed, dict) else None
            result = f"http {status}" + (f": {detail}" if isinstance(detail, str) else "")
            after = None
        audit.record(after=after, result=result, **context)


def _body_cap(scope: Scope) -> int:
    return MAX_UPLOAD_BYTES if _UPLOAD_PATH.match(scope.get("path", "")) else MAX_BODY_BYTES


def _capped(receive: Receive, cap: int) -> Receive:
    """``receive`` that refuses (413) a body once more than ``cap`` bytes came in: a
    chunked body names no length, so it is counted as it arrives, before any parser
    holds it whole."""
    total = 0

    async def capped() -> Message:
        nonlocal total
        message = await receive()
        if message["type"] == "http.request":
            total += len(message.get("body", b""))
            if total > cap:
                # Raised where the app reads the body; FastAPI passes HTTPException on.
                raise StarletteHTTPException(413, f"request body over {cap} bytes")
        return message

    return capped


def _with_headers(scope: Scope, send: Send) -> Send:
    """``send`` that adds the frame headers (and HSTS under TLS) to every answer."""
    framing = _FRAME_SELF if scope.get("path", "").startswith("/twin") else _FRAME_DENY
    extra = list(framing)
    if scope.get("scheme") == "https":
        extra.append((b"strict-transport-security", HSTS))

    async def with_headers(message: Message) -> None:
        if message["type"] == "http.response.start":
            names = {bytes(k).lower() for k, _ in message.get("headers", [])}
            headers = list(message.get("headers", []))
            headers += [(k, v) for k, v in extra if k not in names]
            message = {**message, "headers": headers}
        await send(message)

    return with_headers


def _has_body(scope: Scope) -> bool:
    length = header(scope, "content-length")
    if length is not None:
        return length.strip() not in ("", "0")
    return header(scope, "transfer-encoding") is not None


async def _refuse(scope: Scope, send: Send, status: int, detail: str) -> None:
    if scope["type"] == "websocket":
        # Closing before accepting: the server answers the handshake with HTTP 403.
        await send({"type": "websocket.close", "code": 1008, "reason": detail[:120]})
        return
    payload = json.dumps({"detail": detail, "field": None}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(payload)).encode()),
            ],
        }
    )
    await send({"type": "http.response.body", "body": payload})
