"""A rig's own nats-server as a leaf node of the lab's (nats-server 2.9): the rig's runs
in a stream of its own JetStream domain, the lab's runs stream sourcing it.

Two real nats-server processes: the lab's (domain ``lab``, a leaf node listener) and
rig-a's (domain ``rig-a``, its configuration from ``servotune.bus.leaf``), linked
through a TCP proxy the test cuts (the lab network). The rig's leaf user has the
permissions ``servotune bus-accounts --leaf`` writes.
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

import nats
import pytest
from nats.js.api import StreamInfo

from servotune.api.app import AppConfig
from servotune.bus import subjects
from servotune.bus.accounts import lab_accounts, write_lab_accounts
from servotune.bus.connection import BusSettings
from servotune.bus.leaf import lab_runs_config, leaf_node_conf, rig_runs_config
from servotune.bus.rig import RUN_RETRY_S
from servotune.config import LinkSpec
from servotune.hub.control_client import ControlSettings
from tests.support.bus_lab import VM, App, Rig, start_app, stop_app
from tests.support.control import recorded_line
from tests.support.nats import ServerProcess, TcpProxy, free_port, require_nats_server
from tests.support.waiting import wait_for

RIG = "rig-a"


async def _messages(js: object, stream: str) -> int:
    info: StreamInfo = await js.stream_info(stream)  # type: ignore[attr-defined]
    return int(info.state.messages)


async def _wait_messages(js: object, stream: str, count: int, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while (found := await _messages(js, stream)) < count:
        assert time.monotonic() < deadline, f"{stream}: {found} of {count} messages"
        await asyncio.sleep(0.1)


async def test_a_rigs_runs_reach_the_lab_through_its_leaf_node_also_after_a_cut(
    tmp_path: Path,
) -> None:
    require_nats_server()
    accounts = lab_accounts("hub", [RIG], [], leaf=True)
    write_lab_accounts(tmp_path, accounts)
    users = {a.user: a for a in accounts}
    lab_port, leaf_port, rig_port = free_port(), free_port(), free_port()
    proxy = TcpProxy(leaf_port)  # its port is chosen now, started below
    lab = ServerProcess(
        "lab",
        f"""
