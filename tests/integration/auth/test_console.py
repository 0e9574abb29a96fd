"""One permission table for every path: a console line
is checked as the command it is, ``hold`` (which powers a motor) needs ``move`` and the
lock while every stop stays open to every role, and the websocket's forced hand-over
asks for the password again like a dangerous REST call.

The device tests run a real exposed server on a recorded simulated SLAP2 line
(``WireRecorder``: the simulated device's own record of what reached it) and the demo's
Z1100 chip simulator (its flash is a file: a SetFlash that ran rewrites it).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import sqlite3
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import websockets
from websockets.typing import Origin

from servotune.api.app import AppConfig, create_app
from servotune.auth.permissions import ROLES
from servotune.auth.routes_table import command_permission, console_permission
from servotune.auth.security import AUTH_DB
from servotune.descriptor import UnknownConsoleLineError
from servotune.devices.ep7047 import codec as ep7047_codec
from servotune.devices.ep7047.descriptor import ep7047_descriptor
from servotune.devices.slap2.descriptor import slap2_descriptor
from servotune.devices.slap2.sim.module import Slap2Module
from servotune.devices.z1100 import codec as z1100_codec
from servotune.devices.z1100.descriptor import z1100_descriptor
from servotune.devices.z1100.entry import demo_line as z1100_demo_line
from tests.support.auth import TEST_PASSWORD_COST, make_accounts
from tests.support.control import (
    ExposedServer,
    exposed_line_server,
    exposed_security,
    served,
    session_of,
)
from tests.support.waiting import wait_for

SLAP2 = slap2_descriptor(512)
Z1100 = z1100_descriptor(2048)
EP7047 = ep7047_descriptor(speed_range_steps_s=2000, counts_per_rev=4096)


# --- the table itself --------------------------------------------------------------------


@pytest.mark.parametrize("line", ["pg", "PG", " pg", "p g", "P G", "pG ", "p  g"])
def test_every_spelling_of_pg_the_module_accepts_needs_persist(line: str) -> None:
    # The module ignores spaces (manual) and case (its own examples are in capitals, the
    # simulator lowercases): all of these store the EEPROM.
    assert console_permission(SLAP2, line) == "persist"


def test_console_lines_need_what_the_command_they_are_needs() -> None:
    expected = [
        (SLAP2, "rp", "console"),
        (SLAP2, "rrss", "console"),
        (SLAP2, "kp 60", "tune"),
        (SLAP2, "SV 1000", "tune"),
        (SLAP2, "ma 1000", "move"),
        (SLAP2, "vm", "move"),
        (SLAP2, "pm", "move"),  # powers the motor
        (SLAP2, "spwm 30", "move"),
        (SLAP2, "st", "stop"),
        (SLAP2, "de 1234", "persist"),  # erases the EEPROM
        (Z1100, "SetFlash", "persist"),
        (Z1100, "setflash", "persist"),
        (Z1100, "SetBaud 19200", "persist"),
        (Z1100, "SetKABH 40 10 20", "tune"),
        (Z1100, "SetStart 1", "move"),
        (Z1100, "SetEstop 7", "stop"),
        (Z1100, "GetEncoder", "console"),
        (EP7047, "0x8020:0E", "console"),
        (EP7047, "0x8020:0E = 4096", "tune"),
        (EP7047, "list", "console"),
    ]
    for descriptor, line, permission in expected:
        assert console_permission(descriptor, line) == permission, (descriptor.device, line)
    for descriptor, line in ((SLAP2, "xyz"), (SLAP2, "se 1"), (Z1100, "Nope"), (EP7047, "?")):
        with pytest.raises(UnknownConsoleLineError):
            console_permission(descriptor, line)


def test_every_command_of_every_device_is_classified() -> None:
    """A new firmware command without a rule would be refused, never slip through."""
    module = Slap2Module(0)
    slap2 = set(module._command_table()) - {"se"}  # se: servotune selects the module
    for mnemonic in slap2:
        SLAP2.console.rule(mnemonic)
    for info in z1100_codec.COMMANDS.values():
        Z1100.console.rule(info.name)
    for obj in ep7047_codec.SDO_OBJECTS:
        EP7047.console.rule(f"0x{obj.index:04X}:{obj.subindex:02X} = 1")
    # Every rule names real parameters and commands of its descriptor.
    for descriptor in (SLAP2, Z1100, EP7047):
        for rule in descriptor.console.rules:
            for name in rule.parameters:
                descriptor.parameter(name)
            if rule.command is not None:
                descriptor.command(rule.command)


def test_hold_powers_the_motor_and_needs_move_every_stop_is_open() -> None:
    assert command_permission(SLAP2, "hold") == "move"
    assert "move" not in ROLES["viewer"]
    for descriptor in (SLAP2, Z1100, EP7047):
        for command in descriptor.commands:
            if command.group == "stop" and not command.powers_motor:
                assert command_permission(descriptor, command.name) == "stop", command.name
    assert [c.name for d in (SLAP2, Z1100, EP7047) for c in d.commands if c.powers_motor] == [
        "hold"
    ]


# --- on a SLAP2 line ------------------------------------------------------------------


def _eeprom(tmp_path: Path) -> bytes | None:
    path = tmp_path / "eeprom_0.json"
    return path.read_bytes() if path.exists() else None


def _audit_rows(server: ExposedServer, action: str) -> list[dict[str, Any]]:
    from servotune.auth.audit import AuditQuery

    audit = server.app.state.audit
    audit.flush()
    return list(audit.query(AuditQuery(action=action)))


async def test_console_pg_of_an_operator_is_refused_and_nothing_is_sent(tmp_path: Path) -> None:
    async with exposed_line_server(tmp_path, [0]) as server:
        await wait_for(lambda: bool(server.wire.since(0, 0)), 20, "the module polled")
        olga = await session_of(server, "olga")
        alice = await session_of(server, "alice")
        try:
            started = time.monotonic()
            eeprom = _eeprom(tmp_path)
            for line in ("pg", "PG", " pg", "p g"):
                response = await olga.post("/api/axes/line-0/console", json={"line": line})
                assert response.status_code == 403, response.text
                assert "persist" in response.json()["detail"]
            # The same operator's save_eeprom was already refused the same way.
            save = await olga.post("/api/axes/line-0/commands", json={"command": "save_eeprom"})
            assert save.status_code == 403
            unknown = await olga.post("/api/axes/line-0/console", json={"line": "xyz 1"})
            assert unknown.status_code == 422 and unknown.json()["field"] == "line"
            await asyncio.sleep(0.3)
            sent = [line for _, line in server.wire.since(started, 0)]
            assert "pg" not in sent and not any(line.startswith("xyz") for line in sent)
            assert _eeprom(tmp_path) == eeprom
            # An admin may (after the start-up STOP the module is off: pg is allowed).
            response = await alice.post("/api/axes/line-0/console", json={"line": "P G"})
            assert response.status_code == 200, response.text
            assert response.json()["error"] is None
            assert any(line == "pg" for _, line in server.wire.since(started, 0))
            assert _eeprom(tmp_path) != eeprom
        finally:
            await olga.aclose()
            await alice.aclose()


async def test_a_console_parameter_write_is_audited_with_before_and_after(tmp_path: Path) -> None:
    async with exposed_line_server(tmp_path, [0]) as server:
        await wait_for(lambda: bool(server.wire.since(0, 0)), 20, "the module polled")
        olga = await session_of(server, "olga")
        try:
            # The parameters are read once the link has polled the module: wait for kp.
            params: dict[str, Any] = {}
            for _ in range(100):
                params = (await olga.get("/api/axes/line-0/params")).json()
                if "kp" in params:
                    break
                await asyncio.sleep(0.1)
            before = params["kp"]
            response = await olga.post("/api/axes/line-0/console", json={"line": "KP 55"})
            assert response.status_code == 200 and response.json()["error"] is None
        finally:
            await olga.aclose()
        rows = _audit_rows(server, "/console")
        assert rows, "no audit row"
        row = rows[0]
        assert row["detail"] == "KP 55" and row["result"] == "ok"
        assert json.loads(row["before"]) == {"kp": before}
        assert json.loads(row["after"])["read_back"] == {"kp": 55}


async def test_a_viewer_cannot_hold_and_a_held_axis_refuses_hold(tmp_path: Path) -> None:
    async with exposed_line_server(tmp_path, [0]) as server:
        await wait_for(lambda: bool(server.wire.since(0, 0)), 20, "the module polled")
        victor = await session_of(server, "victor", "192.0.2.20")
        oscar = await session_of(server, "oscar", "192.0.2.21")
        olga = await session_of(server, "olga", "192.0.2.22")
        try:
            started = time.monotonic()
            hold = {"command": "hold"}
            response = await victor.post("/api/axes/line-0/commands", json=hold)
            assert response.status_code == 403, response.text
            # STOP stays open to the viewer.
            assert (await victor.post("/api/stop")).status_code == 200
            # Oscar holds the axis (his tab); Olga's hold is locked out (423).
            async with _tab(server, oscar) as tab:
                await tab.send(json.dumps({"type": "take_control", "axis": "line-0"}))
                await _reply(tab, "take")
                taken_at = time.monotonic()
                response = await olga.post("/api/axes/line-0/commands", json=hold)
                assert response.status_code == 423, response.text
                assert "oscar" in response.json()["detail"]
                await asyncio.sleep(0.3)
                assert "pm" not in [line for _, line in server.wire.since(taken_at, 0)]
            assert "pm" not in [line for _, line in server.wire.since(started, 0)][:1]
        finally:
            for http in (victor, oscar, olga):
                await http.aclose()


@contextlib.asynccontextmanager
async def _tab(server: ExposedServer, http: httpx.AsyncClient) -> AsyncIterator[Any]:
    """A browser tab of ``http``'s user: /ws with its cookie, heartbeating."""
    url = server.base_url.replace("http", "ws", 1) + "/ws"
    headers = {
        "Cookie": f"servotune_session={http.cookies['servotune_session']}",
        "X-Forwarded-For": http.headers["X-Forwarded-For"],
    }
    async with websockets.connect(
        url, origin=Origin(server.base_url), additional_headers=headers, max_size=None
    ) as ws:

        async def beat() -> None:
            while True:
                await ws.send(json.dumps({"type": "heartbeat"}))
                await asyncio.sleep(0.1)

        task = asyncio.create_task(beat())
        try:
            yield ws
        finally:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError, websockets.ConnectionClosed):
                await task


