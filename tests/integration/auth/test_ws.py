"""Websocket access control on a live server: Origin, Host, tickets, revocation, secrets.

Refused handshakes are checked with a raw HTTP/1.1 upgrade request, so the test sends
exactly the headers an attacker's page or script would (a client library adds its own).
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import logging
import os
import sqlite3
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path

import httpx
import pytest
import uvicorn
import websockets

from servotune.api.app import AppConfig, create_app
from servotune.auth.security import AUTH_DB, SecurityConfig
from tests.support.auth import PASSWORDS, TEST_PASSWORD_COST, make_accounts
from tests.support.servers import bound_socket, use_csrf_token
from tests.support.waiting import wait_for


@dataclass
class Live:
    app: object
    port: int
    origin: str
    ws_url: str
    data_dir: Path


@contextlib.asynccontextmanager
async def live(data_dir: Path, *, exposed: bool) -> AsyncIterator[Live]:
    if exposed:
        make_accounts(data_dir)
        security = SecurityConfig(mode="exposed", proxy=["127.0.0.1"], public_hosts=["127.0.0.1"])
    else:
        security = SecurityConfig()
    config = AppConfig(
        data_dir=data_dir,
        web_dir=data_dir / "no-web",
        security=security,
        password_cost=TEST_PASSWORD_COST,
    )
    app = create_app(config)
    sock = bound_socket()
    port = sock.getsockname()[1]
    server = uvicorn.Server(
        # log_config None: uvicorn's loggers (access log included) propagate to caplog.
        uvicorn.Config(
            app, host="127.0.0.1", port=port, log_level="info", lifespan="on", log_config=None
        )
    )
    task = asyncio.create_task(server.serve(sockets=[sock]))
    try:
        await wait_for(lambda: server.started, 20, "the server to start")
        origin = f"http://127.0.0.1:{port}"
        yield Live(app, port, origin, f"ws://127.0.0.1:{port}/ws", data_dir)
    finally:
        server.should_exit = True
        await task


async def handshake(port: int, headers: dict[str, str], path: str = "/ws") -> int:
    """Send a websocket upgrade by hand; the HTTP status of the answer (101 = accepted)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    lines = [
        f"GET {path} HTTP/1.1",
        "Upgrade: websocket",
        "Connection: Upgrade",
        f"Sec-WebSocket-Key: {base64.b64encode(os.urandom(16)).decode()}",
        "Sec-WebSocket-Version: 13",
    ]
    headers = {"Host": f"127.0.0.1:{port}", **headers}
    lines += [f"{k}: {v}" for k, v in headers.items()]
    writer.write(("\r\n".join(lines) + "\r\n\r\n").encode())
    await writer.drain()
    status_line = await asyncio.wait_for(reader.readline(), 10)
    writer.close()
    with contextlib.suppress(ConnectionError):
        await writer.wait_closed()
    return int(status_line.split()[1])


async def session_client(server: Live, user: str) -> httpx.AsyncClient:
    http = httpx.AsyncClient(base_url=server.origin, timeout=20)
    response = await http.post("/api/auth/login", json={"user": user, "password": PASSWORDS[user]})
    assert response.status_code == 200, response.text
    http.headers["X-CSRF-Token"] = response.json()["csrf_token"]
    return http


def cookie_header(http: httpx.AsyncClient) -> str:
    return f"servotune_session={http.cookies['servotune_session']}"


async def test_local_websocket_origin_and_host(tmp_path: Path) -> None:
    async with live(tmp_path, exposed=False) as server:
        own = {"Origin": server.origin}
        assert await handshake(server.port, own) == 101
        assert await handshake(server.port, {"Origin": "http://evil.example"}) == 403
        assert await handshake(server.port, {"Origin": "null"}) == 403
        assert await handshake(server.port, {}) == 403  # no Origin, no ticket, no token
        # DNS rebinding: the attacker's name with our own (rebound) address.
        rebound = {
            "Host": f"evil.example:{server.port}",
            "Origin": f"http://evil.example:{server.port}",
        }
        assert await handshake(server.port, rebound) == 403
        async with websockets.connect(server.ws_url, origin=server.origin) as ws:
            hello = await asyncio.wait_for(ws.recv(), 10)
            assert "hello" in str(hello)


