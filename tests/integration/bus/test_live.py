"""servotune on NATS, part 2: a rig that joins a running hub, the hub's users and its
NATS users per role, and the console through the hub.

Same lab as ``test_bus`` (real nats-server, in-process rigs on simulated SLAP2 lines),
but the hub is served on a real port from the start, so a browser's websocket sees
the navigation change when a rig joins.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import nats
import pytest
import uvicorn
import websockets
from websockets.typing import Origin

from servotune.api.app import AppConfig, create_app
from servotune.auth.security import SecurityConfig
from servotune.bus.connection import BusSettings
from servotune.bus.subjects import axis_cmd, rig_cmd
from tests.support.auth import LAB, TEST_PASSWORD_COST, client, login, make_accounts
from tests.support.bus_lab import (
    RIGS,
    LabRun,
    add_rig_lines,
    create_bus_state,
    start_rig,
    stop_app,
    wait_for_manifest,
)
from tests.support.nats import nats_lab
from tests.support.servers import bound_socket, use_csrf_token
from tests.support.waiting import wait_for

VM = 1 << 2  # SLAP2 rss bit: velocity mode


@dataclass
class Served:
    port: int
    app: Any
    client: httpx.AsyncClient

    @property
    def hub(self) -> Any:
        return self.app.state.hub


@contextlib.asynccontextmanager
async def serve(config: AppConfig) -> AsyncIterator[Served]:
    app = create_app(config)
    sock = bound_socket()
    port = sock.getsockname()[1]
    server = uvicorn.Server(
        uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning", lifespan="on")
    )
    task = asyncio.create_task(server.serve(sockets=[sock]))
    try:
        deadline = time.monotonic() + 15
        while not server.started:
            assert not task.done(), "the hub did not start"
            assert time.monotonic() < deadline, "the hub did not start in 15 s"
            await asyncio.sleep(0.02)
        async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{port}", timeout=10) as http:
            await use_csrf_token(http)
            yield Served(port, app, http)
    finally:
        server.should_exit = True
        await task


def hub_config(run: LabRun) -> AppConfig:
    return AppConfig(
        data_dir=run.tmp / "hub-data",
        web_dir=run.tmp / "no-web",
        twin=False,
        bus=BusSettings(url=run.lab.url, hub="lab", credentials=run.lab.users["hub"].credentials),
    )


@pytest.fixture
async def half_lab(tmp_path: Path) -> AsyncIterator[LabRun]:
    """rig-a on the bus; rig-b's line and credentials ready, the rig not started."""
    async with nats_lab(tmp_path / "nats", RIGS) as nats_lab_:
        run = LabRun(nats_lab_, tmp_path)
        with contextlib.ExitStack() as lines:
            add_rig_lines(run, RIGS, lines)
            try:
                await create_bus_state(nats_lab_)
                await start_rig(run, run.rigs["rig-a"])
                await wait_for_manifest(nats_lab_, "rig-a")
                yield run
            finally:
                for rig in run.rigs.values():
                    await stop_app(rig.app)


class Browser:
    """A hub tab's websocket: every message it got, in order."""

    def __init__(self, socket: Any) -> None:
        self.socket = socket
        self.messages: list[dict[str, Any]] = []
        self._tasks = [asyncio.create_task(self._read()), asyncio.create_task(self._beat())]

    async def _read(self) -> None:
        with contextlib.suppress(websockets.ConnectionClosed):
            async for text in self.socket:
                self.messages.append(json.loads(text))

    async def _beat(self) -> None:
        """The dashboard's heartbeat (the hub's dead-man lease of what this tab holds)."""
        with contextlib.suppress(websockets.ConnectionClosed):
            while True:
                await self.socket.send(json.dumps({"type": "heartbeat"}))
                await asyncio.sleep(0.1)

    def of(self, kind: str) -> list[dict[str, Any]]:
        return [m for m in self.messages if m.get("type") == kind]

    async def close(self) -> None:
        for task in self._tasks:
            task.cancel()
        for task in self._tasks:
            with contextlib.suppress(asyncio.CancelledError):
                await task
        await self.socket.close()


@contextlib.asynccontextmanager
async def browser(port: int) -> AsyncIterator[Browser]:
    socket = await websockets.connect(
        f"ws://127.0.0.1:{port}/ws", max_size=None, origin=Origin(f"http://127.0.0.1:{port}")
    )
    tab = Browser(socket)
    try:
        yield tab
    finally:
        await tab.close()


