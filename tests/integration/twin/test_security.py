"""The 3D twin is no side door.

A real exposed server on a recorded simulated SLAP2 line with the twin on. viser's
client messages are msgpack maps with a ``type``; the tests speak that format as
viser's browser client does (``tests/support/twin_client.py``).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import sqlite3
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import msgspec
import viser
import websockets
from websockets.asyncio.client import ClientConnection
from websockets.typing import Origin, Subprotocol

from servotune.auth.audit import AuditQuery
from servotune.auth.security import AUTH_DB
from servotune.twin.service import SECRET_HEADER
from tests.support.control import ExposedServer, exposed_line_server, session_of
from tests.support.twin_client import ViserScene, until, viser_session
from tests.support.waiting import wait_for

SUBPROTOCOL = Subprotocol(f"viser-v{viser.__version__}")
CAMERA = {
    "type": "ViewerCameraMessage",
    "wxyz": [1.0, 0.0, 0.0, 0.0],
    "position": [0.0, -3.0, 0.0],
    "fov": 1.0,
    "near": 0.01,
    "far": 100.0,
    "image_height": 480,
    "image_width": 640,
    "look_at": [0.0, 0.0, 0.0],
    "up_direction": [0.0, 0.0, 1.0],
}


def children() -> set[int]:
    """The pids of this process' child processes (a share tunnel would be one)."""
    mine = os.getpid()
    found = set()
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        with contextlib.suppress(OSError):
            stat = Path(f"/proc/{entry}/stat").read_text()
            # pid (comm) state ppid ...: comm may hold spaces, so split after its ')'.
            if int(stat.rsplit(")", 1)[1].split()[1]) == mine:
                found.add(int(entry))
    return found


@contextlib.asynccontextmanager
async def twin_socket(
    server: ExposedServer,
    http: httpx.AsyncClient | None = None,
    *,
    query: str = "",
    headers: dict[str, str] | None = None,
) -> AsyncIterator[tuple[ViserScene, ClientConnection]]:
    """/twin as viser's browser client opens it: the session cookie (of ``http``) and
    the page's Origin, or the given headers (a token) without Origin."""
    extra = dict(headers or {})
    origin = None
    if http is not None:
        extra["Cookie"] = f"servotune_session={http.cookies['servotune_session']}"
        extra["X-Forwarded-For"] = http.headers["X-Forwarded-For"]
        origin = server.base_url
    url = server.base_url.replace("http", "ws", 1) + "/twin" + query
    async with viser_session(url, viser.__version__, origin, extra) as (scene, connection):
        await until(lambda: scene.replay_done, 20, "viser's scene replay")
        yield scene, connection


async def closed_code(connection: ClientConnection, timeout_s: float) -> int | None:
    """Read until the server closes; its close code (None: still open). Reading matters:
    a client that stops reading a busy stream never sees the close frame behind it."""
    if connection.close_code is not None:
        return connection.close_code
    try:
        async with asyncio.timeout(timeout_s):
            while True:
                await connection.recv()
    except websockets.ConnectionClosed:
        return connection.close_code
    except TimeoutError:
        return None
    except RuntimeError:  # another task reads this connection (twin_socket's receiver)
        try:
            await asyncio.wait_for(connection.wait_closed(), timeout_s)
        except TimeoutError:
            return None
        return connection.close_code


def refusals(server: ExposedServer, who: str) -> list[dict[str, Any]]:
    audit = server.app.state.audit
    audit.flush()
    return [r for r in audit.query(AuditQuery(action="twin message refused")) if r["who"] == who]


