"""A lab on a real nats-server: rigs and a hub as in-process apps (fixture ``lab``)."""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import nats
import pytest
from nats.errors import Error as NatsError
from nats.js.errors import NotFoundError

from servotune.api.app import AppConfig, create_app
from servotune.bus.connection import BusSettings
from servotune.bus.lab_hub import ensure_bus_state
from servotune.bus.subjects import RIGS_STREAM, manifest
from servotune.config import LinkSpec
from servotune.hub.control_client import ControlSettings
from tests.support.control import WireRecorder, recorded_line
from tests.support.nats import Lab, nats_lab
from tests.support.servers import local_client, use_csrf_token
from tests.support.waiting import wait_for

RIGS = ["rig-a", "rig-b"]


VM = 1 << 2  # SLAP2 rss bit: velocity mode


@dataclass
class App:
    app: Any
    client: httpx.AsyncClient
    stack: contextlib.AsyncExitStack


@dataclass
class Rig:
    name: str
    wire: WireRecorder
    path: str
    data_dir: Path
    app: App | None = None


@dataclass
class LabRun:
    lab: Lab
    tmp: Path
    rigs: dict[str, Rig] = field(default_factory=dict)
    hub: App | None = None

    @property
    def hub_client(self) -> httpx.AsyncClient:
        assert self.hub is not None
        return self.hub.client


async def start_app(config: AppConfig) -> App:
    stack = contextlib.AsyncExitStack()
    app = create_app(config)
    await stack.enter_async_context(app.router.lifespan_context(app))
    client = await stack.enter_async_context(local_client(app, timeout=10))
    await use_csrf_token(client)
    return App(app, client, stack)


async def start_rig(run: LabRun, rig: Rig) -> None:
    config = AppConfig(
        links=[LinkSpec("slap2", rig.path, "line", 19200, [0, 1], 512)],
        data_dir=rig.data_dir,
        web_dir=run.tmp / "no-web",
        twin=False,
        control=ControlSettings(),
        bus=BusSettings(
            url=run.lab.rig_url(rig.name),
            rig=rig.name,
            credentials=run.lab.users[rig.name].credentials,
        ),
    )
    rig.app = await start_app(config)
    for address in (0, 1):
        for _ in range(250):
            response = await rig.app.client.get(f"/api/axes/line-{address}/state")
            if response.status_code == 200:
                break
            await asyncio.sleep(0.02)


async def start_hub(run: LabRun) -> None:
    config = AppConfig(
        data_dir=run.tmp / "hub-data",
        web_dir=run.tmp / "no-web",
        twin=False,
        bus=BusSettings(url=run.lab.url, hub="lab", credentials=run.lab.users["hub"].credentials),
    )
    run.hub = await start_app(config)


def add_rig_lines(run: LabRun, names: Iterable[str], lines: contextlib.ExitStack) -> None:
    """A recorded SLAP2 line (modules 0 and 1) per rig in ``names``, entered on
    ``lines``, and the rig's record in ``run.rigs`` (its files under ``run.tmp``)."""
    for name in names:
        directory = run.tmp / name
        directory.mkdir()
        simulator, wire = lines.enter_context(recorded_line(directory, [0, 1]))
        run.rigs[name] = Rig(name, wire, simulator.path, directory / "data")


async def stop_app(app: App | None) -> None:
    if app is not None:
        await app.stack.aclose()


@pytest.fixture
async def lab(tmp_path: Path) -> AsyncIterator[LabRun]:
    async with nats_lab(tmp_path / "nats", RIGS) as nats_lab_:
        run = LabRun(nats_lab_, tmp_path)
        with contextlib.ExitStack() as lines:
            add_rig_lines(run, RIGS, lines)
            try:
                await create_bus_state(nats_lab_)
                for rig in run.rigs.values():
                    await start_rig(run, rig)
                for rig in RIGS:
                    await wait_for_manifest(nats_lab_, rig)
                await start_hub(run)
                for name in RIGS:
                    await wait_for(
                        lambda n=name: hub_online(run, f"{n}.line-0"), 5, f"{name} online"
                    )
                yield run
            finally:
                await stop_app(run.hub)
                for rig in run.rigs.values():
                    await stop_app(rig.app)


async def create_bus_state(lab: Lab) -> None:
    """What the first ``servotune hub`` of a lab does: the buckets and the runs stream."""
    hub = lab.users["hub"]
    nc = await nats.connect(lab.url, user=hub.name, password=hub.password)
    try:
        await ensure_bus_state(nc)
    finally:
        await nc.close()


async def wait_for_manifest(lab: Lab, rig: str, timeout_s: float = 10.0) -> None:
    hub = lab.users["hub"]
    nc = await nats.connect(lab.url, user=hub.name, password=hub.password)
    try:
        deadline = time.monotonic() + timeout_s
        while True:
            with contextlib.suppress(NatsError, NotFoundError):
                await nc.jetstream().get_last_msg(RIGS_STREAM, manifest(rig))
                return
            assert time.monotonic() < deadline, f"rig {rig} never registered"
            await asyncio.sleep(0.1)
    finally:
        await nc.close()


def hub_online(run: LabRun, axis_id: str) -> bool:
    assert run.hub is not None
    entry = run.hub.app.state.hub.entry(axis_id)
    return bool(entry.health != "offline" and entry.device_values)


def rig_app(lab: LabRun, name: str) -> App:
    app = lab.rigs[name].app
    assert app is not None
    return app


async def hub_nats(lab: LabRun, user: str = "hub", **options: Any) -> Any:
    credentials = lab.lab.users[user]
    return await nats.connect(
        lab.lab.url, user=credentials.name, password=credentials.password, **options
    )