async def _reply(ws: Any, action: str, timeout_s: float = 10) -> dict[str, Any]:
    async with asyncio.timeout(timeout_s):
        while True:
            message = json.loads(await ws.recv())
            if message["type"] == "control_reply" and message["action"] == action:
                assert isinstance(message, dict)
                return message


async def test_websocket_force_needs_a_recent_password_like_rest(tmp_path: Path) -> None:
    async with exposed_line_server(tmp_path, [0]) as server:
        await wait_for(lambda: bool(server.wire.since(0, 0)), 20, "the module polled")
        olga = await session_of(server, "olga", "192.0.2.30")
        alice = await session_of(server, "alice", "192.0.2.31")
        try:
            async with _tab(server, olga) as holder, _tab(server, alice) as admin:
                await holder.send(json.dumps({"type": "take_control", "axis": "line-0"}))
                assert (await _reply(holder, "take"))["ok"]
                # Alice typed her password more than 5 minutes ago.
                db = sqlite3.connect(tmp_path / "data" / AUTH_DB)
                with db:
                    db.execute(
                        "UPDATE sessions SET password_s = ? WHERE user = 'alice'",
                        (time.time() - 301,),
                    )
                db.close()
                stale_at = time.monotonic()
                await admin.send(json.dumps({"type": "force_control", "axis": "line-0"}))
                refused = await _reply(admin, "force")
                assert not refused["ok"] and "password again" in refused["message"]
                await asyncio.sleep(0.3)
                # Nothing happened: no hand-over STOP, olga still holds the axis.
                assert "st" not in [line for _, line in server.wire.since(stale_at, 0)]
                assert server.app.state.control.holder("line-0").user == "olga"
                # After the password, the same force works.
                ok = await alice.post("/api/auth/reauth", json={"password": "alice-admin-pw-123"})
                assert ok.status_code == 204
                await admin.send(json.dumps({"type": "force_control", "axis": "line-0"}))
                assert (await _reply(admin, "force"))["ok"]
                assert "taken over by alice" in (await _reply(holder, "force"))["message"]
        finally:
            await olga.aclose()
            await alice.aclose()