async def test_a_share_request_on_twin_is_refused_audited_and_forks_nothing(
    tmp_path: Path,
) -> None:
    async with exposed_line_server(tmp_path, [0], twin=True) as server:
        victor = await session_of(server, "victor")
        try:
            async with twin_socket(server, victor) as (_, connection):
                await asyncio.sleep(1.0)  # the hashing workers are up: count from here
                before = children()
                await connection.send(msgspec.msgpack.encode(CAMERA))
                for _ in range(6):
                    await connection.send(msgspec.msgpack.encode({"type": "ShareUrlRequest"}))
                await connection.send(
                    msgspec.msgpack.encode({"type": "FileTransferStartUpload", "x": 1})
                )
                await asyncio.sleep(1.5)
                assert children() <= before, "a process was forked"
                twin = server.app.state.twin
                assert twin.share_requests_refused == 0  # never reached viser
                rows = refusals(server, "victor")
                details = " ".join(r["detail"] for r in rows)
                assert "ShareUrlRequest" in details and "FileTransferStartUpload" in details
                assert len(rows) == 2  # the first of each kind; the rest only counted
                # Refused messages are dropped; the viewer's socket stays open.
                await connection.send(msgspec.msgpack.encode(CAMERA))
                assert await closed_code(connection, 0.5) is None
                # viser itself cannot start a tunnel either (its handler is gone, the
                # method refuses), however it is asked.
                assert twin._server.request_share_url() is None
                assert twin.share_requests_refused == 1
                await asyncio.sleep(0.5)
                assert children() <= before
        finally:
            await victor.aclose()


async def test_viser_port_answers_only_the_dashboards_proxy(tmp_path: Path) -> None:
    async with exposed_line_server(tmp_path, [0], twin=True) as server:
        twin = server.app.state.twin
        url = f"ws://127.0.0.1:{twin.port}"
        frames = 0
        async with websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=None) as local:
            try:
                async with asyncio.timeout(10):
                    async for _ in local:
                        frames += 1
            except websockets.ConnectionClosed:
                pass
            assert local.close_code == 1008
        assert frames == 0, "a local user without the secret got scene frames"
        assert twin.refused_connections == 1
        wrong = {SECRET_HEADER: "guess"}
        async with websockets.connect(
            url, subprotocols=[SUBPROTOCOL], additional_headers=wrong, max_size=None
        ) as guessed:
            assert await closed_code(guessed, 10) == 1008
        # The proxy's own connection (what /twin does) is served.
        right = {SECRET_HEADER: twin.secret}
        async with viser_session(url, viser.__version__, None, right) as (scene, _):
            await until(lambda: scene.replay_done, 20, "the replay through the secret")


async def test_twin_closes_with_the_session_like_ws(tmp_path: Path) -> None:
    from servotune.cli import main

    async with exposed_line_server(tmp_path, [0], twin=True) as server:
        victor = await session_of(server, "victor", "192.0.2.40")
        olga = await session_of(server, "olga", "192.0.2.41")
        alice = await session_of(server, "alice", "192.0.2.42")
        try:
            # Logout.
            async with twin_socket(server, victor) as (_, connection):
                assert (await victor.post("/api/auth/logout")).status_code == 204
                assert await closed_code(connection, 5) == 1008
            # Password change.
            async with twin_socket(server, olga) as (_, connection):
                change = {
                    "current_password": "olga-operator-pw-456",
                    "new_password": "olga-operator-pw-457",
                }
                assert (await olga.post("/api/auth/password", json=change)).status_code == 204
                assert await closed_code(connection, 5) == 1008
            # Token revocation through the API.
            created = await alice.post("/api/auth/tokens", json={"name": "twin", "user": "oscar"})
            token = created.json()
            bearer = {"Authorization": f"Bearer {token['token']}"}
            async with twin_socket(server, headers=bearer) as (_, connection):
                revoked = await alice.delete(f"/api/auth/tokens/{token['id']}")
                assert revoked.status_code == 204
                assert await closed_code(connection, 5) == 1008
            # Token revocation with the CLI (another process: the periodic re-check).
            created = await alice.post("/api/auth/tokens", json={"name": "cli", "user": "oscar"})
            token = created.json()
            bearer = {"Authorization": f"Bearer {token['token']}"}
            async with twin_socket(server, headers=bearer) as (_, connection):
                argv = ["tokens", "--data-dir", str(tmp_path / "data"), "revoke", token["id"]]
                assert await asyncio.to_thread(main, argv) == 0
                assert await closed_code(connection, 15) == 1008
            # A ticket's socket ends with the ticket's session.
            ticket = (await alice.post("/api/auth/ws-ticket")).json()["ticket"]
            forwarded = {"X-Forwarded-For": "192.0.2.42"}
            async with twin_socket(server, query=f"?ticket={ticket}", headers=forwarded) as (
                _,
                connection,
            ):
                assert (await alice.post("/api/auth/logout")).status_code == 204
                assert await closed_code(connection, 5) == 1008
        finally:
            for http in (victor, olga, alice):
                await http.aclose()