server_name: lab
listen: 127.0.0.1:{lab_port}
jetstream {{ store_dir: "{tmp_path / "js-lab"}", domain: lab }}
# advertise: the proxy (the cable the test cuts). The rig's server learns the address a
# lab server advertises and reconnects there; with no_advertise it still came back
# on the listener's own address, past the cut proxy (nats-server 2.9.10).
leafnodes {{ listen: 127.0.0.1:{leaf_port}, advertise: "127.0.0.1:{proxy.port}" }}
include "accounts.conf"
""",
        tmp_path,
        lab_port,
    )
    lab.start()
    await proxy.start()
    rig_conf = leaf_node_conf(
        RIG,
        port=rig_port,
        store_dir=tmp_path / "js-rig",
        lab_leaf_url=f"nats-leaf://127.0.0.1:{proxy.port}",
        credentials_file=tmp_path / f"{RIG}.cred",
    )
    rig_server = ServerProcess("rig", rig_conf, tmp_path, rig_port)
    rig_server.start()
    rig_nc = hub_nc = None
    try:
        rig_user, hub_user = users[RIG], users["hub"]
        rig_nc = await nats.connect(rig_server.url, user=RIG, password=rig_user.password)
        hub_nc = await nats.connect(lab.url, user="hub", password=hub_user.password)
        rig_js, hub_js = rig_nc.jetstream(), hub_nc.jetstream()
        await rig_js.add_stream(config=rig_runs_config(RIG))
        await hub_js.add_stream(config=lab_runs_config([RIG]))

        async def record(run_id: str) -> None:
            """As the rig agent publishes a finished run; acknowledged by the rig's own
            server (its domain), whatever the lab network does."""
            ack = await rig_js.publish(
                subjects.runs(RIG),
                json.dumps({"run": run_id}).encode(),
                headers={"Nats-Msg-Id": f"{RIG}/{run_id}"},
                timeout=2,
            )
            assert ack.domain == RIG and ack.stream == rig_runs_config(RIG).name

        await record("r1")
        await _wait_messages(hub_js, subjects.RUNS_STREAM, 1, 10)
        got = await hub_js.get_msg(subjects.RUNS_STREAM, 1)
        assert got.subject == subjects.runs(RIG) and json.loads(got.data or b"") == {"run": "r1"}

        # The lab network cut: the rig records on; the run waits in the rig's stream.
        await proxy.cut()
        await record("r2")
        await record("r3")
        assert await _messages(rig_js, rig_runs_config(RIG).name) == 3
        await proxy.resume()
        await _wait_messages(hub_js, subjects.RUNS_STREAM, 3, 20)
        # A run published twice (a rig retrying after a lost ack) is kept once.
        await record("r3")
        await asyncio.sleep(0.5)
        assert await _messages(rig_js, rig_runs_config(RIG).name) == 3
        assert await _messages(hub_js, subjects.RUNS_STREAM) == 3
        runs = [
            json.loads((await hub_js.get_msg(subjects.RUNS_STREAM, seq)).data or b"")["run"]
            for seq in (1, 2, 3)
        ]
        assert runs == ["r1", "r2", "r3"]
        # What nats-server 2.9 says about the leaf: the lab's JetStream is not extended
        # to it (hence the rig's own domain and the sourcing).
        assert "JetStream Not Extended" in lab.log_path.read_text()
    finally:
        for nc in (rig_nc, hub_nc):
            if nc is not None:
                await nc.close()
        await proxy.stop()
        rig_server.stop()
        lab.stop()


@dataclass
class LeafLab:
    """The lab's nats-server, rig-a's own behind the cuttable leaf link, both apps."""

    proxy: TcpProxy
    rig: Rig
    rig_app: App
    hub_app: App


@contextlib.asynccontextmanager
async def leaf_lab(tmp_path: Path) -> AsyncIterator[LeafLab]:
    """servotune's rig agent on rig-a's nats-server (``--bus-leaf``), the hub on the
    lab's, the leaf link through ``proxy``; rig-a's axis listed and online at the hub."""
    require_nats_server()
    accounts = lab_accounts("hub", [RIG], [], leaf=True)
    write_lab_accounts(tmp_path, accounts)
    lab_port, leaf_port, rig_port = free_port(), free_port(), free_port()
    proxy = TcpProxy(leaf_port)  # its port is chosen now, started below
    lab = ServerProcess(
        "lab",
        f"""