async def test_exposed_websocket_needs_login_and_own_origin(tmp_path: Path) -> None:
    async with live(tmp_path, exposed=True) as server:
        assert await handshake(server.port, {"Origin": server.origin}) == 403
        http = await session_client(server, "victor")
        cookie = {"Cookie": cookie_header(http)}
        assert await handshake(server.port, {**cookie, "Origin": server.origin}) == 101
        assert await handshake(server.port, {**cookie, "Origin": "https://evil.example"}) == 403
        assert await handshake(server.port, {**cookie, "Origin": "null"}) == 403
        assert await handshake(server.port, cookie) == 403  # a cookie needs the Origin
        await http.aclose()


async def test_ticket_is_single_use(tmp_path: Path) -> None:
    async with live(tmp_path, exposed=True) as server:
        http = await session_client(server, "olga")
        ticket = (await http.post("/api/auth/ws-ticket")).json()["ticket"]
        path = f"/ws?ticket={ticket}"
        assert await handshake(server.port, {}, path) == 101
        assert await handshake(server.port, {}, path) == 403  # replay
        assert await handshake(server.port, {}, "/ws?ticket=made-up") == 403
        # A ticket dies with its session.
        ticket = (await http.post("/api/auth/ws-ticket")).json()["ticket"]
        await http.post("/api/auth/logout")
        assert await handshake(server.port, {}, f"/ws?ticket={ticket}") == 403
        await http.aclose()


async def _closed_with(ws: websockets.ClientConnection, timeout_s: float) -> int | None:
    """Read until the server closes; the close code (None when still open)."""
    try:
        async with asyncio.timeout(timeout_s):
            while True:
                await ws.recv()
    except websockets.ConnectionClosed as closed:
        return closed.rcvd.code if closed.rcvd else None
    except TimeoutError:
        return None


async def test_revocation_closes_the_users_websockets(tmp_path: Path) -> None:
    async with live(tmp_path, exposed=True) as server:
        admin = await session_client(server, "alice")
        victor = await session_client(server, "victor")
        olga = await session_client(server, "olga")
        headers = {"Cookie": cookie_header(victor)}
        other = {"Cookie": cookie_header(olga)}
        async with (
            websockets.connect(
                server.ws_url, origin=server.origin, additional_headers=headers
            ) as v1,
            websockets.connect(server.ws_url, origin=server.origin, additional_headers=other) as o1,
        ):
            await v1.recv()
            await o1.recv()
            response = await admin.patch("/api/users/victor", json={"role": "operator"})
            assert response.status_code == 200
            assert await _closed_with(v1, 5) == 1008
            assert await _closed_with(o1, 0.5) is None  # olga's socket stays open
        # Logout closes that session's sockets.
        async with websockets.connect(
            server.ws_url, origin=server.origin, additional_headers=other
        ) as o2:
            await o2.recv()
            assert (await olga.post("/api/auth/logout")).status_code == 204
            assert await _closed_with(o2, 5) == 1008
        # Token revocation closes a script's socket (bearer header, no Origin).
        created = await admin.post("/api/auth/tokens", json={"name": "probe", "user": "olga"})
        token = created.json()
        bearer = {"Authorization": f"Bearer {token['token']}"}
        async with websockets.connect(server.ws_url, additional_headers=bearer) as t1:
            await t1.recv()
            assert (await admin.delete(f"/api/auth/tokens/{token['id']}")).status_code == 204
            assert await _closed_with(t1, 5) == 1008
        for http in (admin, victor, olga):
            await http.aclose()


