"""The websocket ``/ws``: telemetry out, control-lock messages in (``servotune.schema``).

Each connection is one *client* of the control lock (``servotune.hub.control_lock``): it learns
its client id in ``welcome`` and renews its lease with ``heartbeat`` messages.

Robustness: the client only ever sends small JSON text messages. A text message over
``WS_MAX_MESSAGE_BYTES`` closes the connection with 1009 (uvicorn refuses larger frames
itself: ``ws_max_size`` in ``cli.py``); a binary frame with 1003; more than
``WS_MAX_MESSAGES_PER_S`` messages a second with 1008. Malformed JSON is ignored.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Annotated

from fastapi import APIRouter, WebSocket, WebSocketDisconnect
from pydantic import Field, TypeAdapter, ValidationError
from starlette.websockets import WebSocketState

from servotune.api.tcp_alive import last_ack_s
from servotune.auth.authz import REAUTH_DETAIL, password_fresh
from servotune.auth.principal import FORCE_CONTROL, Principal
from servotune.auth.security import SecurityState
from servotune.auth.ws_auth import authenticate_websocket, register_ws, unregister_ws
from servotune.hub.control_client import ControlClient
from servotune.hub.control_lock import ControlLock
from servotune.hub.hub import Hub
from servotune.hub.state import ClientQueue
from servotune.schema import ClientStats, ControlReply, Heartbeat, Ping

# The same union as schema.ClientMessage | schema.ControlClientMessage, flattened so
# pydantic can discriminate on ``type`` in one pass.
from servotune.schema import (  # isort: skip
    AnswerControl,
    ForceControl,
    ReleaseControl,
    RequestControl,
    TakeControl,
)

logger = logging.getLogger(__name__)

WS_MAX_MESSAGE_BYTES = 64 * 1024
WS_MAX_MESSAGES_PER_S = 200
CLOSE_UNSUPPORTED_DATA = 1003
CLOSE_POLICY_VIOLATION = 1008
CLOSE_MESSAGE_TOO_BIG = 1009

router = APIRouter()

_incoming = TypeAdapter(
    Annotated[
        Ping
        | Heartbeat
        | TakeControl
        | RequestControl
        | ReleaseControl
        | AnswerControl
        | ForceControl,
        Field(discriminator="type"),
    ]
)


async def authenticate(websocket: WebSocket) -> Principal | None:
    """Who is connecting (Host / Origin / cookie / ticket checks), or None: then the
    socket is already closed with 1008."""
    return await authenticate_websocket(websocket)


_Registration = tuple[SecurityState, Principal, Callable[[], Awaitable[None]]]


def register(
    websocket: WebSocket, principal: Principal, close: Callable[[], Awaitable[None]]
) -> _Registration:
    """Remember the socket so logout and revocation close it (its axes then lapse)."""
    security: SecurityState = websocket.app.state.security
    register_ws(security, principal, close)
    return (security, principal, close)


def unregister(handle: _Registration) -> None:
    unregister_ws(*handle)


class _AbuseError(Exception):
    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason


@router.websocket("/ws")
async def websocket_endpoint(websocket: WebSocket) -> None:
    """Telemetry and state stream plus the control lock; shapes in ``servotune.schema``."""
    principal = await authenticate(websocket)
    if principal is None:
        return
    control: ControlLock = websocket.app.state.control
    beat = websocket.query_params.get("beat")
    if beat is not None:
        await _heartbeat_socket(websocket, control, principal, beat)
        return
    if websocket.client_state == WebSocketState.CONNECTING:
        await websocket.accept()
    hub: Hub = websocket.app.state.hub
    queue = hub.subscribe()
    address = websocket.client.host if websocket.client else "?"

    async def close(code: int = CLOSE_POLICY_VIOLATION, reason: str = "session ended") -> None:
        with contextlib.suppress(RuntimeError, WebSocketDisconnect):
            await websocket.close(code=code, reason=reason)

    handle = register(websocket, principal, close)
    client: ControlClient | None = None
    try:
        await websocket.send_text(hub.hello().model_dump_json())
        # welcome goes through the queue, so on the wire it follows the snapshot sent
        # below: a client reads the snapshot's control_status lines as "held by
        # someone" until welcome tells it its own tag (a new tab holds nothing yet).
        client = control.connect(principal, address, lambda t: queue.put(t, droppable=False))
        client.alive = _liveness(websocket)
        client.probe = lambda: queue.put(
            ClientStats(sent=queue.sent, dropped=queue.dropped).model_dump_json(),
            droppable=False,
        )
        for text in hub.snapshot_messages():
            await websocket.send_text(text)
        for text in control.snapshot():
            await websocket.send_text(text)
        await _serve(websocket, queue, control, client)
    except _AbuseError as abuse:
        logger.warning("websocket from %s closed: %s", address, abuse.reason)
        await close(abuse.code, abuse.reason)
    except WebSocketDisconnect:
        pass
    finally:
        hub.unsubscribe(queue)
        if client is not None:
            control.disconnect(client)
        unregister(handle)


async def _active(websocket: WebSocket, principal: Principal) -> None:
    """A control action is the user's activity: the session is not idle (watching the
    stream and heartbeats are not; docs/remote-lab.md)."""
    if principal.via == "session" and principal.session_id is not None:
        security: SecurityState = websocket.app.state.security
        await security.db(security.require_store().touch_session, principal.session_id)


async def _password_fresh(websocket: WebSocket, client: ControlClient) -> bool:
    """Whether the client's session typed its password recently enough for a forced
    hand-over (sessions only; a refusal is audited)."""
    principal = client.principal
    if principal.via != "session" or principal.session_id is None:
        return True
    security: SecurityState = websocket.app.state.security
    store = security.require_store()
    session = await security.db(store.session_by_public_id, principal.session_id)
    if session is not None and password_fresh(session):
        return True
    security.require_audit().record(
        who=principal.user,
        action="force_control",
        address=client.address,
        result="refused",
        detail="password required again" if session is not None else "session ended",
    )
    return False


def _liveness(websocket: WebSocket) -> Callable[[], float | None] | None:
    """How to ask when this socket's far end last acknowledged (``api.tcp_alive``), or
    None behind a reverse proxy (the proxy acknowledges, not the browser's machine)."""
    security: SecurityState | None = getattr(websocket.app.state, "security", None)
    if security is not None and security.config.proxy:
        return None
    server, client = websocket.scope.get("server"), websocket.scope.get("client")
    if not server or not client:
        return None
    local, peer = (server[0], int(server[1])), (client[0], int(client[1]))
    return lambda: last_ack_s(local, peer)


async def _heartbeat_socket(
    websocket: WebSocket, control: ControlLock, principal: Principal, client_id: str
) -> None:
    """``/ws?beat=<client_id>``: the heartbeats of a tab's worker, on a socket of their own
    (docs/control.md, "The dead-man"). Only the same user's open tab can be beaten for;
    only ``heartbeat`` messages count; nothing is sent back. Its end changes nothing by
    itself: the lease runs out when the heartbeats stop (a closed tab also closes its
    main socket, which lapses at once)."""
    client = control.client(client_id)
    if client is None or client.user != principal.user:
        with contextlib.suppress(RuntimeError, WebSocketDisconnect):
            await websocket.close(code=CLOSE_POLICY_VIOLATION, reason="no such client")
        return
    if websocket.client_state == WebSocketState.CONNECTING:
        await websocket.accept()
    window_start, count = time.monotonic(), 0
    try:
        while client.connected:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                return
            text = message.get("text")
            now = time.monotonic()
            if now - window_start >= 1.0:
                window_start, count = now, 0
            count += 1
            if text is None or len(text) > 200 or count > WS_MAX_MESSAGES_PER_S:
                break
            try:
                parsed = _incoming.validate_json(text)
            except ValidationError:
                continue
            if isinstance(parsed, Heartbeat):
                client.beats += 1
                control.heartbeat(client, parsed.page_age_ms)
    except WebSocketDisconnect:
        return
    with contextlib.suppress(RuntimeError, WebSocketDisconnect):
        await websocket.close(code=CLOSE_POLICY_VIOLATION, reason="heartbeats only")


async def _serve(
    websocket: WebSocket, queue: ClientQueue, control: ControlLock, client: ControlClient
) -> None:
    async def sender() -> None:
        while True:
            await websocket.send_text(await queue.get())

    async def receiver() -> None:
        window_start, count = time.monotonic(), 0
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                raise WebSocketDisconnect(message.get("code", 1000))
            text = message.get("text")
            if text is None:
                raise _AbuseError(CLOSE_UNSUPPORTED_DATA, "binary frames are not accepted")
            if len(text) > WS_MAX_MESSAGE_BYTES // 4 and len(text.encode()) > WS_MAX_MESSAGE_BYTES:
                too_big = f"message over {WS_MAX_MESSAGE_BYTES} bytes"
                raise _AbuseError(CLOSE_MESSAGE_TOO_BIG, too_big)
            now = time.monotonic()
            if now - window_start >= 1.0:
                window_start, count = now, 0
            count += 1
            if count > WS_MAX_MESSAGES_PER_S:
                raise _AbuseError(CLOSE_POLICY_VIOLATION, "too many messages")
            try:
                parsed = _incoming.validate_json(text)
            except ValidationError:
                continue
            if isinstance(parsed, Heartbeat):
                control.heartbeat(client, parsed.page_age_ms)
            elif isinstance(parsed, Ping):
                stats = ClientStats(sent=queue.sent, dropped=queue.dropped)
                queue.put(stats.model_dump_json(), droppable=False)
            elif (
                isinstance(parsed, ForceControl)
                and FORCE_CONTROL in client.principal.permissions
                and not await _password_fresh(websocket, client)
            ):
                # The REST rule for dangerous actions (authz.password_fresh), here too.
                reply = ControlReply(
                    axis=parsed.axis, action="force", ok=False, message=REAUTH_DETAIL
                )
                queue.put(reply.model_dump_json(), droppable=False)
            else:
                # Not awaited here: a hand-over waits for a STOP, and heartbeats must keep
                # being read meanwhile. The control lock owns the task (it finishes
                # even if this socket closes).
                control.submit(client, parsed)
                await _active(websocket, client.principal)

    tasks = [asyncio.create_task(sender()), asyncio.create_task(receiver())]
    try:
        done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        for task in done:
            error = task.exception()
            if error is None or isinstance(error, WebSocketDisconnect):
                continue
            if websocket.application_state == WebSocketState.DISCONNECTED:
                # Closed by the server from another task (logout, revocation, expiry)
                # while the sender was sending: how this connection ends, not an error.
                continue
            raise error
    finally:
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
