"""Accounts, sessions, API tokens and the audit log (``servotune.api.auth_routes``)."""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field


class SessionInfo(BaseModel):
    """``GET /api/auth/session`` and ``POST /api/auth/login``: who the caller is (``user``
    null: nobody), how, and the CSRF token every state-changing call sends."""

    mode: Literal["local", "exposed"]
    user: str | None
    role: str | None
    permissions: list[str]
    csrf_token: str
    via: str | None = Field(
        default=None, description="session, token or local; null when nobody is logged in"
    )
    roles: list[str] = Field(description="every role, least privileged first")


class TicketReply(BaseModel):
    """``POST /api/auth/ws-ticket``: a single-use websocket ticket."""

    ticket: str
    expires_in_s: float


class TokenInfo(BaseModel):
    """An API token as listed (``GET /api/auth/tokens``): never its secret."""

    id: str
    user: str
    name: str
    role: str
    created_s: float = Field(description="unix seconds")
    expires_s: float = Field(description="unix seconds")
    last_used_s: float | None = Field(description="unix seconds; null: never used")


class NewToken(TokenInfo):
    """``POST /api/auth/tokens``: the new token with its secret, shown this once."""

    token: str


class UserInfo(BaseModel):
    """An account (``GET /api/users``, ``POST /api/users``)."""

    name: str
    role: str
    created_s: float = Field(description="unix seconds")


class UserChanged(BaseModel):
    """``PATCH /api/users/{name}``: the account's role after the change."""

    name: str
    role: str


class AuditEntry(BaseModel):
    """One entry of the audit log (``GET /api/audit``), newest first."""

    id: int
    t_s: float = Field(description="unix seconds")
    who: str
    action: str
    axis: str | None
    address: str | None
    before: str | None = Field(description="JSON of the state before, if recorded")
    after: str | None = Field(description="JSON of the state after, if recorded")
    result: str
    detail: str