async def test_no_secret_in_logs_or_audit(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    secrets_seen: list[str] = list(PASSWORDS.values())
    async with live(tmp_path, exposed=True) as server:
        async with httpx.AsyncClient(base_url=server.origin, timeout=20) as stranger:
            # People type their password into the user field: it must not be written down.
            await stranger.post(
                "/api/auth/login", json={"user": PASSWORDS["olga"], "password": "x"}
            )
            await stranger.post("/api/auth/login", json={"user": "olga", "password": "typo-pw-1"})
            secrets_seen.append("typo-pw-1")
        admin = await session_client(server, "alice")
        secrets_seen += [admin.cookies["servotune_session"], admin.headers["X-CSRF-Token"]]
        created = await admin.post("/api/auth/tokens", json={"name": "ci", "user": "olga"})
        secrets_seen.append(created.json()["token"])
        new_user = {"name": "nina", "role": "viewer", "password": "nina-secret-pw-1"}
        secrets_seen.append(new_user["password"])
        assert (await admin.post("/api/users", json=new_user)).status_code == 201
        reset = {"password": "nina-secret-pw-2"}
        secrets_seen.append(reset["password"])
        assert (await admin.patch("/api/users/nina", json=reset)).status_code == 200
        ticket = (await admin.post("/api/auth/ws-ticket")).json()["ticket"]
        assert await handshake(server.port, {}, f"/ws?ticket={ticket}") == 101
        bearer = {"Authorization": f"Bearer {created.json()['token']}"}
        async with httpx.AsyncClient(base_url=server.origin, timeout=20) as script:
            assert (await script.post("/api/stop", headers=bearer)).status_code == 200
        await admin.post("/api/auth/logout")
        await admin.aclose()
        server.app.state.audit.flush()  # type: ignore[attr-defined]
        db = sqlite3.connect(tmp_path / AUTH_DB)
        audit = "\n".join(str(row) for row in db.execute("SELECT * FROM audit"))
        db.close()
    assert "login" in audit and "token create" in audit and "POST /api/stop" in audit
    # Everything the server side logged (the test's own HTTP client logs the headers it
    # received at DEBUG: that is the client's log, not the server's).
    client_loggers = ("httpcore", "httpx", "websockets.client")
    logs = "\n".join(
        f"{r.name} {r.getMessage()} {r.exc_text or ''}"
        for r in caplog.records
        if not r.name.startswith(client_loggers)
    )
    assert any(r.name.startswith(("uvicorn", "servotune")) for r in caplog.records)
    for secret in secrets_seen:
        assert secret not in audit, "a secret in the audit table"
        assert secret not in logs, "a secret in the log"
    # The access log keeps the ticket's URL: that is why a ticket is single use, valid
    # 10 s and bound to an address (a redeemed one is worthless). Never in the audit.
    assert ticket not in audit


async def test_local_mode_existing_clients_keep_working(tmp_path: Path) -> None:
    """The helper the existing suite uses: the CSRF token from /api/auth/session."""
    async with (
        live(tmp_path, exposed=False) as server,
        httpx.AsyncClient(base_url=server.origin, timeout=20) as http,
    ):
        assert (await http.post("/api/stop")).status_code == 403
        await use_csrf_token(http)
        assert (await http.post("/api/stop")).status_code == 200


async def test_cli_role_change_closes_websockets_of_a_running_server(tmp_path: Path) -> None:
    """``servotune users role`` runs in another process: the server notices within ~2 s."""
    from servotune.cli import main

    async with live(tmp_path, exposed=True) as server:
        victor = await session_client(server, "victor")
        headers = {"Cookie": cookie_header(victor)}
        async with websockets.connect(
            server.ws_url, origin=server.origin, additional_headers=headers
        ) as ws:
            await ws.recv()
            argv = ["users", "--data-dir", str(server.data_dir), "role", "victor", "operator"]
            assert await asyncio.to_thread(main, argv) == 0
            assert await _closed_with(ws, 15) == 1008
        assert (await victor.get("/api/axes")).status_code == 401
        await victor.aclose()
