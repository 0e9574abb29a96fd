"""Login, logout, session, CSRF token, websocket ticket, users, tokens and the audit log.

Every route here is in ``servotune.auth.routes_table.ROUTE_PERMISSIONS`` like any other;
the app-wide ``authorize`` dependency has already resolved ``request.state.principal``
and checked the permission before a handler runs. These handlers write their own
audit entries (never with a password, token, cookie or ticket in them).
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response
from fastapi.responses import PlainTextResponse
from pydantic import BaseModel, Field

from servotune.api.responses import errors
from servotune.auth.audit import AuditQuery
from servotune.auth.middleware import client_address, session_cookie
from servotune.auth.passwords import (
    MAX_PASSWORD_LENGTH,
    MIN_PASSWORD_LENGTH,
    PasswordWorkersBusyError,
    WeakPasswordError,
    check_password_rule,
)
from servotune.auth.permissions import ADMIN, ROLE_ORDER, UnknownRoleError, permissions_of
from servotune.auth.principal import AUDIT_ALL, Principal
from servotune.auth.security import SESSION_COOKIE, TICKET_TTL_S, SecurityState
from servotune.auth.store import (
    SESSION_LIFETIME_S,
    TOKEN_DEFAULT_DAYS,
    TOKEN_MAX_DAYS,
    USER_NAME,
    AccountError,
    Session,
    Token,
)
from servotune.auth.throttle import Attempt, ThrottledError
from servotune.auth.ws_auth import close_websockets
from servotune.schema import (
    AuditEntry,
    NewToken,
    SessionInfo,
    TicketReply,
    TokenInfo,
    UserChanged,
    UserInfo,
)

# What the account routes can answer besides their success (bodies are ``ErrorBody``).
router = APIRouter(tags=["auth"], responses=errors(404, 409, 422, 429))

Role = Literal["viewer", "operator", "admin"]


class LoginRequest(BaseModel):
    user: str = Field(min_length=1, max_length=64)
    password: str = Field(min_length=1, max_length=MAX_PASSWORD_LENGTH)


class PasswordRequest(BaseModel):
    password: str = Field(min_length=1, max_length=MAX_PASSWORD_LENGTH)


class PasswordChange(BaseModel):
    current_password: str = Field(min_length=1, max_length=MAX_PASSWORD_LENGTH)
    new_password: str = Field(min_length=MIN_PASSWORD_LENGTH, max_length=MAX_PASSWORD_LENGTH)


class TokenCreate(BaseModel):
    name: str = Field(min_length=1, max_length=64)
    user: str | None = Field(default=None, description="owner (default: the caller)")
    role: Role | None = Field(default=None, description="default: the owner's role")
    days: int = Field(default=TOKEN_DEFAULT_DAYS, ge=1, le=TOKEN_MAX_DAYS)


class UserCreate(BaseModel):
    name: str = Field(pattern=f"^{USER_NAME.pattern}$", description="letters, digits or . _ @ -")
    role: Role
    password: str = Field(min_length=MIN_PASSWORD_LENGTH, max_length=MAX_PASSWORD_LENGTH)


class UserChange(BaseModel):
    role: Role | None = None
    password: str | None = Field(
        default=None, min_length=MIN_PASSWORD_LENGTH, max_length=MAX_PASSWORD_LENGTH
    )


def _security(request: Request) -> SecurityState:
    security: SecurityState = request.app.state.security
    return security


def _principal(request: Request) -> Principal:
    principal: Principal | None = getattr(request.state, "principal", None)
    if principal is None:
        raise HTTPException(401, "log in first")
    return principal


def _begin_attempt(security: SecurityState, address: str, user: str, what: str) -> Attempt:
    """Reserve a password check (before anything is hashed), or answer 429."""
    try:
        return security.throttle.begin(address, user)
    except ThrottledError as exc:
        security.require_audit().record(
            who="?", action=what, address=address, result="throttled", detail="429"
        )
        raise HTTPException(
            429,
            f"too many failed attempts: try again in {exc.retry_after_s:.0f} s",
            headers={"Retry-After": str(max(1, round(exc.retry_after_s)))},
        ) from None


async def _check_password(
    security: SecurityState, attempt: Attempt, stored: str | None, password: str
) -> bool:
    """Verify in the hashing pool; a full pool uncounts the attempt and answers 429."""
    try:
        return await security.require_passwords().verify(stored, password)
    except PasswordWorkersBusyError as exc:
        security.throttle.cancel(attempt)
        raise HTTPException(
            429, str(exc), headers={"Retry-After": str(exc.retry_after_s)}
        ) from None


async def _hash(security: SecurityState, password: str) -> str:
    try:
        return await security.require_passwords().hash(password)
    except PasswordWorkersBusyError as exc:
        raise HTTPException(
            429, str(exc), headers={"Retry-After": str(exc.retry_after_s)}
        ) from None


def _info(security: SecurityState, principal: Principal | None, cookie: str | None) -> SessionInfo:
    return SessionInfo(
        mode="exposed" if security.exposed else "local",
        user=principal.user if principal else None,
        role=principal.role if principal else None,
        permissions=sorted(principal.permissions) if principal else [],
        csrf_token=security.csrf_token(cookie),
        via=principal.via if principal else None,
        roles=list(ROLE_ORDER),
    )


def _set_cookie(request: Request, response: Response, value: str) -> None:
    response.set_cookie(
        SESSION_COOKIE,
        value,
        max_age=int(SESSION_LIFETIME_S),
        path="/",
        httponly=True,
        samesite="strict",
        secure=request.url.scheme == "https",
    )


@router.get("/api/auth/session", response_model=SessionInfo)
async def session_info(request: Request) -> SessionInfo:
    """Who the caller is (or nobody), the mode, and the CSRF token for mutating calls."""
    principal: Principal | None = getattr(request.state, "principal", None)
    cookie = session_cookie(request.scope) if principal and principal.via == "session" else None
    return _info(_security(request), principal, cookie)


@router.post("/api/auth/login", response_model=SessionInfo)
async def login(body: LoginRequest, request: Request, response: Response) -> SessionInfo:
    """Check the password; a new session (new id, the old cookie's session ends)."""
    security = _security(request)
    if not security.exposed:
        raise HTTPException(409, "local mode: no login needed")
    store = security.require_store()
    audit = security.require_audit()
    address = client_address(request.scope)
    attempt = _begin_attempt(security, address, body.user, "login")
    stored = await security.db(store.password_hash, body.user)
    if not await _check_password(security, attempt, stored, body.password):
        # An unknown name is not written down: people type their password into it.
        audit.record(
            who=body.user if stored is not None else "?",
            action="login",
            address=address,
            result="failed",
            detail="wrong password" if stored is not None else "unknown user name",
        )
        raise HTTPException(401, "wrong user name or password")
    security.throttle.succeeded(attempt)
    old = session_cookie(request.scope)
    if old is not None:
        previous = await security.db(store.lookup_session, old)
        if previous is not None:
            await security.db(store.end_session, previous.digest)
    cookie, session = await security.db(store.create_session, body.user, address)
    _set_cookie(request, response, cookie)
    audit.record(
        who=body.user, action="login", address=address, detail=f"session {session.public_id}"
    )
    principal = _session_principal(session)
    return _info(security, principal, cookie)


def _session_principal(session: Session) -> Principal:
    return Principal(
        user=session.user,
        role=session.role,
        permissions=permissions_of(session.role),
        session_id=session.public_id,
        via="session",
    )


@router.post("/api/auth/logout", status_code=204, response_model=None)
async def logout(request: Request, response: Response) -> None:
    """End this session and close its websockets."""
    principal = _principal(request)
    security = _security(request)
    session: Session | None = getattr(request.state, "session", None)
    if session is not None:
        await security.db(security.require_store().end_session, session.digest)
        await close_websockets(security, principal.user, principal.session_id)
    response.delete_cookie(SESSION_COOKIE, path="/", httponly=True, samesite="strict")
    security.require_audit().record(
        who=principal.user, action="logout", address=client_address(request.scope)
    )


@router.post("/api/auth/reauth", status_code=204, response_model=None)
async def reauth(body: PasswordRequest, request: Request) -> None:
    """Type the password again before a dangerous action (valid 5 minutes)."""
    principal = _principal(request)
    security = _security(request)
    session: Session | None = getattr(request.state, "session", None)
    if session is None:
        return  # local mode or a token: nothing to confirm
    address = client_address(request.scope)
    attempt = _begin_attempt(security, address, principal.user, "reauth")
    store = security.require_store()
    stored = await security.db(store.password_hash, principal.user)
    if not await _check_password(security, attempt, stored, body.password):
        security.require_audit().record(
            who=principal.user, action="reauth", address=address, result="failed"
        )
        raise HTTPException(401, "wrong password")
    security.throttle.succeeded(attempt)
    await security.db(store.mark_password_entered, session.digest)
    security.require_audit().record(who=principal.user, action="reauth", address=address)


@router.post("/api/auth/password", status_code=204, response_model=None)
async def change_own_password(body: PasswordChange, request: Request, response: Response) -> None:
    """Change the caller's password; every session of the user ends (log in again)."""
    principal = _principal(request)
    security = _security(request)
    if principal.via != "session":
        raise HTTPException(409, "change a password from a logged-in browser session")
    store = security.require_store()
    address = client_address(request.scope)
    attempt = _begin_attempt(security, address, principal.user, "password change")
    stored = await security.db(store.password_hash, principal.user)
    if not await _check_password(security, attempt, stored, body.current_password):
        security.require_audit().record(
            who=principal.user, action="password change", address=address, result="failed"
        )
        raise HTTPException(401, "wrong current password")
    security.throttle.succeeded(attempt)
    try:
        check_password_rule(body.new_password)
    except WeakPasswordError as exc:
        raise HTTPException(422, str(exc)) from None
    new_hash = await _hash(security, body.new_password)
    await security.db(store.set_password_hash, principal.user, new_hash)
    await close_websockets(security, principal.user)
    response.delete_cookie(SESSION_COOKIE, path="/", httponly=True, samesite="strict")
    security.require_audit().record(who=principal.user, action="password change", address=address)


@router.post("/api/auth/ws-ticket", response_model=TicketReply)
async def ws_ticket(request: Request) -> TicketReply:
    """A single-use websocket ticket (``/ws?ticket=...``), valid 10 s from this address."""
    principal = _principal(request)
    security = _security(request)
    ticket = security.issue_ticket(principal, client_address(request.scope))
    return TicketReply(ticket=ticket, expires_in_s=TICKET_TTL_S)


# --- API tokens (admin) ---------------------------------------------------------------


def _token_row(token: Token) -> TokenInfo:
    return TokenInfo(
        id=token.id,
        user=token.user,
        name=token.name,
        role=token.role,
        created_s=token.created_s,
        expires_s=token.expires_s,
        last_used_s=token.last_used_s,
    )


@router.get("/api/auth/tokens", response_model=list[TokenInfo])
async def list_tokens(request: Request, user: str | None = None) -> list[TokenInfo]:
    """Every token (``?user=`` filters); never the secret, which is not stored."""
    security = _security(request)
    store = security.require_store()
    return [_token_row(t) for t in await security.db(store.list_tokens, user)]


@router.post("/api/auth/tokens", status_code=201, response_model=NewToken)
async def create_token(body: TokenCreate, request: Request) -> NewToken:
    """A new API token; its secret is in this answer and nowhere else, ever."""
    principal = _principal(request)
    security = _security(request)
    store = security.require_store()
    owner = body.user or principal.user
    user = await security.db(store.get_user, owner)
    if user is None:
        raise HTTPException(404, f"no user {owner!r}")
    role = body.role or user.role
    try:
        secret, token = await security.db(store.create_token, owner, body.name, role, body.days)
    except (AccountError, UnknownRoleError) as exc:
        raise HTTPException(422, str(exc)) from None
    security.require_audit().record(
        who=principal.user,
        action="token create",
        address=client_address(request.scope),
        after={"id": token.id, "user": owner, "name": body.name, "role": role, "days": body.days},
    )
    return NewToken(**_token_row(token).model_dump(), token=secret)


@router.delete("/api/auth/tokens/{token_id}", status_code=204, response_model=None)
async def revoke_token(token_id: str, request: Request) -> None:
    """Delete a token; websockets opened with it close."""
    principal = _principal(request)
    security = _security(request)
    try:
        token = await security.db(security.require_store().revoke_token, token_id)
    except AccountError as exc:
        raise HTTPException(404, str(exc)) from None
    await close_websockets(security, token.user, f"token:{token.id}")
    security.require_audit().record(
        who=principal.user,
        action="token revoke",
        address=client_address(request.scope),
        before={"id": token.id, "user": token.user, "name": token.name},
    )


# --- users (admin) --------------------------------------------------------------------


@router.get("/api/users", response_model=list[UserInfo])
async def list_users(request: Request) -> list[UserInfo]:
    security = _security(request)
    store = security.require_store()
    return [
        UserInfo(name=u.name, role=u.role, created_s=u.created_s)
        for u in await security.db(store.list_users)
    ]


@router.post("/api/users", status_code=201, response_model=UserInfo)
async def add_user(body: UserCreate, request: Request) -> UserInfo:
    """A new account (the first admin comes from the command line only)."""
    principal = _principal(request)
    security = _security(request)
    try:
        check_password_rule(body.password)
        password_hash = await _hash(security, body.password)
        user = await security.db(
            security.require_store().add_user, body.name, body.role, password_hash
        )
    except (AccountError, WeakPasswordError) as exc:
        raise HTTPException(422, str(exc)) from None
    security.require_audit().record(
        who=principal.user,
        action="user add",
        address=client_address(request.scope),
        after={"name": user.name, "role": user.role},
    )
    return UserInfo(name=user.name, role=user.role, created_s=user.created_s)


@router.patch("/api/users/{name}", response_model=UserChanged)
async def change_user(name: str, body: UserChange, request: Request) -> UserChanged:
    """New role and/or password: the user's sessions end and their websockets close."""
    principal = _principal(request)
    security = _security(request)
    store = security.require_store()
    user = await security.db(store.get_user, name)
    if user is None:
        raise HTTPException(404, f"no user {name!r}")
    demoted = body.role is not None and body.role != ADMIN and user.role == ADMIN
    if demoted and await security.db(store.count_admins) <= 1:
        raise HTTPException(409, "the last admin cannot lose the admin role")
    try:
        if body.password is not None:
            check_password_rule(body.password)
            password_hash = await _hash(security, body.password)
            await security.db(store.set_password_hash, name, password_hash)
        if body.role is not None:
            await security.db(store.set_role, name, body.role)
    except (AccountError, WeakPasswordError) as exc:
        raise HTTPException(422, str(exc)) from None
    closed = await close_websockets(security, name)
    changes = [c for c, v in (("role", body.role), ("password", body.password)) if v is not None]
    security.require_audit().record(
        who=principal.user,
        action="user change",
        address=client_address(request.scope),
        before={"name": name, "role": user.role},
        after={"name": name, "role": body.role or user.role},
        detail=f"changed {', '.join(changes) or 'nothing'}; {closed} websocket(s) closed",
    )
    return UserChanged(name=name, role=body.role or user.role)


@router.delete("/api/users/{name}", status_code=204, response_model=None)
async def remove_user(name: str, request: Request) -> None:
    """Delete the account with its sessions and tokens; its websockets close."""
    principal = _principal(request)
    security = _security(request)
    store = security.require_store()
    user = await security.db(store.get_user, name)
    if user is None:
        raise HTTPException(404, f"no user {name!r}")
    if user.role == ADMIN and await security.db(store.count_admins) <= 1:
        raise HTTPException(409, "the last admin cannot be removed")
    await security.db(store.remove_user, name)
    await close_websockets(security, name)
    security.require_audit().record(
        who=principal.user,
        action="user remove",
        address=client_address(request.scope),
        before={"name": name, "role": user.role},
    )


# --- audit ----------------------------------------------------------------------------


AuditLimit = Annotated[int, Query(ge=1, le=10_000)]


def _audit_filter(default_limit: int) -> Callable[..., AuditQuery]:
    """A dependency reading the audit filters from the query string.

    Everyone sees their own actions; a role with ``audit:all`` sees everything, so the
    ``who`` filter of anyone else is replaced by their own name.
    """

    def dependency(
        request: Request,
        who: str | None = None,
        action: str | None = None,
        axis: str | None = None,
        result: str | None = None,
        since_s: float | None = None,
        until_s: float | None = None,
        limit: AuditLimit = default_limit,
    ) -> AuditQuery:
        if AUDIT_ALL not in _principal(request).permissions:
            who = _principal(request).user
        return AuditQuery(who, action, axis, result, since_s, until_s, limit)

    return dependency


@router.get("/api/audit", response_model=list[AuditEntry])
async def audit_entries(
    request: Request, query: Annotated[AuditQuery, Depends(_audit_filter(500))]
) -> list[dict[str, Any]]:
    """Audit entries, newest first (your own unless your role may read all)."""
    audit = _security(request).require_audit()
    await asyncio.to_thread(audit.flush)
    return await asyncio.to_thread(audit.query, query)


@router.get(
    "/api/audit.csv",
    response_class=PlainTextResponse,
    responses={200: {"content": {"text/csv": {}}}},
)
async def audit_csv(
    request: Request, query: Annotated[AuditQuery, Depends(_audit_filter(10_000))]
) -> PlainTextResponse:
    """The same entries as a CSV download."""
    audit = _security(request).require_audit()
    await asyncio.to_thread(audit.flush)
    text = await asyncio.to_thread(audit.csv, query)
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
    return PlainTextResponse(
        text,
        media_type="text/csv",
        headers={"Content-Disposition": f'attachment; filename="servotune-audit-{stamp}.csv"'},
    )