def online(hub: Any, axis_id: str) -> bool:
    try:
        entry = hub.entry(axis_id)
    except KeyError:
        return False
    return bool(entry.health != "offline" and entry.device_values)


async def test_a_rig_joining_a_running_hub_is_listed_live_and_goes_offline(
    half_lab: LabRun,
) -> None:
    run = half_lab
    async with serve(hub_config(run)) as hub, browser(hub.port) as tab:
        await wait_for(lambda: online(hub.hub, "rig-a.line-0"), 10, "rig-a online at the hub")
        await wait_for(lambda: bool(tab.of("hello")), 5, "the tab's hello")
        first = tab.of("hello")[0]
        assert {a["id"] for a in first["axes"]} == {"rig-a.line-0", "rig-a.line-1"}

        rig_b = run.rigs["rig-b"]
        await start_rig(run, rig_b)
        # The tab is told: a new hello lists both rigs (its navigation rebuilds from it).
        await wait_for(lambda: len(tab.of("hello")) >= 2, 15, "a new hello after rig-b joined")
        latest = tab.of("hello")[-1]
        assert {a["id"] for a in latest["axes"]} == {f"{r}.line-{a}" for r in RIGS for a in (0, 1)}
        assert {link["id"] for link in latest["links"]} == {"rig-a.line", "rig-b.line"}
        ids = {a["id"] for a in (await hub.client.get("/api/axes")).json()}
        assert {"rig-b.line-0", "rig-b.line-1"} <= ids
        # Live, with its parameters (the hub asked the rig for a snapshot) ...
        await wait_for(lambda: online(hub.hub, "rig-b.line-1"), 10, "rig-b online at the hub")
        await wait_for(
            lambda: any(m.get("axis") == "rig-b.line-1" for m in tab.of("telemetry")),
            5,
            "rig-b's telemetry at the tab",
        )
        # ... commanded like any axis, reaching rig-b's device ...
        t0 = time.monotonic()
        response = await hub.client.patch("/api/axes/rig-b.line-1/params", json={"kp": 321})
        assert response.status_code == 200 and response.json()["kp"] == 321, response.text
        assert any(line.startswith("kp") for _, line in rig_b.wire.since(t0, 1))
        # The hub finding rig-b stopped nothing there (only a hub tab's take will).
        assert rig_b.app is not None
        assert rig_b.app.app.state.bus.rig.verbs_handled == ["write_params"]
        # ... and under the hub's control lock: held by the tab, a change without the
        # tab's connection id is refused with 423 and nothing is sent.
        welcome = next(m for m in tab.messages if m.get("type") == "welcome")
        await tab.socket.send(json.dumps({"type": "take_control", "axis": "rig-b.line-0"}))
        await wait_for(
            lambda: any(
                m.get("type") == "control_status"
                and m.get("axis") == "rig-b.line-0"
                and (m.get("holder") or {}).get("client_tag") == welcome["client_tag"]
                for m in tab.messages
            ),
            5,
            "the tab holds rig-b.line-0",
        )
        t1 = time.monotonic()
        response = await hub.client.patch("/api/axes/rig-b.line-0/params", json={"kp": 99})
        assert response.status_code == 423, response.text
        assert not [line for _, line in rig_b.wire.since(t1, 0) if line.startswith("kp")]

        # Joining, rig-b was never announced offline (seen before: every joining rig was
        # first announced "is offline" right after "joined").
        told = [e.message for e in hub.hub._events]
        assert not [m for m in told if "rig-b.line: disconnected" in m], told
        # rig-b's network cut: offline within 2 s at the hub and at the tab.
        await run.lab.proxies["rig-b"].cut()
        cut = time.monotonic()
        seen = len(tab.messages)
        await wait_for(
            lambda: any(
                m.get("type") == "axis_status"
                and m.get("axis") == "rig-b.line-1"
                and m.get("health") == "offline"
                for m in tab.messages[seen:]
            ),
            2.5,
            "rig-b offline at the tab",
        )
        assert time.monotonic() - cut <= 2.0
        assert hub.hub.entry("rig-b.line-1").health == "offline"


def exposed_hub_config(run: LabRun) -> AppConfig:
    data_dir = run.tmp / "hub-data"
    data_dir.mkdir(parents=True, exist_ok=True)
    make_accounts(data_dir, ("olga", "victor"))
    return AppConfig(
        data_dir=data_dir,
        web_dir=run.tmp / "no-web",
        twin=False,
        security=SecurityConfig(host="0.0.0.0", proxy=["127.0.0.1"], public_hosts=[LAB]),
        bus=BusSettings(url=run.lab.url, hub="lab", credentials=run.lab.users["hub"].credentials),
        password_cost=TEST_PASSWORD_COST,
    )