server_name: lab
listen: 127.0.0.1:{lab_port}
jetstream {{ store_dir: "{tmp_path / "js-lab"}", domain: lab }}
# advertise: the proxy (the cable the test cuts). The rig's server learns the address a
# lab server advertises and reconnects there; with no_advertise it still came back
# on the listener's own address, past the cut proxy (nats-server 2.9.10).
leafnodes {{ listen: 127.0.0.1:{leaf_port}, advertise: "127.0.0.1:{proxy.port}" }}
include "accounts.conf"
""",
        tmp_path,
        lab_port,
    )
    lab.start()
    await proxy.start()
    rig_server = ServerProcess(
        "rig",
        leaf_node_conf(
            RIG,
            port=rig_port,
            store_dir=tmp_path / "js-rig",
            lab_leaf_url=f"nats-leaf://127.0.0.1:{proxy.port}",
            credentials_file=tmp_path / f"{RIG}.cred",
        ),
        tmp_path,
        rig_port,
    )
    rig_server.start()
    with contextlib.ExitStack() as lines:
        directory = tmp_path / RIG
        directory.mkdir()
        simulator, wire = lines.enter_context(recorded_line(directory, [0, 1]))
        rig = Rig(RIG, wire, simulator.path, directory / "data")
        rig_app = hub_app = None
        try:
            rig_app = await start_app(
                AppConfig(
                    links=[LinkSpec("slap2", rig.path, "line", 19200, [0, 1], 512)],
                    data_dir=rig.data_dir,
                    web_dir=tmp_path / "no-web",
                    twin=False,
                    control=ControlSettings(),
                    bus=BusSettings(
                        url=rig_server.url, rig=RIG, credentials=tmp_path / f"{RIG}.cred", leaf=True
                    ),
                )
            )
            rig.app = rig_app
            hub_app = await start_app(
                AppConfig(
                    data_dir=tmp_path / "hub-data",
                    web_dir=tmp_path / "no-web",
                    twin=False,
                    bus=BusSettings(url=lab.url, hub="lab", credentials=tmp_path / "hub.cred"),
                )
            )
            hub = hub_app.app.state.hub
            await wait_for(lambda: _online(hub, f"{RIG}.line-0"), 20, "rig-a listed and online")
            yield LeafLab(proxy, rig, rig_app, hub_app)
        finally:
            await stop_app(hub_app)
            await stop_app(rig_app)
            await proxy.stop()
            rig_server.stop()
            lab.stop()


async def test_a_leaf_rig_is_listed_commanded_and_its_runs_arrive_after_a_cut(
    tmp_path: Path,
) -> None:
    """The whole path with the rig behind its own leaf node."""
    async with leaf_lab(tmp_path) as leaf:
        proxy, rig, wire = leaf.proxy, leaf.rig_app, leaf.rig.wire
        hub_app = leaf.hub_app
        hub = hub_app.app.state.hub
        # A gain from the hub reaches the rig's device across the leaf link.
        t0 = time.monotonic()
        response = await hub_app.client.patch(f"/api/axes/{RIG}.line-0/params", json={"kp": 222})
        assert response.status_code == 200 and response.json()["kp"] == 222, response.text
        assert any(line.startswith("kp") for _, line in wire.since(t0, 0))
        # The lab network cut: offline at the hub within 2 s; the rig records a run.
        await proxy.cut()
        cut = time.monotonic()
        await wait_for(lambda: hub.entry(f"{RIG}.line-0").health == "offline", 2.5, "offline")
        assert time.monotonic() - cut <= 2.0
        response = await rig.client.post(
            "/api/axes/line-0/bench/runs", json={"kind": "move", "distance": 1000}
        )
        assert response.status_code == 202, response.text
        run_id = response.json()["id"]
        for _ in range(400):
            runs = (await rig.client.get("/api/axes/line-0/bench/runs")).json()
            if next(r for r in runs if r["id"] == run_id)["status"] != "recording":
                break
            await asyncio.sleep(0.05)
        await asyncio.sleep(RUN_RETRY_S + 0.5)  # the agent has put it in its stream
        await proxy.resume()
        # Back: online again, and the run recorded meanwhile reaches the hub's store
        # (the lab's stream sources it from the rig's domain).
        await wait_for(lambda: _online(hub, f"{RIG}.line-0"), 20, "rig-a back")
        for _ in range(300):
            response = await hub_app.client.get(f"/api/bench/runs/{run_id}")
            body = response.json() if response.status_code == 200 else {}
            if body.get("rig") == RIG and body.get("status") != "recording":
                break
            await asyncio.sleep(0.1)
        else:
            pytest.fail("the run recorded during the cut never reached the hub")
        assert body["samples"]


async def test_motion_started_from_the_hub_stops_when_the_leaf_link_is_cut(
    tmp_path: Path,
) -> None:
    """The leaf link cut, the rig's own nats-server up: the rig's bus connection is
    fine, but the hub session's keep-alives stop arriving, and the rig's dead-man stops
    what that session set in motion (a STOP on the rig's wire) within its lease."""
    async with leaf_lab(tmp_path) as leaf:
        wire, rig = leaf.rig.wire, leaf.rig_app
        response = await leaf.hub_app.client.post(
            f"/api/axes/{RIG}.line-0/commands", json={"command": "velocity_mode"}
        )
        assert response.status_code == 200, response.text
        await wait_for(lambda: bool(wire.bus.module(0).rss & VM), 2, "velocity mode on rig-a")
        agent = rig.app.state.bus.rig
        assert agent.connected
        await leaf.proxy.cut()
        cut = time.monotonic()
        # The dead-man's stop holds: from vm the rig sends pm.
        await wait_for(lambda: wire.first("pm", 0, cut) is not None, 3, "pm on rig-a's wire")
        stopped_at = wire.first("pm", 0, cut)
        assert stopped_at is not None
        assert not wire.bus.module(0).rss & VM
        # The rig's connection to its own nats-server never went down: the keep-alives
        # stopped, not the rig's bus.
        assert agent.connected
        lease_s = rig.app.state.control.settings.lease_s
        # After the last keep-alive: the lease, the watchdog period, the STOP on the wire.
        assert stopped_at - cut < lease_s + 1.0, f"st after {stopped_at - cut:.3f} s"


def _online(hub: Any, axis_id: str) -> bool:
    try:
        entry = hub.entry(axis_id)
    except KeyError:
        return False
    return bool(entry.health != "offline" and entry.device_values)
