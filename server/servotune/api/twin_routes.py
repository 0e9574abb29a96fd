"""The 3D twin behind the dashboard's own origin: viser's page and a websocket proxy.

viser listens on 127.0.0.1 only and checks nothing (no authentication, no Origin), so
the browser never talks to it directly:

- ``GET /twin/`` serves viser's one-file client (the page of the exact viser version
  the server runs: client and server must match). ``GET /twin/axis/{id}`` redirects
  to it with camera parameters that frame that axis (viser's client takes
  ``initialCameraPosition`` / ``initialCameraLookAt`` from its URL); ``/twin/`` alone
  is the rig view of every axis.
- ``WS /twin`` pumps frames both ways to ``ws://127.0.0.1:<viser port>``, echoing the
  subprotocol viser selects (``viser-v<version>``). viser's client connects to its
  page URL with the query and the trailing slash removed: ``/twin/?...`` →
  ``ws(s)://<host>/twin``, hence this exact path.

Access: the same rules as the rest of the dashboard. The Host check and (exposed mode)
the login apply to every route through ``servotune.auth`` (middleware and the app-wide
permission table, where these routes need "view"); the websocket goes through
``servotune.auth.ws_auth.authenticate_websocket`` (Host, Origin, cookie or ticket) and
is registered with the session lifecycle like ``/ws``: logout, a password or role
change, token revocation (API or CLI), the end of the ticket's session and session
expiry close it (1008).

What the browser may say to viser: viser's client sends msgpack maps with a ``type``.
Only ``ALLOWED_CLIENT_MESSAGES`` pass (what the twin's camera needs); anything else is
dropped and written to the audit log (first of each type per connection), above all
``ShareUrlRequest``, which would make viser fork a tunnel to its public share service.
Text frames (viser's client sends none) close the socket with 1003, a frame over
``WS_MAX_MESSAGE_BYTES`` with 1009, more than ``WS_MAX_MESSAGES_PER_S`` a second
with 1008, as on ``/ws``.
"""

from __future__ import annotations

import asyncio
import contextlib
import gzip
import logging
import time
from collections import Counter

import msgspec
import websockets
from fastapi import APIRouter, HTTPException, Request, WebSocket
from fastapi.responses import RedirectResponse, Response
from starlette.requests import HTTPConnection
from starlette.websockets import WebSocketDisconnect
from websockets.asyncio.client import ClientConnection
from websockets.typing import Subprotocol

from servotune.api.ws import (
    CLOSE_MESSAGE_TOO_BIG,
    CLOSE_POLICY_VIOLATION,
    CLOSE_UNSUPPORTED_DATA,
    WS_MAX_MESSAGE_BYTES,
    WS_MAX_MESSAGES_PER_S,
)
from servotune.auth.principal import Principal
from servotune.auth.security import SecurityState
from servotune.auth.ws_auth import authenticate_websocket, register_ws, unregister_ws
from servotune.twin.service import SECRET_HEADER, Twin

logger = logging.getLogger(__name__)

router = APIRouter(prefix="", include_in_schema=False)

# Close code 1011: the twin is not available (a refusal is 1008, sent by the auth check).
UNAVAILABLE = 1011

# viser client -> server messages the twin needs: the camera pose of the viewer (viser
# keeps it per client and counts a client as connected after the first one). The twin
# has no GUI element, no click or drag binding and no upload; sharing is never wanted.
# Recorded from viser 1.1.1's browser client in tests/browser/test_twin.py.
ALLOWED_CLIENT_MESSAGES = frozenset({"ViewerCameraMessage"})
# Refused messages written to the audit log per connection (then only counted).
_AUDITED_REFUSALS = 20


def _twin(connection: HTTPConnection) -> Twin:
    twin: Twin | None = getattr(connection.app.state, "twin", None)
    if twin is None:
        raise HTTPException(status_code=503, detail="the 3D twin is not running")
    return twin


class _ClientPage:
    """viser's client page, read once (3 MB) and gzipped once, off the event loop."""

    def __init__(self) -> None:
        self._lock = asyncio.Lock()
        self._plain: bytes | None = None
        self._gzipped: bytes | None = None

    async def get(self, twin: Twin, accept_gzip: bool) -> tuple[bytes, bool]:
        async with self._lock:
            if self._plain is None:
                plain = await asyncio.to_thread(twin.client_page.read_bytes)
                self._gzipped = await asyncio.to_thread(gzip.compress, plain, 6)
                self._plain = plain
        if accept_gzip and self._gzipped is not None:
            return self._gzipped, True
        return self._plain, False


def _client_page(connection: HTTPConnection) -> _ClientPage:
    state = connection.app.state
    page: _ClientPage | None = getattr(state, "twin_page", None)
    if page is None:
        page = _ClientPage()
        state.twin_page = page
    return page


@router.get("/twin")
async def twin_no_slash() -> RedirectResponse:
    # The page must live under /twin/ so that its websocket goes to /twin.
    return RedirectResponse("/twin/", status_code=307)


@router.get("/twin/")
async def twin_page(request: Request) -> Response:
    """viser's client (rig view of every axis; camera parameters in the query)."""
    twin = _twin(request)
    body, gzipped = await _client_page(request).get(
        twin, "gzip" in request.headers.get("accept-encoding", "")
    )
    headers = {"Cache-Control": "no-cache", "Vary": "Accept-Encoding"}
    if gzipped:
        headers["Content-Encoding"] = "gzip"
    return Response(body, media_type="text/html; charset=utf-8", headers=headers)


