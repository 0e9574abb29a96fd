"""A STOP that could not go out never acts on motion started after it.

The hub keeps a STOP that failed (link down) and sends it "the moment the link and
the axis are back" (README) — but only while it still means what the user meant: it is
dropped, and the user told, when a command reached the axis after it was pressed, when
another STOP reached the axis since (the dead-man's, a hand-over's, the user's again),
and after ``PENDING_STOP_MAX_S``; when it does go out, it says when it was pressed.
The remote side of the same rule (a rig refusing a hub's STOP pressed before its local
user moved the axis) is in tests/integration/bus/test_faults.py.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

import servotune.hub.stops as hub_stops
from servotune.devices.slap2.descriptor import slap2_descriptor
from servotune.devices.slap2.sim.line import Slap2Line
from servotune.devices.slap2.sim.module import Slap2Module
from servotune.hub.hub import Hub
from servotune.link.base import CommandOutcome, LinkDownError
from servotune.sim.pty import PtySimulator
from servotune.storage import Storage
from tests.support.supervision import Tap, hub_on_line
from tests.support.waiting import wait_for


class FlakyStopAxis:
    """An axis whose STOP cannot go out while ``stop_down`` (its other commands can:
    the STOP path of a rig on the bus is a connection of its own)."""

    id = "ax"
    name = "ax"
    address = 0
    descriptor = slap2_descriptor(512)

    def __init__(self) -> None:
        self.stop_down = True
        self.sent: list[str] = []

    async def stop(self) -> None:
        if self.stop_down:
            raise LinkDownError("the STOP path is down")
        self.sent.append("stop")

    async def command(self, name: str, args: Any) -> CommandOutcome:
        if name == "stop":
            await self.stop()
        else:
            self.sent.append(name)
        return CommandOutcome([name], "")

    async def read_params(self) -> dict[str, int]:
        return {}

    async def write_params(self, values: Any) -> dict[str, int]:
        self.sent.append("write")
        return dict(values)

    async def console(self, line: str) -> tuple[str, list[str]]:
        self.sent.append(line)
        return line, []


class OneAxisLink:
    id = "line"
    device = "slap2"
    path = "/dev/fake"
    baud = 19200
    state = "connected"

    def __init__(self, axis: FlakyStopAxis) -> None:
        self.axes = [axis]

    async def run(self) -> None:
        await asyncio.Event().wait()


async def _hub(tmp_path: Path, now: list[float]) -> tuple[Hub, FlakyStopAxis]:
    """A started hub (its fan-out's status tick judges pending STOPs) on the clock
    ``now[-1]``."""
    axis = FlakyStopAxis()
    hub = Hub([OneAxisLink(axis)], Storage(tmp_path / "db.sqlite"), clock=lambda: now[-1])  # type: ignore[list-item]
    await hub.start()
    hub.on_link_status("line", "connected", "", 10.0, 20.0, 0)
    hub.on_axis_health("ax", "ok", "")
    return hub, axis


def _messages(hub: Hub) -> list[str]:
    return [event.message for event in hub._events]


async def test_a_command_that_reached_the_axis_after_the_stop_cancels_it(tmp_path: Path) -> None:
    now = [1000.0]
    hub, axis = await _hub(tmp_path, now)
    assert await hub.stop_all() == ["ax"]
    assert hub.entry("ax").stop_on_reconnect
    now.append(1002.0)
    await hub.command("ax", "velocity_mode", {})
    assert not hub.entry("ax").stop_on_reconnect
    assert any(
        "not sent: the axis was commanded since (velocity_mode)" in m for m in _messages(hub)
    )
    # The STOP path is back: nothing goes out, the velocity mode started after the
    # STOP is not cut.
    axis.stop_down = False
    await asyncio.sleep(0.3)
    assert axis.sent == ["velocity_mode"]
    await hub.stop()


async def test_a_stop_that_reached_the_axis_since_cancels_the_pending_one(tmp_path: Path) -> None:
    now = [1000.0]
    hub, axis = await _hub(tmp_path, now)
    await hub.stop_all()
    assert hub.entry("ax").stop_on_reconnect
    # Another STOP reaches the axis (here the control lock's: a dead-man or a hand-over
    # calls note_stopped after its own STOP went out).
    axis.stop_down = False
    now.append(1001.0)
    await axis.stop()
    hub.note_stopped(hub.entry("ax"))
    assert not hub.entry("ax").stop_on_reconnect
    assert any("not sent: the axis was stopped since" in m for m in _messages(hub))
    await asyncio.sleep(0.2)
    assert axis.sent == ["stop"]  # that one only
    await hub.stop()


async def test_a_pending_stop_expires_told_and_unsent(tmp_path: Path) -> None:
    now = [1000.0]
    hub, axis = await _hub(tmp_path, now)
    await hub.stop_all()
    now.append(1000.0 + hub_stops.PENDING_STOP_MAX_S + 0.5)
    await wait_for(lambda: not hub.entry("ax").stop_on_reconnect, 2, "the STOP expired")
    expired = [m for m in _messages(hub) if "never delivered" in m]
    assert expired and "press STOP again" in expired[0] and "pressed at" in expired[0]
    axis.stop_down = False
    await asyncio.sleep(0.3)
    assert axis.sent == []
    await hub.stop()


async def test_the_stop_overtaken_rule(tmp_path: Path) -> None:
    """What a rig answers a hub's STOP with (``Hub.stop_overtaken``)."""
    now = [1000.0]
    hub, axis = await _hub(tmp_path, now)
    axis.stop_down = False
    assert hub.stop_overtaken("ax", 999.0) is None
    await hub.command("ax", "velocity_mode", {})
    why = hub.stop_overtaken("ax", 999.0)
    assert why is not None and "commanded" in why
    assert hub.stop_overtaken("ax", 1000.5) is None  # pressed after the command
    now.append(1001.0)
    await hub.command("ax", "stop", {})
    why = hub.stop_overtaken("ax", 1000.5)
    assert why is not None and "already stopped" in why
    await hub.stop()


# --- a real line unplugged and plugged back ----------------------------------------------


@contextlib.asynccontextmanager
async def _stop_while_unplugged(tmp_path: Path) -> AsyncIterator[tuple[Hub, Any, Tap]]:
    """A hub on a real pty line whose cable is pulled, and STOP all pressed then:
    (the hub, the simulator to plug back, the device's record of what it received)."""
    bus = Slap2Line([Slap2Module(0, eeprom_path=tmp_path / "eeprom_0.json")])
    tap = Tap(bus)
    with PtySimulator(tap, baud=19200, link_path=str(tmp_path / "tty")) as sim:
        hub, _ = hub_on_line(sim.path, [0], tmp_path)
        await hub.start()
        try:
            await wait_for(lambda: hub.link_status("line").state == "connected", 10, "link")
            sim.unplug()
            await wait_for(lambda: hub.link_status("line").state != "connected", 10, "down")
            assert await hub.stop_all() == ["line-0"]
            yield hub, sim, tap
        finally:
            await hub.stop()


async def test_a_stop_pending_too_long_is_not_sent_when_the_line_is_back(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(hub_stops, "PENDING_STOP_MAX_S", 1.0)
    async with _stop_while_unplugged(tmp_path) as (hub, sim, tap):
        await wait_for(lambda: any("never delivered" in m for m in _messages(hub)), 5, "expiry")
        mark = tap.mark()
        sim.replug()
        await wait_for(lambda: hub.link_status("line").state == "connected", 15, "back")
        await wait_for(lambda: hub.entry("line-0").health == "ok", 10, "axis back")
        await asyncio.sleep(1.0)  # several polls: a STOP would be out by now
        assert b"st\r" not in tap.since(mark)
        assert not any("STOP sent" in m for m in _messages(hub))


async def test_a_pending_stop_that_goes_out_says_when_it_was_pressed(tmp_path: Path) -> None:
    async with _stop_while_unplugged(tmp_path) as (hub, sim, tap):
        mark = tap.mark()
        sim.replug()
        await wait_for(lambda: b"st\r" in tap.since(mark), 15, "the STOP on the wire")
        await wait_for(lambda: any("STOP sent" in m for m in _messages(hub)), 5, "the event")
        sent = next(m for m in _messages(hub) if "STOP sent" in m)
        assert "pressed at" in sent and "s ago" in sent, sent
