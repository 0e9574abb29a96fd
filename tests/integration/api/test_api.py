"""REST and websocket API on a live server, against simulated modules on a real pty."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any

import pytest
import websockets

from tests.support.servers import LiveServer, live_server
from tests.support.sim_lines import running_simulator


async def test_axes_descriptor_and_params(api: LiveServer) -> None:
    axes = (await api.client.get("/api/axes")).json()
    assert [a["id"] for a in axes] == ["line-0", "line-1"]
    assert axes[0] == {
        "id": "line-0",
        "device": "slap2",
        "link": "line",
        "address": 0,
        "name": "SLAP2 #0",
    }
    descriptor = (await api.client.get("/api/axes/line-0/descriptor")).json()
    kp = next(p for p in descriptor["parameters"] if p["name"] == "kp")
    assert (kp["minimum"], kp["maximum"], kp["persisted"]) == (0, 32767, True)
    assert {f["name"] for f in descriptor["flags"]} >= {"move", "inpos", "oc", "limit1"}
    params = (await api.client.get("/api/axes/line-0/params")).json()
    assert params["kp"] == 40 and params["ki"] == 40 and params["kd"] == 80
    assert (await api.client.get("/api/axes/nope/params")).status_code == 404


async def test_bad_input_is_422_and_nothing_is_written(api: LiveServer) -> None:
    response = await api.client.patch("/api/axes/line-0/params", json={"kd": 90, "kp": 40000})
    assert response.status_code == 422
    body = response.json()
    assert body["field"] == "kp"
    assert "0..32767" in body["detail"]
    # The valid kd in the same request was not written either.
    assert api.bus.module(0).settings["kd"] == 80
    for bad, field in [
        ({"kp": "fast"}, "kp"),
        ({"kp": 1.5}, "kp"),
        ({"gain": 3}, "gain"),
        ({"current_limit_ma": 2500}, "current_limit_ma"),
    ]:
        response = await api.client.patch("/api/axes/line-0/params", json=bad)
        assert response.status_code == 422, bad
        assert response.json()["field"] == field
    response = await api.client.post(
        "/api/axes/line-0/commands", json={"command": "move_absolute", "position": 1 << 30}
    )
    assert response.status_code == 422
    assert response.json()["field"] == "position"
    assert "16777216" in response.json()["detail"]
    response = await api.client.post("/api/axes/line-0/commands", json={"command": "fly"})
    assert response.status_code == 422
    assert api.bus.module(0).settings["kp"] == 40


async def test_patch_writes_and_reads_back(api: LiveServer) -> None:
    response = await api.client.patch(
        "/api/axes/line-1/params", json={"kp": 65, "inpos_window": 12}
    )
    assert response.status_code == 200, response.text
    assert response.json() == {"kp": 65, "inpos_window": 12}
    assert api.bus.module(1).settings["kp"] == 65
    assert api.bus.module(1).settings["sipw"] == 12


async def test_move_refused_without_pm_then_runs(api: LiveServer) -> None:
    url = "/api/axes/line-0/commands"
    response = await api.client.post(url, json={"command": "move_relative", "distance": 2000})
    assert response.status_code == 409
    assert "position mode" in response.json()["detail"]
    assert (await api.client.post(url, json={"command": "position_mode"})).status_code == 200
    response = await api.client.post(url, json={"command": "move_relative", "distance": 2000})
    assert response.status_code == 200, response.text
    assert response.json()["sent"] == ["mr2000"]

    async def arrived() -> bool:
        state = await api.state("line-0")
        return bool(state["flags"]["inpos"]) and abs(state["position"] - 2000) <= 5

    for _ in range(200):
        if await arrived():
            break
        await asyncio.sleep(0.05)
    else:
        pytest.fail(f"no arrival: {await api.state('line-0')}")
    # STOP for all axes: the module in pm keeps holding (st + pm), the one that was
    # never powered stays unpowered (STOP never powers a motor).
    assert (await api.client.post("/api/stop")).json() == {"failed": []}
    assert api.bus.module(0).rss & (1 << 3) and not api.bus.module(0).moving
    assert not api.bus.module(1).rss & (0b11 << 2)
    # The explicit power-off (category 0) leaves the controller off.
    response = await api.client.post(url, json={"command": "power_off"})
    assert response.status_code == 200 and response.json()["sent"] == ["st"]
    assert not api.bus.module(0).rss & (1 << 3)


async def test_console_shows_multiline_replies(api: LiveServer) -> None:
    body = (await api.client.post("/api/axes/line-1/console", json={"line": "rrss"})).json()
    assert body["error"] is None
    assert len(body["reply"]) >= 5
    body = (await api.client.post("/api/axes/line-1/console", json={"line": "q p"})).json()
    assert body["sent"] == "qp" and body["reply"] == ["40"]
    response = await api.client.post("/api/axes/line-1/console", json={"line": "se 0"})
    assert response.status_code == 422


async def test_link_down_is_503_and_recovers(api: LiveServer) -> None:
    api.simulator.unplug()
    for _ in range(100):
        status = (await api.client.get("/api/links/line/status")).json()
        if status["state"] in ("disconnected", "reconnecting"):
            break
        await asyncio.sleep(0.05)
    response = await api.client.post("/api/axes/line-0/commands", json={"command": "position_mode"})
    assert response.status_code == 503
    api.simulator.replug()
    for _ in range(200):
        status = (await api.client.get("/api/links/line/status")).json()
        if status["state"] == "connected":
            break
        await asyncio.sleep(0.05)
    assert status["state"] == "connected"
    response = await api.client.post("/api/axes/line-0/commands", json={"command": "position_mode"})
    assert response.status_code == 200


async def test_reset_is_flagged_and_settings_restored(api: LiveServer) -> None:
    await api.client.patch("/api/axes/line-0/params", json={"kp": 77, "kd": 150})
    api.simulator.power_cycle(0)
    for _ in range(200):
        state = await api.state("line-0")
        if state["health"] == "reset":
            break
        await asyncio.sleep(0.05)
    assert state["health"] == "reset"
    assert api.bus.module(0).settings["kp"] == 40
    response = await api.client.post(
        "/api/axes/line-0/commands", json={"command": "restore_parameters"}
    )
    assert response.status_code == 200, response.text
    assert api.bus.module(0).settings["kp"] == 77
    assert api.bus.module(0).settings["kd"] == 150
    assert (await api.state("line-0"))["health"] == "ok"


async def test_settings_survive_a_server_restart(tmp_path: Path) -> None:
    with running_simulator([0, 1], tmp_path, link_path=str(tmp_path / "tty")) as (sim, bus):
        async with live_server(sim, bus, tmp_path / "data") as server:
            await server.client.patch("/api/axes/line-1/params", json={"ki": 3})
        sim.power_cycle(None)
        async with live_server(sim, bus, tmp_path / "data") as server:
            state = await server.state("line-1")
            assert state["health"] == "reset"
            await server.client.post(
                "/api/axes/line-1/commands", json={"command": "restore_parameters"}
            )
            assert bus.module(1).settings["ki"] == 3


async def test_saved_means_stored_by_the_save_command(api: LiveServer) -> None:
    """Every SLAP2 parameter once carried a "saved" badge meaning "can be stored".
    The server now says which values the device's save command stored (``params``
    with source ``stored``, after a save it saw succeed, and in the snapshot of a new
    client); nothing before a save (not known). The UI marks a value saved only while
    the device holds the stored value."""
    async with websockets.connect(api.ws_url, origin=api.base_url) as ws:
        snapshot = await _messages_until_quiet(ws)
        assert not [m for m in snapshot if m["type"] == "params" and m["source"] == "stored"]
        await api.client.patch("/api/axes/line-0/params", json={"kp": 77})
        response = await api.client.post(
            "/api/axes/line-0/commands", json={"command": "save_eeprom"}
        )
        assert response.status_code == 200, response.text
        for _ in range(500):
            message = json.loads(await asyncio.wait_for(ws.recv(), 5))
            if message["type"] == "params" and message["source"] == "stored":
                break
        else:
            pytest.fail("no stored values after a save")
        assert message["axis"] == "line-0" and message["values"]["kp"] == 77
        assert "ki" in message["values"] and "syscon" in message["values"]
    async with websockets.connect(api.ws_url, origin=api.base_url) as late:
        snapshot = await _messages_until_quiet(late)
        stored = [m for m in snapshot if m["type"] == "params" and m["source"] == "stored"]
        assert [m["axis"] for m in stored] == ["line-0"] and stored[0]["values"]["kp"] == 77


async def _messages_until_quiet(ws: Any, window_s: float = 1.0) -> list[dict[str, Any]]:
    """The messages a new client gets in its first ``window_s`` (hello, snapshot),
    telemetry left out."""
    out: list[dict[str, Any]] = []
    loop = asyncio.get_running_loop()
    deadline = loop.time() + window_s
    while (remaining := deadline - loop.time()) > 0:
        try:
            message = json.loads(await asyncio.wait_for(ws.recv(), remaining))
        except TimeoutError:
            break
        if message["type"] != "telemetry":
            out.append(message)
    return out


async def test_websocket_streams_and_second_client_sees_changes(api: LiveServer) -> None:
    async with (
        websockets.connect(api.ws_url, origin=api.base_url) as first,
        websockets.connect(api.ws_url, origin=api.base_url) as second,
    ):
        hello = json.loads(await first.recv())
        assert hello["type"] == "hello"
        assert [a["id"] for a in hello["axes"]] == ["line-0", "line-1"]
        times: list[float] = []
        while len(times) < 40:
            message = json.loads(await asyncio.wait_for(first.recv(), 5))
            if message["type"] == "telemetry" and message["axis"] == "line-0":
                assert len(message["channels"]["position"]) == len(message["t"])
                assert len(message["flags"]["inpos"]) == len(message["t"])
                times.extend(message["t"])
        assert times == sorted(times)
        assert times[-1] > times[0]
        await api.client.patch("/api/axes/line-0/params", json={"kd": 123})
        for _ in range(500):
            message = json.loads(await asyncio.wait_for(second.recv(), 5))
            if message["type"] == "params" and message["values"].get("kd") == 123:
                assert message["source"] == "write"
                break
        else:
            pytest.fail("the second client never saw the change")


async def test_a_stalled_client_does_not_slow_the_others(api: LiveServer) -> None:
    async with websockets.connect(api.ws_url, max_queue=1, origin=api.base_url) as stalled:
        await stalled.recv()  # hello, then never read again
        async with websockets.connect(api.ws_url, origin=api.base_url) as reader:
            count = 0
            loop = asyncio.get_running_loop()
            start = loop.time()
            while loop.time() - start < 2.0:
                message = json.loads(await asyncio.wait_for(reader.recv(), 5))
                if message["type"] == "telemetry":
                    count += len(message["t"])
            status = (await api.client.get("/api/links/line/status")).json()
    # Both axes keep streaming at the link's rate to the client that reads.
    assert count >= 0.6 * 2 * 2.0 * status["rate_hz"], (count, status)
    assert status["rate_hz"] > 10


async def test_stop_says_what_it_does_and_hold_keeps_the_motor_powered(api: LiveServer) -> None:
    descriptor = (await api.client.get("/api/axes/line-0/descriptor")).json()
    assert descriptor["stop"]["motor_powered"] is True
    assert descriptor["stop"]["category"] == 2
    assert descriptor["stop"]["power_off_command"] == "power_off"
    assert descriptor["stop"]["gentler"] == ["jog_stop", "hold"]
    url = "/api/axes/line-0/commands"
    pm = 1 << 3
    # After st (motor unpowered) hold turns the controller on where the shaft is; STOP
    # on an unpowered motor sends st only.
    response = await api.client.post(url, json={"command": "stop"})
    assert response.status_code == 200 and response.json()["sent"] == ["st"]
    assert not api.bus.module(0).rss & pm
    response = await api.client.post(url, json={"command": "hold"})
    assert response.status_code == 200, response.text
    assert response.json()["sent"] == ["pm"]
    assert api.bus.module(0).rss & pm
    # In pm with a move running, hold replans the move to the position at the press.
    await api.client.patch("/api/axes/line-0/params", json={"velocity": 500})
    response = await api.client.post(url, json={"command": "move_relative", "distance": 200000})
    assert response.status_code == 200, response.text
    for _ in range(200):
        state = await api.state("line-0")
        if state["flags"]["move"] and state["position"] > 50:
            break
        await asyncio.sleep(0.02)
    else:
        pytest.fail(f"the move did not start: {state}")
    response = await api.client.post(url, json={"command": "hold"})
    assert response.status_code == 200, response.text
    (sent,) = response.json()["sent"]
    assert sent.startswith("ma")
    held = int(sent[2:])
    for _ in range(300):
        state = await api.state("line-0")
        if not state["flags"]["move"] and state["flags"]["inpos"]:
            break
        await asyncio.sleep(0.05)
    else:
        pytest.fail(f"the axis did not come to rest: {state}")
    assert api.bus.module(0).rss & pm, "hold must leave the controller on"
    assert abs(state["position"] - held) <= 5
    assert held < 200000


async def test_omitted_argument_takes_its_default_and_console_refuses_control_chars(
    api: LiveServer,
) -> None:
    url = "/api/axes/line-0/commands"
    await api.client.post(url, json={"command": "stop"})
    response = await api.client.post(url, json={"command": "open_loop_pwm"})
    assert (response.status_code, response.json()["field"]) == (422, "pwm")
    for line in ("rp\rsv0", "se\x18", "\x0b"):
        response = await api.client.post("/api/axes/line-0/console", json={"line": line})
        assert (response.status_code, response.json()["field"]) == (422, "line"), line
    # Nothing of those reached the module: its settings are the factory ones.
    assert api.bus.module(0).settings["sv"] == 2000