# --- on a Z1100 chip ------------------------------------------------------------------


async def test_console_setflash_of_an_operator_is_refused(tmp_path: Path) -> None:
    make_accounts(tmp_path)
    state = tmp_path / "sim"
    config = AppConfig(
        data_dir=tmp_path,
        web_dir=tmp_path / "no-web",
        simulators=[lambda: z1100_demo_line(state)],
        security=exposed_security(),
        twin=False,
        password_cost=TEST_PASSWORD_COST,
    )
    async with served(create_app(config)) as server:
        olga = await session_of(server, "olga")
        alice = await session_of(server, "alice")
        try:
            flash = state / "z1100_flash.json"
            await wait_for(flash.exists, 20, "the chip's flash file")
            stamp = flash.stat().st_mtime_ns
            for line in ("SetFlash", "setflash", "SETFLASH"):
                response = await olga.post("/api/axes/demo-z1100-x/console", json={"line": line})
                assert response.status_code == 403, response.text
            await asyncio.sleep(0.5)
            assert flash.stat().st_mtime_ns == stamp, "the flash was written"
            response = await alice.post("/api/axes/demo-z1100-x/console", json={"line": "SetFlash"})
            assert response.status_code == 200, response.text
            await wait_for(lambda: flash.stat().st_mtime_ns != stamp, 20, "the flash written")
        finally:
            await olga.aclose()
            await alice.aclose()
