"""Websocket authentication, and closing a user's websockets when their access ends.

The browser sends no custom header on a websocket and CORS does not apply to it, so a
page on any site could open ``ws://localhost:8000/ws`` with the victim's cookies. The
handshake is therefore accepted only when:

- the ``Origin`` is this server's own (``null`` and foreign origins are refused); a
  handshake without Origin comes from a non-browser client and must then carry a
  bearer token or a ticket (it has no ambient cookie authority to abuse);
- and, in exposed mode, the caller presents the session cookie, an
  ``Authorization: Bearer`` token (scripts), or ``?ticket=`` from
  ``POST /api/auth/ws-ticket``: single use, valid 10 s, bound to the caller's address
  (a long-lived token never goes in a URL: access logs keep URLs).

The endpoint (owned by the control module) calls :func:`authenticate_websocket` first,
accepts the socket itself, and registers a close callback with :func:`register_ws`.
Logout, password change, role change, user removal and token revocation call
:func:`close_websockets`, which runs the callbacks of that user (or that one session).

The registry is per process (a module-level ``WsRegistry``): the contract's
``register_ws(principal, close_callback)`` carries no app, and one process serves one
accounts database. Entries are removed by :func:`unregister_ws` when a socket ends.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import logging

from fastapi import WebSocket

from servotune.auth.authz import caller
from servotune.auth.middleware import client_address, own_origin
from servotune.auth.principal import VIEW, Principal
from servotune.auth.security import CloseCallback, SecurityState

logger = logging.getLogger(__name__)


def register_ws(
    security: SecurityState, principal: Principal, close_callback: CloseCallback
) -> None:
    """Remember an open websocket of this app; ``close_callback()`` closes it (sync or
    async)."""
    security.websockets.add(principal, close_callback)


def unregister_ws(
    security: SecurityState, principal: Principal, close_callback: CloseCallback
) -> None:
    """Forget a websocket that has ended (call it in the endpoint's ``finally``)."""
    del principal  # the callback identifies the entry; the principal keeps the API symmetric
    security.websockets.remove(close_callback)


def open_websockets(security: SecurityState, user: str) -> int:
    return security.websockets.count(user)


async def close_websockets(
    security: SecurityState, user: str, session_id: str | None = None
) -> int:
    """Close the user's websockets (only those of ``session_id`` when given); returns how many."""
    registry = security.websockets
    callbacks = registry.matching(user, session_id)
    for callback in callbacks:
        registry.remove(callback)
        try:
            result = callback()
            if inspect.isawaitable(result):
                await result
        except Exception:  # one broken socket must not keep the others open
            logger.warning("closing a websocket of %s failed", user, exc_info=True)
    return len(callbacks)


RECHECK_PERIOD_S = 2.0


async def recheck_websockets(security: SecurityState) -> None:
    """Forever: close sockets whose session or token has gone.

    Changes through the API close sockets at once. Every RECHECK_PERIOD_S this loop
    also closes (1008) the sockets of a session that expired while they were open (an
    hour without a request or a control action, or 12 hours old), and those of sessions
    and tokens that ``servotune users``/``tokens`` changed in another process.
    """
    while True:
        await asyncio.sleep(RECHECK_PERIOD_S)
        try:
            await _recheck(security)
        except RuntimeError:
            return  # the security state closed (shutdown)
        except Exception:  # one failed pass must not end the checks for good
            logger.exception("re-checking the open websockets failed")


async def _recheck(security: SecurityState) -> None:
    store = security.store
    if store is None:
        return
    for principal, callback in security.websockets.entries():
        session_id = principal.session_id or ""
        if principal.via == "session":
            alive = await security.db(store.session_by_public_id, session_id) is not None
        elif principal.via == "token":
            token_id = session_id.removeprefix("token:")
            alive = await security.db(store.token_alive, token_id)
        else:
            continue
        if not alive:
            security.websockets.remove(callback)
            with contextlib.suppress(Exception):
                result = callback()
                if inspect.isawaitable(result):
                    await result


async def authenticate_websocket(websocket: WebSocket) -> Principal | None:
    """The principal of a websocket handshake, or None after closing it with 1008.

    Does not accept the socket: the caller accepts it when this returns a principal.
    """
    security: SecurityState = websocket.app.state.security
    scope = websocket.scope
    address = client_address(scope)
    origin = websocket.headers.get("origin")
    ticket = websocket.query_params.get("ticket")
    bearer = websocket.headers.get("authorization", "")[:7].lower() == "bearer "

    async def refuse(why: str, who: str = "?") -> None:
        security.require_audit().record(
            who=who, action="websocket refused", address=address, result="refused", detail=why
        )
        with contextlib.suppress(RuntimeError):
            await websocket.close(code=1008, reason=why[:120])

    if origin is not None and origin.strip().lower() != own_origin(scope):
        await refuse(f"foreign Origin {origin[:80]!r}")
        return None
    if origin is None and not (ticket or bearer):
        await refuse("no Origin and no ticket or token")
        return None
    principal: Principal | None
    if ticket:
        principal = security.redeem_ticket(ticket, address)
        if principal is None:
            await refuse("unknown, used or expired ticket")
            return None
        if principal.via == "session" and principal.session_id is not None:
            # The session may have ended in the seconds since the ticket was issued.
            store = security.require_store()
            alive = await security.db(store.session_by_public_id, principal.session_id)
            if alive is None:
                await refuse("the ticket's session has ended", principal.user)
                return None
    else:
        principal, _ = await caller(websocket, security)
    if principal is None:
        await refuse("not logged in")
        return None
    if VIEW not in principal.permissions:
        await refuse("needs permission 'view'", principal.user)
        return None
    return principal