@contextlib.asynccontextmanager
async def running_app(config: AppConfig) -> AsyncIterator[Any]:
    app = create_app(config)
    async with app.router.lifespan_context(app):
        yield app


async def test_a_hub_viewer_cannot_command_a_rig_and_the_view_user_is_refused_by_nats(
    half_lab: LabRun,
) -> None:
    run = half_lab
    rig = run.rigs["rig-a"]
    assert rig.app is not None
    agent = rig.app.app.state.bus.rig
    async with running_app(exposed_hub_config(run)) as app:
        hub = app.state.hub
        await wait_for(lambda: online(hub, "rig-a.line-0"), 10, "rig-a online at the hub")
        handled = len(agent.verbs_handled)
        t0 = time.monotonic()
        async with client(app) as victor:
            await login(victor, "victor")
            # Reading is a viewer's: it reaches the rig (on the hub's view connection).
            response = await victor.get("/api/axes/rig-a.line-0/params")
            assert response.status_code == 200, response.text
            for method, path, body in (
                ("PATCH", "/api/axes/rig-a.line-0/params", {"kp": 10}),
                ("POST", "/api/axes/rig-a.line-0/commands", {"command": "velocity_mode"}),
                ("POST", "/api/axes/rig-a.line-0/console", {"line": "q p"}),
            ):
                response = await victor.request(method, path, json=body)
                assert response.status_code == 403, (path, response.text)
        await asyncio.sleep(0.3)
        assert agent.verbs_handled[handled:] == ["read_params"]
        assert not [line for _, line in rig.wire.since(t0) if line.startswith(("kp", "vm"))]
        # An operator at the hub may (the hub's operate connection).
        async with client(app) as olga:
            await login(olga, "olga")
            response = await olga.patch("/api/axes/rig-a.line-0/params", json={"kp": 11})
            assert response.status_code == 200 and response.json()["kp"] == 11, response.text

    # The hub's view user, with a handmade client: nats-server refuses every command.
    errors: list[Exception] = []

    async def on_error(exc: Exception) -> None:
        errors.append(exc)

    view = run.lab.users["hub-view"]
    nc = await nats.connect(run.lab.url, user=view.name, password=view.password, error_cb=on_error)
    handled = len(agent.verbs_handled)
    t1 = time.monotonic()
    try:
        body = json.dumps(
            {"session": "x" * 16, "hub": "view", "values": {"kp": 5}, "args": {"line": "q p"}}
        ).encode()
        refused = [
            axis_cmd("rig-a", "line", "line-0", "write_params"),
            axis_cmd("rig-a", "line", "line-0", "velocity_mode"),
            axis_cmd("rig-a", "line", "line-0", "console"),
            axis_cmd("rig-a", "line", "line-0", "stop"),
            rig_cmd("rig-a", "stop_all"),
            rig_cmd("rig-a", "keepalive"),
        ]
        for subject in refused:
            await nc.publish(subject, body)
        await nc.flush(timeout=2)
        await wait_for(lambda: len(errors) >= len(refused), 5, "a violation per command")
        # What it may do: read.
        reply = await nc.request(
            axis_cmd("rig-a", "line", "line-0", "read_params"), body, timeout=5
        )
        assert json.loads(reply.data)["ok"] is True
    finally:
        await nc.close()
    assert all("permissions violation" in str(e).lower() for e in errors), errors
    await asyncio.sleep(0.3)
    assert agent.verbs_handled[handled:] == ["read_params"]
    # (An "st" may be there: the rig's own dead-man stopping what the hub moved.)
    assert not [line for _, line in rig.wire.since(t1) if line.startswith(("kp", "vm"))]


