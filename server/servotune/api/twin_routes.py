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
``servotune.auth.ws_auth.authenticate_websocket`` (Host, Origin, cookie or ticket).
"""

from __future__ import annotations

import asyncio
import contextlib
import gzip
import logging

import websockets
from fastapi import APIRouter, HTTPException, Request, WebSocket
from fastapi.responses import RedirectResponse, Response
from starlette.requests import HTTPConnection
from starlette.websockets import WebSocketDisconnect
from websockets.asyncio.client import ClientConnection
from websockets.typing import Subprotocol

from servotune.auth.ws_auth import authenticate_websocket
from servotune.twin import Twin

logger = logging.getLogger(__name__)

router = APIRouter(prefix="", include_in_schema=False)

# Close code 1011: the twin is not available (a refusal is 1008, sent by the auth check).
UNAVAILABLE = 1011


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
    if await authenticate_websocket(websocket) is None:
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
            compression=None,
            max_size=None,
            open_timeout=10,
        )
    except (OSError, TimeoutError, websockets.InvalidHandshake) as exc:
        logger.warning("twin websocket: viser did not accept: %s", exc)
        await websocket.close(code=UNAVAILABLE, reason="the 3D twin did not answer")
        return
    twin.viewer_opened()
    try:
        await websocket.accept(subprotocol=upstream.subprotocol)
        await _pump(websocket, upstream)
    finally:
        twin.viewer_closed()
        await upstream.close()


async def _pump(websocket: WebSocket, upstream: ClientConnection) -> None:
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
        """browser -> viser until the browser goes away."""
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                return (0, "")
            if message.get("bytes") is not None:
                await upstream.send(message["bytes"])
            elif message.get("text") is not None:
                await upstream.send(message["text"])

    tasks = [asyncio.create_task(down()), asyncio.create_task(up())]
    try:
        done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        first = done.pop()
        if first is tasks[0] and first.exception() is None:
            # viser ended the session (e.g. a version mismatch): tell the browser why.
            code, reason = first.result()
            with contextlib.suppress(RuntimeError, WebSocketDisconnect):
                await websocket.close(code=code if code >= 1000 else 1000, reason=reason)
        elif first.exception() is not None and not isinstance(
            first.exception(), WebSocketDisconnect | websockets.ConnectionClosed
        ):
            logger.warning("twin websocket proxy: %s", first.exception())
    finally:
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
