"""The one authorization dependency every route goes through.

``authorize`` resolves the Principal (local mode: ``LOCAL_PRINCIPAL``; a bearer token or
the session cookie otherwise), stores it at ``request.state.principal``, looks the
matched route up in ``ROUTE_PERMISSIONS`` and refuses 401/403; a route missing from the
table is a 500. Then, for a permission that changes an axis, it asks the control lock
(``app.state.control.require``, written by the control module) whether this client
holds that axis (423 otherwise). Last it prepares the audit entry the middleware
completes with the response's status.
"""

from __future__ import annotations

import logging
import time
from typing import Any

from fastapi import HTTPException, Request
from starlette.requests import HTTPConnection

from servotune.auth.audit import AuditLog
from servotune.auth.middleware import MUTATING, client_address, session_cookie
from servotune.auth.permissions import DANGEROUS, LOCKED, REAUTH_AFTER_S, permissions_of
from servotune.auth.principal import CONSOLE, LOCAL_PRINCIPAL, MOVE, PARAM_SETS, STOP, Principal
from servotune.auth.routes_table import (
    COMMAND,
    CONSOLE_LINE,
    PUBLIC,
    ROUTE_PERMISSIONS,
    UnknownConsoleLineError,
    command_permission,
    console_permission,
)
from servotune.auth.security import CLIENT_HEADER, SecurityState
from servotune.auth.store import AuthStore, Session
from servotune.hub.state import UnknownAxisError
from servotune.link.base import InvalidArgumentError

logger = logging.getLogger(__name__)

# Routes whose answer is worth keeping as the audit's "after" (small, no secrets).
_KEEP_AFTER = frozenset(
    {
        ("PATCH", "/api/axes/{axis_id}/params"),
        ("POST", "/api/axes/{axis_id}/commands"),
        ("POST", "/api/axes/{axis_id}/console"),
        ("POST", "/api/axes/{axis_id}/param-sets/{name}/restore"),
        ("PUT", "/api/axes/{axis_id}/bench/limits"),
        ("POST", "/api/axes/{axis_id}/autotune/accept"),
        ("POST", "/api/axes/{axis_id}/autotune/keep"),
        ("POST", "/api/axes/{axis_id}/autotune/revert"),
    }
)
# These routes write their own audit entries (and their bodies may hold secrets).
_BODY_AUDITED = frozenset(
    {
        ("POST", "/api/axes/{axis_id}/commands"),
        ("PATCH", "/api/axes/{axis_id}/params"),
        ("POST", "/api/axes/{axis_id}/console"),
    }
)
_SELF_AUDITED_PREFIXES = ("/api/auth/", "/api/users")


def security_of(connection: HTTPConnection) -> SecurityState:
    security: SecurityState = connection.app.state.security
    return security


def _bearer(connection: HTTPConnection) -> str | None:
    value = connection.headers.get("authorization", "")
    if value[:7].lower() == "bearer ":
        return value[7:].strip()
    return None


def resolve_principal(
    connection: HTTPConnection, security: SecurityState
) -> tuple[Principal | None, Session | None]:
    """Who is asking (synchronous: short SQLite lookups; callers use a thread).

    A bearer token wins over the cookie; a bad bearer token is an anonymous caller
    (never a fall-back to the cookie). Local mode without a token is the local principal.
    """
    store: AuthStore = security.require_store()
    token_text = _bearer(connection)
    if token_text is not None:
        token = store.lookup_token(token_text)
        if token is None:
            return None, None
        principal = Principal(
            user=token.user,
            role=token.role,
            permissions=permissions_of(token.role),
            session_id=f"token:{token.id}",
            via="token",
        )
        return principal, None
    if not security.exposed:
        return LOCAL_PRINCIPAL, None
    cookie = session_cookie(connection.scope)
    if cookie is None:
        return None, None
    session = store.lookup_session(cookie)
    if session is None:
        return None, None
    principal = Principal(
        user=session.user,
        role=session.role,
        permissions=permissions_of(session.role),
        session_id=session.public_id,
        via="session",
    )
    return principal, session


