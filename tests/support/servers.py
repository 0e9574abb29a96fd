"""Servers for tests: a live uvicorn server on a free port, local httpx clients, CSRF."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import socket
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import uvicorn
from websockets.typing import Origin

from servotune.api.app import AppConfig, create_app
from servotune.config import LinkSpec
from servotune.demo import demo_simulators
from servotune.hub.control_client import ControlSettings
from servotune.sim.pty import PtySimulator
from tests.support.waiting import wait_for


def local_client(app: Any, **kwargs: Any) -> Any:
    """An httpx client of ``app`` as a browser on this machine reaches it: a local Host
    name (the DNS-rebinding check refuses others). Call ``use_csrf_token`` on it before
    any state-changing request."""
    import httpx

    transport = httpx.ASGITransport(app=app)
    return httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1", **kwargs)


async def use_csrf_token(client: Any) -> None:
    """Make an httpx client send the server's CSRF token on every request (local mode).

    The token comes from ``GET /api/auth/session``, as the web client gets it; a page on
    another site cannot read that answer.
    """
    response = await client.get("/api/auth/session")
    assert response.status_code == 200, response.text
    client.headers["X-CSRF-Token"] = response.json()["csrf_token"]


@dataclass
class LiveServer:
    base_url: str
    ws_url: str
    client: httpx.AsyncClient
    simulator: Any
    bus: Any
    app: Any = None

    async def state(self, axis_id: str) -> dict[str, Any]:
        response = await self.client.get(f"/api/axes/{axis_id}/state")
        assert response.status_code == 200, response.text
        result: dict[str, Any] = response.json()
        return result


def bound_socket() -> socket.socket:
    """A TCP socket bound to a free port of 127.0.0.1, for ``uvicorn.Server.serve(sockets=
    [sock])``: held from the choice of the port to the server's listen, so nothing else
    (another test worker, a client's ephemeral port) can take the port in between, as
    it can with ``free_port()``. The server closes it when it stops."""
    # IPPROTO_TCP named: asyncio sets TCP_NODELAY only on sockets whose proto says TCP
    # (proto 0 left Nagle on: ~40 ms more per small request, with delayed ACKs).
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.bind(("127.0.0.1", 0))
    return sock


@contextlib.asynccontextmanager
async def live_server(
    simulator: PtySimulator | None,
    bus: Any,
    data_dir: Path,
    *,
    web_dir: Path | None = None,
    spec: LinkSpec | None = None,
) -> AsyncIterator[LiveServer]:
    if spec is None:
        assert simulator is not None
        spec = LinkSpec("slap2", simulator.path, "line", simulator.baud, [0, 1], 512)
    # A page that changes an axis takes it and must heartbeat; a browser starved of CPU on
    # a loaded machine sends heartbeats seconds apart, which would stop these tests' moves
    # (correctly). The dead-man's timing is tested in test_control.py.
    config = AppConfig(
        links=[spec],
        data_dir=data_dir,
        web_dir=web_dir or data_dir / "no-web",
        control=ControlSettings(lease_s=10.0),
    )
    app = create_app(config)
    sock = bound_socket()
    port = sock.getsockname()[1]
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", lifespan="on")
    )
    task = asyncio.create_task(server.serve(sockets=[sock]))
    try:
        await wait_for(lambda: server.started, 10, "the server to start")
        base = f"http://127.0.0.1:{port}"
        async with httpx.AsyncClient(base_url=base, timeout=10) as client:
            await use_csrf_token(client)
            live = LiveServer(base, f"ws://127.0.0.1:{port}/ws", client, simulator, bus, app)
            for axis in (await client.get("/api/axes")).json():
                axis_id = axis["id"]
                for _ in range(250):
                    response = await client.get(f"/api/axes/{axis_id}/state")
                    if response.status_code == 200:
                        break
                    await asyncio.sleep(0.02)
            yield live
    finally:
        server.should_exit = True
        await task


def origin(ws_url: str) -> Origin:
    """The dashboard's own origin (the websocket refuses any other)."""
    return Origin(ws_url.replace("ws://", "http://").removesuffix("/ws"))


@contextlib.asynccontextmanager
async def serve(
    spec: LinkSpec | list[LinkSpec], data_dir: Path
) -> AsyncIterator[tuple[Any, httpx.AsyncClient, str]]:
    """A live server on ``spec`` (one link or several): (app, client, websocket url)."""
    specs = spec if isinstance(spec, list) else [spec]
    app = create_app(AppConfig(links=specs, data_dir=data_dir, web_dir=data_dir / "no-web"))
    sock = bound_socket()
    port = sock.getsockname()[1]
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", lifespan="on")
    )
    task = asyncio.create_task(server.serve(sockets=[sock]))
    try:
        await wait_for(lambda: server.started, 10, "the server to start")
        async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{port}", timeout=10) as client:
            await use_csrf_token(client)
            for axis in (await client.get("/api/axes")).json():
                for _ in range(250):
                    if (await client.get(f"/api/axes/{axis['id']}/state")).status_code == 200:
                        break
                    await asyncio.sleep(0.02)
            yield app, client, f"ws://127.0.0.1:{port}/ws"
    finally:
        server.should_exit = True
        await task


@dataclass
class Demo:
    base_url: str
    ws_url: str
    client: httpx.AsyncClient


@contextlib.asynccontextmanager
async def demo_server(tmp_path: Path, web_dir: Path | None = None) -> AsyncIterator[Demo]:
    """The demo app (2 SLAP2, 3 Z1100 axes, 1 EP7047), without the autopilot."""
    data_dir = tmp_path / "data"
    config = AppConfig(
        data_dir=data_dir,
        simulators=demo_simulators(data_dir),
        web_dir=web_dir or tmp_path / "no-web",
    )
    app = create_app(config)
    sock = bound_socket()
    port = sock.getsockname()[1]
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", lifespan="on")
    )
    task = asyncio.create_task(server.serve(sockets=[sock]))
    try:
        await wait_for(lambda: server.started, 30, "the server to start")
        base = f"http://127.0.0.1:{port}"
        async with httpx.AsyncClient(base_url=base, timeout=20) as client:
            await use_csrf_token(client)
            yield Demo(base, f"ws://127.0.0.1:{port}/twin", client)
    finally:
        server.should_exit = True
        await task


@contextlib.contextmanager
def sim_process(tmp_path: Path) -> Iterator[str]:
    """``servotune sim slap2`` (modules 0 and 1) in a child process; yields its pty path.

    In a session of its own, as a device on a wire would be: on Linux a scheduling
    group (autogroup) of its own, so this test's own work (the server in this process)
    cannot starve it into late echoes (``servotune.sim.process.own_scheduling_group``
    does the same for the demo's simulators)."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "servotune.cli",
            "sim",
            "slap2",
            "--addresses",
            "0,1",
            "--state-dir",
            str(tmp_path),
        ],
        stdout=subprocess.PIPE,
        text=True,
        env=os.environ.copy(),
        start_new_session=True,
    )
    try:
        assert process.stdout is not None
        path = process.stdout.readline().strip()
        assert path, "the simulator printed no path"
        yield path
    finally:
        process.send_signal(signal.SIGTERM)
        try:
            process.wait(timeout=5)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
        if process.stdout is not None:
            process.stdout.close()
