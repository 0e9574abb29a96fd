"""Helpers for the control-lock tests and ``scripts/perf_deadman.py``.

``recorded_line``: a simulated SLAP2 line behind a ``WireRecorder`` (``sim_lines``: every
line the host sent, with the time it reached the simulated device and the module
selected then), in a simulator process of its own. ``RawWebsocket`` is a minimal websocket
client on a raw TCP socket, so a test can vanish without a close frame (RST via
SO_LINGER 0) or simply go silent. ``Operator`` is a well-behaved tab (heartbeats).
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import functools
import json
import os
import shutil
import socket
import struct
import subprocess
import time
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import uvicorn
import websockets
from websockets.typing import Origin

from servotune.api.app import AppConfig, create_app
from servotune.auth.passwords import PasswordCost
from servotune.config import LinkSpec
from servotune.devices.slap2.sim.line import Slap2Line
from servotune.hub.control_client import CLIENT_HEADER, ControlSettings
from servotune.sim.process import Remote
from tests.support.servers import bound_socket, use_csrf_token
from tests.support.sim_builders import WireRecorder, recorded_slap2_line
from tests.support.sim_lines import simulator_process

CR = 0x0D
CTRL_X = 0x18


@contextlib.contextmanager
def recorded_line(tmp_path: Path, addresses: list[int]) -> Iterator[tuple[Remote, Remote]]:
    """SLAP2 modules at ``addresses`` behind a ``WireRecorder``, in a simulator process
    of their own (``tests.support.sim_lines.simulator_process``): its ``PtySimulator`` and the
    recorder as ``Remote`` views."""
    build = functools.partial(recorded_slap2_line, addresses, tmp_path)
    with simulator_process("slap2-recorded", build, 19200, str(tmp_path / "tty")) as pair:
        yield pair


@dataclass
class Server:
    base_url: str
    ws_url: str
    port: int
    app: Any
    wire: WireRecorder
    client: httpx.AsyncClient

    @property
    def bus(self) -> Slap2Line:
        return self.wire.bus


@contextlib.asynccontextmanager
async def control_server(
    tmp_path: Path,
    settings: ControlSettings | None = None,
    *,
    autopilot: bool = False,
    ws_max_size: int | None = None,
    web_dir: Path | None = None,
    addresses: list[int] | None = None,
    clock: Callable[[], float] = time.monotonic,
) -> AsyncIterator[Server]:
    """A real uvicorn server on a free port, on a recorded simulated SLAP2 line;
    ``clock``: the control lock's (see ``StepClock``)."""
    addresses = addresses or [0, 1]
    with recorded_line(tmp_path, addresses) as (simulator, wire):
        spec = LinkSpec("slap2", simulator.path, "line", simulator.baud, addresses, 512)
        config = AppConfig(
            links=[spec],
            data_dir=tmp_path / "data",
            web_dir=web_dir or tmp_path / "no-web",
            autopilot=autopilot,
            control=settings or ControlSettings(),
            control_clock=clock,
        )
        app = create_app(config)
        sock = bound_socket()
        port = sock.getsockname()[1]
        options: dict[str, Any] = {}
        if ws_max_size is not None:
            options["ws_max_size"] = ws_max_size
        server = uvicorn.Server(
            uvicorn.Config(
                app, host="127.0.0.1", port=port, log_level="warning", lifespan="on", **options
            )
        )
        task = asyncio.create_task(server.serve(sockets=[sock]))
        try:
            deadline = time.monotonic() + 10
            while not server.started:
                assert time.monotonic() < deadline, "the server did not start"
                await asyncio.sleep(0.02)
            base = f"http://127.0.0.1:{port}"
            async with httpx.AsyncClient(base_url=base, timeout=10) as client:
                await use_csrf_token(client)
                for address in addresses:
                    for _ in range(250):
                        response = await client.get(f"/api/axes/line-{address}/state")
                        if response.status_code == 200:
                            break
                        await asyncio.sleep(0.02)
                yield Server(base, f"ws://127.0.0.1:{port}/ws", port, app, wire, client)
        finally:
            server.should_exit = True
            await task


@dataclass
class ExposedServer:
    base_url: str
    app: Any
    wire: WireRecorder | None = None


@contextlib.asynccontextmanager
async def served(app: Any, wire: WireRecorder | None = None) -> AsyncIterator[ExposedServer]:
    """``app`` on a real uvicorn on a free port, configured as ``servotune serve`` runs
    it (forwarded headers left to servotune's middleware, a bounded graceful shutdown);
    uvicorn's records propagate, so caplog sees them."""
    from servotune.cli import GRACEFUL_SHUTDOWN_S

    sock = bound_socket()

    port = sock.getsockname()[1]
    server = uvicorn.Server(
        uvicorn.Config(
            app,
            host="127.0.0.1",
            port=port,
            log_level="warning",
            lifespan="on",
            proxy_headers=False,
            timeout_graceful_shutdown=GRACEFUL_SHUTDOWN_S,
            log_config=None,
        )
    )
    task = asyncio.create_task(server.serve(sockets=[sock]))
    try:
        deadline = time.monotonic() + 30
        while not server.started:
            assert time.monotonic() < deadline, "the server did not start"
            await asyncio.sleep(0.02)
        yield ExposedServer(f"http://127.0.0.1:{port}", app, wire)
    finally:
        server.should_exit = True
        await task