async def test_the_console_and_parameter_sets_through_the_hub_reach_the_rig(
    half_lab: LabRun,
) -> None:
    run = half_lab
    rig = run.rigs["rig-a"]
    async with serve(hub_config(run)) as hub:
        await wait_for(lambda: online(hub.hub, "rig-a.line-1"), 10, "rig-a online at the hub")
        t0 = time.monotonic()
        response = await hub.client.post("/api/axes/rig-a.line-1/console", json={"line": "q p"})
        assert response.status_code == 200, response.text
        body = response.json()
        assert body["sent"] == "qp" and body["reply"] == ["40"] and body["error"] is None
        assert any(line == "qp" for _, line in rig.wire.since(t0, 1))
        # Refused by the rig's own console check, with the rig's 422 naming the line.
        response = await hub.client.post("/api/axes/rig-a.line-1/console", json={"line": "se 0"})
        assert response.status_code == 422, response.text
        # Nothing typed: the rig's hub logs every console line it sends. (The wire
        # cannot tell: a typed "se0" is the same line as the poller's own select.)
        assert rig.app is not None
        typed = [e.message for e in rig.app.app.state.hub._events if "console 'se" in e.message]
        assert not typed, typed
        assert any("console 'qp'" in e.message for e in rig.app.app.state.hub._events)
        # A parameter set kept at the hub (read from the rig's device), restored: the
        # values go to the rig as a parameter write, validated there, read back.
        assert rig.app is not None
        response = await hub.client.post(
            "/api/axes/rig-a.line-1/param-sets", json={"name": "lab-default"}
        )
        assert response.status_code == 201, response.text
        saved_kp = response.json()["params"]["kp"]
        response = await hub.client.patch("/api/axes/rig-a.line-1/params", json={"kp": 7})
        assert response.status_code == 200, response.text
        t2 = time.monotonic()
        response = await hub.client.post("/api/axes/rig-a.line-1/param-sets/lab-default/restore")
        assert response.status_code == 200 and response.json()["kp"] == saved_kp, response.text
        assert any(line.startswith("kp") for _, line in rig.wire.since(t2, 1))
        device = (await rig.app.client.get("/api/axes/line-1/params")).json()
        assert device["kp"] == saved_kp


async def test_a_bench_test_from_the_hub_runs_on_the_rig_within_the_rigs_limits(
    half_lab: LabRun,
) -> None:
    run = half_lab
    rig = run.rigs["rig-a"]
    assert rig.app is not None
    rig_client = rig.app.client
    async with serve(hub_config(run)) as hub:
        await wait_for(lambda: online(hub.hub, "rig-a.line-0"), 10, "rig-a online at the hub")
        info = (await hub.client.get("/api/axes/rig-a.line-0/bench")).json()
        assert "move" in info["kinds"]  # the rig's kinds, from its manifest
        # The rig's own limits hold for a test the hub asks for: 422 naming the field.
        response = await rig_client.put(
            "/api/axes/line-0/bench/limits", json={"max_distance_counts": 500}
        )
        assert response.status_code == 200, response.text
        response = await hub.client.post(
            "/api/axes/rig-a.line-0/bench/runs", json={"kind": "move", "distance": 1000}
        )
        assert response.status_code == 422, response.text
        assert response.json()["field"] == "distance" and "500" in response.json()["detail"]
        assert (await rig_client.get("/api/axes/line-0/bench/runs")).json() == []
        # Within them: the rig runs and records it; the hub lists it at once and
        # its tabs see it progress.
        queue = hub.hub.subscribe()
        try:
            response = await hub.client.post(
                "/api/axes/rig-a.line-0/bench/runs", json={"kind": "move", "distance": 400}
            )
            assert response.status_code == 202, response.text
            run_id = response.json()["id"]
            assert response.json()["axis_id"] == "rig-a.line-0"
            on_rig = (await rig_client.get("/api/axes/line-0/bench/runs")).json()
            assert [r["id"] for r in on_rig] == [run_id]
            listed = (await hub.client.get("/api/axes/rig-a.line-0/bench/runs")).json()
            assert run_id in [r["id"] for r in listed]
            progress: list[dict[str, Any]] = []
            deadline = time.monotonic() + 30
            while not any(m.get("status") != "recording" for m in progress):
                assert time.monotonic() < deadline, f"no finished run at the hub: {progress}"
                with contextlib.suppress(TimeoutError):
                    message = json.loads(await asyncio.wait_for(queue.get(), 1.0))
                    if message.get("type") == "run" and message.get("run_id") == run_id:
                        progress.append(message)
            assert {m["axis"] for m in progress} == {"rig-a.line-0"}
        finally:
            hub.hub.unsubscribe(queue)
        # The finished run reaches the hub's store (runs stream), samples and all.
        for _ in range(300):
            meta = await hub.client.get(f"/api/bench/runs/{run_id}")
            # (Written in two steps: the row, then its samples and final status.)
            body = meta.json() if meta.status_code == 200 else {}
            if body.get("rig") == "rig-a" and body.get("status") != "recording":
                break
            await asyncio.sleep(0.1)
        else:
            pytest.fail("the run never reached the hub's store")
        assert body["samples"]