REAUTH_DETAIL = "enter your password again (POST /api/auth/reauth)"


def password_fresh(session: Session | None, now_s: float | None = None) -> bool:
    """The re-authentication rule of dangerous actions, for REST and websocket alike:
    a session's password must have been typed in the last REAUTH_AFTER_S (an API token
    or local mode has no session and was created under such a check)."""
    if session is None:
        return True
    return (time.time() if now_s is None else now_s) - session.password_s <= REAUTH_AFTER_S


def needs_lookup(connection: HTTPConnection, security: SecurityState) -> bool:
    """Whether resolving the caller reads the accounts database (a token or a session
    cookie is presented). Without one the answer is known at once, with no I/O."""
    if _bearer(connection) is not None:
        return True
    return security.exposed and session_cookie(connection.scope) is not None


async def caller(
    connection: HTTPConnection, security: SecurityState, *, urgent: bool = False
) -> tuple[Principal | None, Session | None]:
    """``resolve_principal`` off the event loop when it reads the database: in the
    threads reserved for the accounts database, or (``urgent``: STOP and the other
    stops) in the one thread reserved for those, which nothing else queues in."""
    if not needs_lookup(connection, security):
        return resolve_principal(connection, security)
    if urgent:
        return await security.db_urgent(resolve_principal, connection, security)
    return await security.db(resolve_principal, connection, security)


# The permission of a console line whose effect the descriptor does not state: no role
# has it; the caller with CONSOLE gets 422 naming ``line`` (see authorize).
UNCLASSIFIED_LINE = "<unclassified console line>"


async def _permission_for(request: Request, permission: str) -> str:
    """The permission this request needs: ``permission`` itself, or for a command or a
    console line the one of what the body asks (routes_table's COMMAND, CONSOLE_LINE)."""
    if permission not in (COMMAND, CONSOLE_LINE):
        return permission
    try:
        body = await request.json()
    except ValueError:
        body = None
    axis_id = request.path_params.get("axis_id", "")
    try:
        descriptor = request.app.state.hub.descriptor(axis_id)
    except UnknownAxisError:
        return MOVE  # the strictest reading; the route answers 404 to those allowed
    field = "command" if permission == COMMAND else "line"
    value = body.get(field) if isinstance(body, dict) else None
    if permission == COMMAND:
        return command_permission(descriptor, str(value or ""))
    if not isinstance(value, str):
        return CONSOLE  # the route's own validation answers 422
    try:
        return console_permission(descriptor, value)
    except UnknownConsoleLineError as exc:
        request.state.console_refusal = str(exc)
        return UNCLASSIFIED_LINE