def exposed_security() -> Any:
    """Exposed mode behind a TLS "proxy" on 127.0.0.1: each client names its address
    with ``X-Forwarded-For`` and reaches the server as ``http://127.0.0.1``."""
    from servotune.auth.security import SecurityConfig

    return SecurityConfig(mode="exposed", proxy=["127.0.0.1"], public_hosts=["127.0.0.1"])


@contextlib.asynccontextmanager
async def exposed_line_server(
    tmp_path: Path,
    addresses: list[int],
    *,
    twin: bool = False,
    password_cost: PasswordCost | None = None,
) -> AsyncIterator[ExposedServer]:
    """A real server in exposed mode (the accounts of ``tests/support/auth.py``) on a
    recorded simulated SLAP2 line (``exposed_security``, ``served``). Passwords at
    ``password_cost`` (accounts and app; None: ``TEST_PASSWORD_COST``)."""
    from tests.support.auth import TEST_PASSWORD_COST, make_accounts

    cost = password_cost or TEST_PASSWORD_COST
    make_accounts(tmp_path / "data", cost=cost)
    with recorded_line(tmp_path, addresses) as (simulator, wire):
        spec = LinkSpec("slap2", simulator.path, "line", simulator.baud, addresses, 512)
        config = AppConfig(
            links=[spec],
            data_dir=tmp_path / "data",
            web_dir=tmp_path / "no-web",
            security=exposed_security(),
            twin=twin,
            password_cost=cost,
        )
        async with served(create_app(config), wire) as server:
            yield server


async def session_of(
    server: ExposedServer, user: str, address: str = "192.0.2.10"
) -> httpx.AsyncClient:
    """A logged-in client of ``user`` (tests/support/auth.py's passwords) from ``address``."""
    from tests.support.auth import PASSWORDS

    http = httpx.AsyncClient(
        base_url=server.base_url, timeout=60, headers={"X-Forwarded-For": address}
    )
    response = await http.post("/api/auth/login", json={"user": user, "password": PASSWORDS[user]})
    assert response.status_code == 200, response.text
    http.headers["X-CSRF-Token"] = response.json()["csrf_token"]
    return http


@dataclass
class Operator:
    """One browser tab: a websocket that heartbeats, plus REST with its client id."""

    server: Server
    socket: Any = None
    client_id: str = ""
    tag: str = ""
    messages: list[dict[str, Any]] = field(default_factory=list)
    heartbeats: bool = True
    _tasks: list[asyncio.Task[None]] = field(default_factory=list)

    async def __aenter__(self) -> Operator:
        self.socket = await websockets.connect(
            self.server.ws_url, max_size=None, origin=Origin(self.server.base_url)
        )
        while not self.client_id:
            message = json.loads(await asyncio.wait_for(self.socket.recv(), 5))
            if message["type"] == "welcome":
                self.client_id, self.tag = message["client_id"], message["client_tag"]
            elif message["type"] != "telemetry":
                # The snapshot (hello, axis and control status) arrives before welcome.
                # Kept: an axis the autopilot took before this tab connected is in it,
                # and nowhere else (dropping it made a test wait 30 s for nothing).
                self.messages.append(message)
        self._tasks = [asyncio.create_task(self._read()), asyncio.create_task(self._beat())]
        return self

    async def __aexit__(self, *exc: object) -> None:
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        await self.socket.close()

    async def _read(self) -> None:
        async for raw in self.socket:
            message = json.loads(raw)
            if message["type"] != "telemetry":
                self.messages.append(message)

    async def _beat(self) -> None:
        while True:
            if self.heartbeats:
                await self.socket.send(json.dumps({"type": "heartbeat"}))
            await asyncio.sleep(0.1)

    async def send(self, type_: str, axis: str, **extra: Any) -> None:
        await self.socket.send(json.dumps({"type": type_, "axis": axis, **extra}))

    async def expect(
        self, match: Callable[[dict[str, Any]], bool], what: str, timeout_s: float = 5
    ) -> dict[str, Any]:
        """The first message (old or new) that matches; consumed so it is not seen twice."""
        deadline = time.monotonic() + timeout_s
        while True:
            for index, message in enumerate(self.messages):
                if match(message):
                    del self.messages[index]
                    return message
            if time.monotonic() > deadline:
                kinds = [m["type"] for m in self.messages][-20:]
                raise AssertionError(f"no {what} within {timeout_s} s (got {kinds})")
            await asyncio.sleep(0.01)

    async def reply(self, action: str, timeout_s: float = 5) -> dict[str, Any]:
        return await self.expect(
            lambda m: m["type"] == "control_reply" and m["action"] == action,
            f"control_reply {action}",
            timeout_s,
        )

    def headers(self) -> dict[str, str]:
        return {CLIENT_HEADER: self.client_id}

    async def patch(self, axis: str, values: dict[str, int]) -> httpx.Response:
        return await self.server.client.patch(
            f"/api/axes/{axis}/params", json=values, headers=self.headers()
        )

    async def command(self, axis: str, name: str, **args: int) -> httpx.Response:
        return await self.server.client.post(
            f"/api/axes/{axis}/commands", json={"command": name, **args}, headers=self.headers()
        )


