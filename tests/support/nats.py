"""nats-server for the bus tests: started by the fixture itself, on free ports, with a
temporary config (JetStream store, an account with users and subject permissions), and
a TCP proxy per rig the test can cut (the rig's network cable to the lab).

The rigs in these tests are in-process: each is a whole servotune app (its own hub,
control lock, storage) on its own simulated SLAP2 line, connected to the lab's server
with its own credentials. A rig behind its own leaf node (JetStream domain per rig):
tests/integration/bus/test_leaf.py, docs/lab.md.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from servotune.bus.accounts import lab_accounts, write_lab_accounts
from servotune.perf.demo import free_port

NATS_SERVER = shutil.which("nats-server") or "/usr/sbin/nats-server"


def require_nats_server() -> None:
    if not os.path.exists(NATS_SERVER):
        pytest.fail("nats-server is not installed: scripts/test.sh installs it (ensure_nats)")


@contextlib.contextmanager
def child_process(args: list[str], log: Path, cwd: Path | None = None) -> Iterator[Any]:
    """``args`` as a process of its own (output to ``log``), ended with it (by its
    pid, resumed first in case a test stopped it)."""
    import signal

    with log.open("wb") as out:
        child = subprocess.Popen(args, stdout=out, stderr=subprocess.STDOUT, cwd=cwd)
    try:
        yield child
    finally:
        if child.poll() is None:
            os.kill(child.pid, signal.SIGCONT)
            child.terminate()
            try:
                child.wait(10)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()


def hub_command(lab: Lab, port: int, data_dir: Path) -> list[str]:
    """``servotune hub`` on ``lab`` (its own process: its CPU, threads and stalls are
    its own)."""
    return [
        sys.executable,
        "-m",
        "servotune",
        "hub",
        "--bus",
        lab.url,
        "--bus-credentials",
        str(lab.users["hub"].credentials),
        "--port",
        str(port),
        "--data-dir",
        str(data_dir),
    ]


@dataclass
class User:
    name: str
    password: str
    credentials: Path


class ServerProcess:
    def __init__(self, name: str, config: str, directory: Path, port: int) -> None:
        self.name = name
        self.port = port
        self.url = f"nats://127.0.0.1:{port}"
        self.config_path = directory / f"{name}.conf"
        self.config_path.write_text(config)
        self.config_path.chmod(0o600)
        self.log_path = directory / f"{name}.log"
        self._process: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        log = self.log_path.open("ab")
        self._process = subprocess.Popen(
            [NATS_SERVER, "-c", str(self.config_path)], stdout=log, stderr=log
        )
        log.close()
        deadline = time.monotonic() + 10
        while True:
            with (
                contextlib.suppress(OSError),
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2),
            ):
                return
            if self._process.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"nats-server {self.name} did not start: {self.log_path.read_text()}")
            time.sleep(0.05)

    @property
    def pid(self) -> int:
        assert self._process is not None
        return self._process.pid

    def stop(self) -> None:
        if self._process is not None and self._process.poll() is None:
            self._process.terminate()
            try:
                self._process.wait(5)
            except subprocess.TimeoutExpired:
                self._process.kill()
                self._process.wait()
        self._process = None


class TcpProxy:
    """A TCP relay the test can cut: the lab network between a rig's leaf node and the
    lab's server. ``cut`` closes every relayed connection and refuses new ones."""

    def __init__(self, target_port: int) -> None:
        self.target_port = target_port
        self.port = free_port()
        self._server: asyncio.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()

    async def start(self) -> None:
        self._server = await asyncio.start_server(self._relay, "127.0.0.1", self.port)

    async def _relay(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.target_port)
        except OSError:
            writer.close()
            return
        self._writers.update((writer, up_writer))

        async def pipe(src: asyncio.StreamReader, dst: asyncio.StreamWriter) -> None:
            with contextlib.suppress(OSError, asyncio.IncompleteReadError):
                while data := await src.read(65536):
                    dst.write(data)
                    await dst.drain()
            dst.close()

        with contextlib.suppress(asyncio.CancelledError):
            await asyncio.gather(pipe(reader, up_writer), pipe(up_reader, writer))

    async def cut(self) -> None:
        if self._server is not None:
            self._server.close()
            self._server = None
        for writer in list(self._writers):
            writer.transport.abort()
        self._writers.clear()

    async def resume(self) -> None:
        """The cable is back: accept connections on the same port again."""
        if self._server is None:
            self._server = await asyncio.start_server(self._relay, "127.0.0.1", self.port)

    async def stop(self) -> None:
        await self.cut()


@dataclass
class Lab:
    """The lab's nats-server, a cuttable proxy per rig, the users' credential files."""

    directory: Path
    server: ServerProcess
    users: dict[str, User]
    proxies: dict[str, TcpProxy] = field(default_factory=dict)

    @property
    def url(self) -> str:
        return self.server.url

    def rig_url(self, rig: str) -> str:
        """A rig reaches the lab's server through its own proxy: its network cable."""
        return f"nats://127.0.0.1:{self.proxies[rig].port}"


@contextlib.asynccontextmanager
async def nats_lab(directory: Path, rigs: list[str]) -> AsyncIterator[Lab]:
    """The lab's server (JetStream, an account with users) and a proxy per rig."""
    require_nats_server()
    directory.mkdir(parents=True, exist_ok=True)
    # The shipped generator (``servotune bus-accounts``): the tests check its permissions.
    accounts = lab_accounts("hub", rigs, ["viewer"])
    write_lab_accounts(directory, accounts)
    users = {a.user: User(a.user, a.password, directory / f"{a.user}.cred") for a in accounts}
    port = free_port()
    config = f"""
server_name: lab
listen: 127.0.0.1:{port}
max_payload: 8MB
jetstream {{ store_dir: "{directory / "js"}", max_memory_store: 64MB, max_file_store: 2GB }}
include "accounts.conf"
"""
    server = ServerProcess("lab", config, directory, port)
    server.start()
    lab = Lab(directory, server, users)
    try:
        for rig in rigs:
            proxy = TcpProxy(port)
            await proxy.start()
            lab.proxies[rig] = proxy
        yield lab
    finally:
        for proxy in lab.proxies.values():
            await proxy.stop()
        server.stop()


async def rig_request(
    nc: Any, subject: str, body: dict[str, Any], timeout_s: float = 5.0
) -> tuple[bool, dict[str, Any]]:
    """A handmade command as the hub sends it (``bus.remote``): the rig answers "taken"
    (``St-Taken``) before it runs a command, then the outcome. Returns (taken, the
    outcome's JSON)."""
    import json

    from servotune.bus.messages import ACK_HEADER

    inbox = nc.new_inbox()
    got: asyncio.Queue[Any] = asyncio.Queue()

    async def collect(msg: Any) -> None:
        await got.put(msg)

    subscription = await nc.subscribe(inbox, cb=collect)
    try:
        await nc.publish(subject, json.dumps(body).encode(), reply=inbox)
        taken = False
        deadline = time.monotonic() + timeout_s
        while True:
            msg = await asyncio.wait_for(got.get(), max(0.01, deadline - time.monotonic()))
            if (msg.headers or {}).get(ACK_HEADER):
                taken = True
                continue
            reply: dict[str, Any] = json.loads(msg.data)
            return taken, reply
    finally:
        await subscription.unsubscribe()