async def test_open_sockets_close_when_the_session_expires(tmp_path: Path) -> None:
    """Idle (1 h without a request) and absolute (12 h) limits end /ws and /twin too:
    a periodic check closes them (finding 7: they streamed on until a REST call)."""
    async with exposed_line_server(tmp_path, [0], twin=True) as server:
        victor = await session_of(server, "victor", "192.0.2.50")
        olga = await session_of(server, "olga", "192.0.2.51")
        ws_url = server.base_url.replace("http", "ws", 1) + "/ws"
        try:
            for http, column, age_s in ((victor, "last_seen_s", 3700), (olga, "created_s", 43300)):
                headers = {
                    "Cookie": f"servotune_session={http.cookies['servotune_session']}",
                    "X-Forwarded-For": http.headers["X-Forwarded-For"],
                }
                async with (
                    twin_socket(server, http) as (_, twin),
                    websockets.connect(
                        ws_url, origin=Origin(server.base_url), additional_headers=headers
                    ) as ws,
                ):
                    await ws.recv()
                    user = "victor" if http is victor else "olga"
                    db = sqlite3.connect(tmp_path / "data" / AUTH_DB)
                    with db:
                        db.execute(
                            f"UPDATE sessions SET {column} = {column} - ? WHERE user = ?",
                            (age_s, user),
                        )
                    db.close()
                    started = time.monotonic()
                    assert await closed_code(twin, 10) == 1008
                    assert await closed_code(ws, 10) == 1008
                    print(f"{user}: closed {time.monotonic() - started:.1f} s after expiry")
        finally:
            await victor.aclose()
            await olga.aclose()


async def test_twin_limits_messages_like_ws(tmp_path: Path) -> None:
    async with exposed_line_server(tmp_path, [0], twin=True) as server:
        olga = await session_of(server, "olga")
        try:
            async with twin_socket(server, olga) as (_, connection):
                camera = msgspec.msgpack.encode(CAMERA)
                with contextlib.suppress(websockets.ConnectionClosed):
                    for _ in range(400):
                        await connection.send(camera)
                assert await closed_code(connection, 10) == 1008
            async with twin_socket(server, olga) as (_, connection):
                await connection.send("text")
                assert await closed_code(connection, 10) == 1003
            async with twin_socket(server, olga) as (_, connection):
                await connection.send(b"\x81" + bytes(70 * 1024))
                assert await closed_code(connection, 10) == 1009
        finally:
            await olga.aclose()


async def test_the_proxy_still_serves_viewer_cameras(tmp_path: Path) -> None:
    """The allowed message reaches viser: the proxy's allowlist is no blanket drop."""
    async with exposed_line_server(tmp_path, [0], twin=True) as server:
        victor = await session_of(server, "victor")
        try:
            async with twin_socket(server, victor) as (_, connection):
                twin = server.app.state.twin
                await connection.send(msgspec.msgpack.encode(CAMERA))

                def viser_clients() -> int:
                    return len(twin._server.get_clients())

                await wait_for(lambda: viser_clients() == 1, 10, "viser counting the camera")
                assert not refusals(server, "victor")
        finally:
            await victor.aclose()
