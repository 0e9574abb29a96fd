"""The server closing a websocket is an end, not an error (uvicorn
logged "Exception in ASGI application" when the server closed a /ws).

When logout, revocation or the session re-check closes a socket (from another task)
while its sender is streaming, the sender's next send meets a closed socket. That is
how the connection ends; nothing may be logged as a server error.
"""

from __future__ import annotations

import asyncio
import logging
from pathlib import Path

import websockets
from websockets.typing import Origin

from servotune.auth.ws_auth import close_websockets
from tests.support.control import control_server


class _Records(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


async def test_a_socket_closed_by_the_server_while_streaming_logs_no_error(
    tmp_path: Path,
) -> None:
    async with control_server(tmp_path) as server:
        # uvicorn configured its loggers (propagate off): listen on them directly.
        records = _Records()
        loggers = [logging.getLogger(n) for n in ("uvicorn.error", "uvicorn", "servotune")]
        for logger in loggers:
            logger.addHandler(records)
        try:
            hub = server.app.state.hub
            security = server.app.state.security
            for _ in range(5):
                async with websockets.connect(
                    server.ws_url, origin=Origin(server.base_url), max_size=None
                ) as ws:
                    await ws.recv()
                    # A backlog for the sender: it is sending when the close comes.
                    for i in range(2000):
                        hub._broadcast(f'{{"type": "event", "n": {i}}}', droppable=False)
                    await asyncio.sleep(0)
                    assert await close_websockets(security, "local") == 1
                    try:
                        async with asyncio.timeout(10):
                            while True:
                                await ws.recv()
                    except websockets.ConnectionClosed as closed:
                        assert closed.rcvd is not None and closed.rcvd.code == 1008
            await asyncio.sleep(0.5)
        finally:
            for logger in loggers:
                logger.removeHandler(records)
    errors = [r for r in records.records if r.levelno >= logging.ERROR]
    assert not errors, [f"{r.name}: {r.getMessage()}\n{r.exc_text}" for r in errors]
