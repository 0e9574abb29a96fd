"""The demo autopilot: gentle repeating moves on axes nobody operates (``--autopilot``)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Protocol

from servotune.hub.records import AxisEntry
from servotune.link.base import Autopilot, DriverError
from servotune.schema import LinkState

logger = logging.getLogger(__name__)


class AutopilotGate(Protocol):
    """Who decides when the demo autopilot may drive an axis (``servotune.hub.control_lock``).

    Without a gate the autopilot stops for good the first time a user operates an axis.
    """

    def autopilot_paused(self, axis_id: str) -> None:
        """The autopilot stopped driving ``axis_id`` (someone operated it, or STOP)."""
        ...

    def autopilot_may_resume(self, axis_id: str) -> bool:
        """May the autopilot drive ``axis_id`` again now? True means it holds the axis."""
        ...


class AutopilotHost(Protocol):
    """What ``DemoAutopilot`` asks of the hub (``Hub``)."""

    @property
    def autopilot_gate(self) -> AutopilotGate | None: ...

    def link_state(self, link_id: str) -> LinkState:
        """The link's state as last published (not judged for staleness)."""
        ...

    def show_status(self, entry: AxisEntry) -> None:
        """Send every client the axis' status."""
        ...


class DemoAutopilot:
    """Drives one axis at a time in a task of its own (``run``), while nobody else
    operates it."""

    def __init__(self, host: AutopilotHost, clock: Callable[[], float]) -> None:
        self._host = host
        self._clock = clock

    async def run(self, entry: AxisEntry) -> None:
        """Gentle repeating moves while nobody else operates the axis (demo only).

        ``entry.operated`` means "the autopilot is not driving this axis now": a user
        change sets it. With an ``autopilot_gate`` (the control lock) the autopilot
        waits and resumes when the gate lets it; without one it stops for good.
        The moves come from the driver's ``autopilot_commands`` / ``autopilot_settled``
        (see ``link.base.Autopilot``); axes whose driver has none stay still.
        """
        driver = entry.driver
        if not isinstance(driver, Autopilot):
            return
        amplitude = driver.autopilot_amplitude()
        direction = 1
        paused = False
        while True:
            if entry.operated:
                gate = self._host.autopilot_gate
                if gate is None:
                    return
                if not paused:
                    paused = True
                    gate.autopilot_paused(entry.info.id)
                await asyncio.sleep(0.5)
                if entry.operated and gate.autopilot_may_resume(entry.info.id):
                    paused = False
                    entry.operated = False
                    self._host.show_status(entry)
                continue
            await asyncio.sleep(0.5)
            link_state = self._host.link_state(entry.link.id)
            sample = entry.latest
            if link_state != "connected" or entry.health == "offline" or sample is None:
                continue
            try:
                for name, args in driver.autopilot_commands(sample, direction * amplitude):
                    if entry.operated:
                        break
                    await driver.command(name, args)
                    await asyncio.sleep(0.05)
                direction = -direction
                deadline = self._clock() + 8.0
                await asyncio.sleep(0.3)
                while not entry.operated and self._clock() < deadline:
                    latest = entry.latest
                    if latest is not None and driver.autopilot_settled(latest):
                        break
                    await asyncio.sleep(0.05)
                await asyncio.sleep(0.8)
            except DriverError as exc:
                logger.info("autopilot on %s: %s", entry.info.id, exc)
                await asyncio.sleep(1.0)