async def authorize(connection: HTTPConnection) -> None:
    """The app-wide dependency; see the module docstring for what it checks."""
    if not isinstance(connection, Request):
        return  # websockets: servotune.auth.ws_auth.authenticate_websocket in the endpoint
    request = connection
    route = request.scope.get("route")
    path = getattr(route, "path", request.url.path)
    key = (request.method, path)
    declared = ROUTE_PERMISSIONS.get(key)
    if declared is None:
        logger.error("route %s %s has no entry in ROUTE_PERMISSIONS", *key)
        raise HTTPException(500, f"route {request.method} {path} declares no permission")
    security = security_of(request)
    # The permission first (a command's comes from its body): a STOP resolves its
    # caller in the lane reserved for stops, so no queue of other requests (a login
    # flood once held STOP for seconds) stands in front of it.
    permission = declared if declared == PUBLIC else await _permission_for(request, declared)
    principal, session = await caller(request, security, urgent=permission == STOP)
    request.state.principal = principal
    request.state.session = session
    if declared == PUBLIC:
        return
    audit = security.require_audit()
    address = client_address(request.scope)
    mutating = request.method in MUTATING
    if principal is None:
        if mutating:
            audit.record(
                who="?",
                action=f"{request.method} {path}",
                address=address,
                result="refused",
                detail="not logged in",
            )
        raise HTTPException(401, "log in first", headers={"WWW-Authenticate": "Bearer"})
    axis_id = request.path_params.get("axis_id")
    # A console line needs the console, and then what the line is (routes_table).
    for needed in (CONSOLE, permission) if declared == CONSOLE_LINE else (permission,):
        if needed == UNCLASSIFIED_LINE:
            why = getattr(request.state, "console_refusal", "unknown console line")
            _refused(audit, principal, request, path, address, why)
            raise InvalidArgumentError("line", why)
        if needed not in principal.permissions:
            _refused(audit, principal, request, path, address, f"needs permission {needed!r}")
            raise HTTPException(
                403, f"your role {principal.role!r} does not allow this (needs {needed!r})"
            )
    if mutating and permission in DANGEROUS and not password_fresh(session):
        _refused(audit, principal, request, path, address, "password required again")
        raise HTTPException(401, REAUTH_DETAIL)
    if mutating and not path.startswith(_SELF_AUDITED_PREFIXES):
        request.state.audit = await _audit_context(request, principal, path, address)
    if (
        mutating
        and permission in LOCKED
        and axis_id is not None
        and not (permission == PARAM_SETS and not path.endswith("/restore"))
    ):
        control = getattr(request.app.state, "control", None)
        if control is not None:
            client_id = request.headers.get(CLIENT_HEADER)
            await control.require(axis_id, client_id, principal)


def _refused(
    audit: AuditLog, principal: Principal, request: Request, path: str, address: str, why: str
) -> None:
    audit.record(
        who=principal.user,
        action=f"{request.method} {path}",
        axis=request.path_params.get("axis_id"),
        address=address,
        result="refused",
        detail=why,
    )


async def _audit_context(
    request: Request, principal: Principal, path: str, address: str
) -> dict[str, Any]:
    """What the middleware writes once the answer is known (it adds result and after)."""
    axis_id = request.path_params.get("axis_id")
    key = (request.method, path)
    context: dict[str, Any] = {
        "who": principal.user,
        "action": f"{request.method} {path}",
        "axis": axis_id,
        "address": client_address(request.scope),
        "keep_after": key in _KEEP_AFTER,
        "detail": "",
        "before": None,
    }
    body: object = None
    # Only the small bodies the audit describes are read here (a command, a parameter
    # write, a console line); a run import's body (up to 64 MiB) is left to its route,
    # which streams it off the event loop.
    if key in _BODY_AUDITED and request.headers.get("content-length", "0") not in ("", "0"):
        try:
            body = await request.json()
        except ValueError:
            body = None
    if key == ("POST", "/api/axes/{axis_id}/commands") and isinstance(body, dict):
        context["detail"] = str(body.get("command", ""))
        context["before"] = {k: v for k, v in body.items() if k != "command"} or None
    elif key == ("PATCH", "/api/axes/{axis_id}/params") and isinstance(body, dict) and axis_id:
        try:
            known = request.app.state.hub.entry(axis_id).last_known
        except Exception:  # an unknown axis is the route's 404 to give
            known = {}
        context["before"] = {name: known.get(name) for name in body}
        context["detail"] = "requested " + ", ".join(f"{k}={v}" for k, v in body.items())
    elif key == ("POST", "/api/axes/{axis_id}/console") and isinstance(body, dict):
        line = str(body.get("line", ""))
        context["detail"] = line
        try:
            written = request.app.state.hub.descriptor(axis_id or "").console.parameters_set(line)
        except UnknownAxisError:
            written = []
        if written:
            # The route adds the read-back as "after" (servotune.api.routes.console).
            known = request.app.state.hub.entry(axis_id).last_known
            context["before"] = {name: known.get(name) for name in written}
    elif "run_id" in request.path_params:
        context["detail"] = f"run {request.path_params['run_id']}"
    elif "name" in request.path_params:
        context["detail"] = f"set {request.path_params['name']}"
    return context