def holder_of(status: dict[str, Any]) -> str | None:
    holder = status.get("holder")
    return None if holder is None else holder.get("client_tag") or holder["kind"]


class RawWebsocket:
    """A websocket client on a plain TCP stream (RFC 6455 framing, client side)."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.messages: asyncio.Queue[dict[str, Any]] = asyncio.Queue()
        self._task: asyncio.Task[None] | None = None

    @classmethod
    async def connect(cls, port: int, path: str = "/ws") -> RawWebsocket:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        key = base64.b64encode(os.urandom(16)).decode()
        writer.write(
            (
                f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\n"
                f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                f"Sec-WebSocket-Version: 13\r\nOrigin: http://127.0.0.1:{port}\r\n\r\n"
            ).encode()
        )
        head = await reader.readuntil(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 101"), head
        client = cls(reader, writer)
        client._task = asyncio.create_task(client._read())
        return client

    async def _read(self) -> None:
        with contextlib.suppress(asyncio.IncompleteReadError, ConnectionError):
            while True:
                first, second = await self.reader.readexactly(2)
                length = second & 0x7F
                if length == 126:
                    (length,) = struct.unpack("!H", await self.reader.readexactly(2))
                elif length == 127:
                    (length,) = struct.unpack("!Q", await self.reader.readexactly(8))
                payload = await self.reader.readexactly(length)
                if first & 0x0F == 0x1:
                    message = json.loads(payload)
                    if message["type"] != "telemetry":
                        await self.messages.put(message)

    def send_text(self, text: str) -> None:
        payload = text.encode()
        mask = os.urandom(4)
        header = bytearray([0x81])
        if len(payload) < 126:
            header.append(0x80 | len(payload))
        elif len(payload) < 1 << 16:
            header.append(0x80 | 126)
            header += struct.pack("!H", len(payload))
        else:
            header.append(0x80 | 127)
            header += struct.pack("!Q", len(payload))
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        self.writer.write(bytes(header) + mask + masked)

    async def welcome(self) -> dict[str, Any]:
        while True:
            message = await asyncio.wait_for(self.messages.get(), 5)
            if message["type"] == "welcome":
                return message

    async def wait_for(self, match: Callable[[dict[str, Any]], bool]) -> dict[str, Any]:
        while True:
            message = await asyncio.wait_for(self.messages.get(), 5)
            if match(message):
                return message

    @property
    def port(self) -> int:
        """The client's own (source) port."""
        port: int = self.writer.get_extra_info("sockname")[1]
        return port

    def drop(self) -> None:
        """Vanish: RST, no close frame (SO_LINGER 0, then close)."""
        sock = self.writer.get_extra_info("socket")
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        if self._task is not None:
            self._task.cancel()
        self.writer.transport.abort()

    async def close_quietly(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        self.writer.transport.abort()
        self.writer.close()
        with contextlib.suppress(ConnectionError):
            await self.writer.wait_closed()


def can_cut_the_network() -> str:
    """Why ``cut_network`` cannot work here ("" when it can)."""
    if os.geteuid() != 0:
        return "cutting a connection needs root (an iptables rule)"
    if shutil.which("iptables") is None:
        return "cutting a connection needs iptables"
    return ""


@contextlib.contextmanager
def cut_network(*client_ports: int) -> Iterator[None]:
    """A network cut between a test client and the server: every packet from the
    client's ports is dropped on the loopback, its acknowledgements included (a laptop
    gone to sleep, a cable pulled), from one moment until the block ends."""
    ports = ",".join(str(p) for p in client_ports)
    rule = ["INPUT", "-i", "lo", "-p", "tcp", "-m", "multiport", "--sports", ports, "-j", "DROP"]
    subprocess.run(["iptables", "-I", *rule], check=True)
    try:
        yield
    finally:
        subprocess.run(["iptables", "-D", *rule], check=True)


async def take_with_raw_client(
    server: Server, axis: str, heartbeat_s: float = 0.1, *, take: bool = True
) -> tuple[RawWebsocket, str, asyncio.Task[None]]:
    """A raw client that takes ``axis`` (unless not ``take``: it will only move it) and
    heartbeats; returns it, its client id and its heartbeat task."""
    raw = await RawWebsocket.connect(server.port)
    welcome = await raw.welcome()
    if take:
        raw.send_text(json.dumps({"type": "take_control", "axis": axis}))
        reply = await raw.wait_for(lambda m: m["type"] == "control_reply")
        assert reply["ok"], reply

    async def beat() -> None:
        while True:
            raw.send_text('{"type":"heartbeat"}')
            await asyncio.sleep(heartbeat_s)

    return raw, str(welcome["client_id"]), asyncio.create_task(beat())