@router.get("/twin/axis/{axis_id}")
async def twin_axis(axis_id: str, request: Request) -> RedirectResponse:
    """The 3D view of one axis: viser's page with a camera that frames it."""
    twin = _twin(request)
    try:
        view = twin.axis_view(axis_id)
    except KeyError:
        raise HTTPException(status_code=404, detail=f"no 3D view of axis {axis_id!r}") from None
    return RedirectResponse(f"/twin/?{view.query()}", status_code=307)


@router.websocket("/twin")
async def twin_socket(websocket: WebSocket) -> None:
    """Frames both ways between the browser and viser; the subprotocol is echoed."""
    principal = await authenticate_websocket(websocket)
    if principal is None:
        return  # closed with 1008 by the check
    twin: Twin | None = getattr(websocket.app.state, "twin", None)
    if twin is None:
        await websocket.close(code=UNAVAILABLE, reason="the 3D twin is not running")
        return
    offered = [Subprotocol(p) for p in websocket.scope.get("subprotocols", [])]
    try:
        upstream = await websockets.asyncio.client.connect(
            f"ws://127.0.0.1:{twin.port}",
            subprotocols=offered or None,
            additional_headers={SECRET_HEADER: twin.secret},
            compression=None,
            max_size=None,
            open_timeout=10,
        )
    except (OSError, TimeoutError, websockets.InvalidHandshake) as exc:
        logger.warning("twin websocket: viser did not accept: %s", exc)
        await websocket.close(code=UNAVAILABLE, reason="the 3D twin did not answer")
        return
    security: SecurityState = websocket.app.state.security
    session = _TwinSession(websocket, upstream, principal, security)
    register_ws(security, principal, session.end)
    twin.viewer_opened()
    try:
        await websocket.accept(subprotocol=upstream.subprotocol)
        await session.pump()
    finally:
        unregister_ws(security, principal, session.end)
        twin.viewer_closed()
        await upstream.close()


class _TwinSession:
    """One browser connection to viser through the proxy (see the module doc)."""

    def __init__(
        self,
        websocket: WebSocket,
        upstream: ClientConnection,
        principal: Principal,
        security: SecurityState,
    ) -> None:
        self.websocket = websocket
        self.upstream = upstream
        self.principal = principal
        self.security = security
        self.refused: Counter[str] = Counter()
        self._closing = False

    async def end(self, code: int = CLOSE_POLICY_VIOLATION, reason: str = "session ended") -> None:
        """Close both sides (the session lifecycle calls this: logout, revocation ...)."""
        if self._closing:
            return
        self._closing = True
        with contextlib.suppress(RuntimeError, WebSocketDisconnect):
            await self.websocket.close(code=code, reason=reason)
        await self.upstream.close()

    def _refuse(self, kind: str) -> None:
        self.refused[kind] += 1
        if sum(self.refused.values()) > _AUDITED_REFUSALS or self.refused[kind] > 1:
            return
        client = self.websocket.client
        self.security.require_audit().record(
            who=self.principal.user,
            action="twin message refused",
            address=client.host if client else "?",
            result="refused",
            detail=f"viser message {kind[:80]!r} is not allowed",
        )
        logger.warning("twin: %s sent viser a %s: dropped", self.principal.user, kind[:80])

    def _allowed(self, frame: bytes) -> bool:
        try:
            message = msgspec.msgpack.decode(frame)
        except msgspec.DecodeError:
            self._refuse("<not msgpack>")
            return False
        kind = message.get("type") if isinstance(message, dict) else None
        if not isinstance(kind, str) or kind not in ALLOWED_CLIENT_MESSAGES:
            self._refuse(str(kind))
            return False
        return True

    async def pump(self) -> None:
        websocket, upstream = self.websocket, self.upstream

        async def down() -> tuple[int, str]:
            """viser -> browser until viser closes; returns its close code and reason."""
            try:
                async for message in upstream:
                    if isinstance(message, bytes):
                        await websocket.send_bytes(message)
                    else:
                        await websocket.send_text(message)
            except websockets.ConnectionClosed:
                pass
            return (upstream.close_code or 1000, upstream.close_reason or "")

        async def up() -> tuple[int, str]:
            """browser -> viser until the browser goes away or breaks a limit."""
            window_start, count = time.monotonic(), 0
            while True:
                message = await websocket.receive()
                if message["type"] == "websocket.disconnect":
                    return (0, "")
                now = time.monotonic()
                if now - window_start >= 1.0:
                    window_start, count = now, 0
                count += 1
                if count > WS_MAX_MESSAGES_PER_S:
                    return (CLOSE_POLICY_VIOLATION, "too many messages")
                frame = message.get("bytes")
                if frame is None:
                    return (CLOSE_UNSUPPORTED_DATA, "text frames are not accepted")
                if len(frame) > WS_MAX_MESSAGE_BYTES:
                    return (CLOSE_MESSAGE_TOO_BIG, f"message over {WS_MAX_MESSAGE_BYTES} bytes")
                if self._allowed(frame):
                    await upstream.send(frame)

        tasks = [asyncio.create_task(down()), asyncio.create_task(up())]
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            first = done.pop()
            error = first.exception()
            if error is None:
                code, reason = first.result()
                if first is tasks[0]:
                    # viser ended the session (e.g. a version mismatch): tell the browser.
                    await self.end(code if code >= 1000 else 1000, reason)
                elif code:
                    logger.warning("twin websocket of %s closed: %s", self.principal.user, reason)
                    await self.end(code, reason)
            elif not self._closing and not isinstance(
                error, WebSocketDisconnect | websockets.ConnectionClosed
            ):
                logger.warning("twin websocket proxy: %s", error)
        finally:
            for task in tasks:
                task.cancel()
            for task in tasks:
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
